"""Volume-averaged Navier-Stokes gas solver: a node-based, time-staggered projection scheme (seed 001 §2.4.1).

Equations (seed 001 eqs 3-4, ρ constant, ε given at the nodes each step):

    ∂ε/∂t + ∇·(εu) = 0,
    ρ ∂(εu)/∂t + ρ ∇·(εu ⊗ u) = −∇P + ∇·(ε μ_eff ∇u) + ερg − K (u − v̄) + f.

Model choices (and why):

* **Everything at the nodes** (P1 / Q1 nodal values, like YALES2): the coupling projects and interpolates
  with the same node weights, and every constant operator is assembled ONCE with DOLFINx into CSR arrays
  (`febed.gas.operators`). A step is then a few Numba sparse-row sweeps, one Poisson solve with a constant
  AMG-preconditioned matrix, and ghost updates — no per-step assembly.
* **Unknown**: the superficial velocity q = εu (the conserved momentum per ρ); u = q/ε is output.
* **Predictor** (seed 001 eq 36, lumped mass ΔV_i = ∫φ_i): explicit forward Euler for convection
  (Galerkin nodal-product form, written skew-symmetrically: ½∇·(q⊗u) + ½u·∇q + ½q∇·u), viscosity
  (edge form of ∇·(εμ_eff∇u)) and the old pressure
  gradient, with the momentum exchange −K_i(u_i − v̄_i) *implicit and diagonal*:
  (ρ/Δt + K_i/ε_i^{n+1}) q*_i = ρ q_i^n/Δt + R_i/ΔV_i + K_i v̄_i + f_i. This is unconditionally stable in K
  (stiff drag, K Δt/ρε ≫ 1) and exact for the steady drag balance.
* **Convective stability**: forward Euler + central Galerkin convection is unstable (the FE step adds the
  anti-diffusion −Δt/2 (u·∇)²q). We add the Taylor-Galerkin / Lax-Wendroff streamline term
  ρ Δt/2 ∇·(ū ū·∇q), which cancels it exactly for linear convection: second order in time for convection,
  stable at CFL ≤ 0.2, and it vanishes as Δt → 0 without crosswind diffusion (switch: `taylor_galerkin`).
  The skew-symmetric convection keeps the nonlinear terms from feeding kinetic energy into grid modes:
  a nearly inviscid perturbed vortex (ν = 1e-6, 2000 steps at CFL 0.2) loses energy monotonically,
  while the conservative form with the same TG term blows up after ~1500 steps and plain FE at once.
* **Outlet backflow**: an outlet with a fixed pressure and a free velocity lets gas re-enter, carrying
  kinetic energy into the domain that nothing removes; when a plume reaches the outlet a vortex there
  grows until the step collapses (observed in the seed-000 bed from t ≈ 0.5 s: outlet speeds 2.5 m/s,
  then 25 m/s). Following Moghadam et al. (2011, Comput. Mech. 48) the outlet gets the traction
  β ρ/2 min(u·n, 0) u, which removes at least the convective energy influx for β ≥ 1 and is zero where
  gas leaves. At a node it is the force −c_i u_i, c_i = β ρ/2 max(−q_i·B_i, 0)/ΔV_i (B_i = ∫φ_i n ds),
  evaluated with q^n and added to the implicit diagonal like K (`backflow` = β, default 1; 0 = off).
* **Partial-slip walls** (`BoundarySpec.slip_length` λ): the Navier wall shear ε μ_eff u_t/λ on the lumped
  wall area a_i is the force −c_i u_i, c_i = ε_i μ_eff,i a_i/(λ ΔV_i), added to the implicit diagonal like K
  (so also to the pressure passes' and the drag-weighted projection's factor 1 + D_i); the normal velocity
  is removed as for a free slip (`febed.gas.boundary`).
* **Pressure** (seed 001 eqs 37-39, YALES2 form): the gas carries the full −∇P, so without drag the Poisson
  operator is the constant Laplacian L (with drag L_w, below); with φ = Δt δP/ρ,
  L φ = −(Dq* + ΔV (ε^{n+1} − ε^n)/Δt), D the Galerkin divergence. It includes the ∂ε/∂t source so that
  continuity holds node by node *in flux form*: Dq* + Lφ + ΔV Δε/Δt = 0 on every non-outlet node (to the
  KSP tolerance).
* **Correction**: q^{n+1} = q* − ΔV⁻¹ G φ (G the Galerkin gradient), P^{n+1} = P^n + ρφ/Δt. Using the
  compact L with the nodal gradient G is the classical approximate projection (no checkerboard modes);
  the nodal q^{n+1} is divergence-free only up to (L − D ΔV⁻¹ G)φ = O(Δt h² ∇⁴P).
* **Poisson tolerance**: with gas flowing in, the solve stops when ||r||_2 ≤ mass_tolerance · inflow / √N
  (N nodes), which *guarantees* |Σ r_i| ≤ mass_tolerance · inflow, i.e. the per-step mass balance below;
  it does not over-solve near steady states (warm start). Without inflow: ||r|| ≤ pressure_rtol ||b||.
* **Mass balance**: inflow is exact (U_f A, `febed.gas.boundary`); the outflow is the flux through the
  outlet faces of the outlet nodes' control volumes, ∮_out q*·n minus the correction flux
  Σ_out (Dq* + Lφ + ΔV Δε/Δt)_i. With these, inflow − outflow − d/dt∫ε dV equals the Poisson residual
  summed over the non-outlet nodes: it closes to the solver tolerance. `outflow_direct` = ∮_out q^{n+1}·n
  is also reported (it differs by the approximate-projection defect).
* **Drag and the pressure equation** (`drag_weighted_projection`, on by default): the predictor treats the drag
  implicitly, so the momentum equation's response to a pressure increment is divided by 1 + D_i,
  D_i = K_i Δt/(ρ ε_i). The projection carries the same factor: w_i = 1/(1 + D_i), the operator is the
  finite-element form of ∇·(w∇φ) with w averaged over each cell, L_w = Σ_c w_c K_c (`febed.gas.weighted`:
  symmetric positive semi-definite with zero row sums on every cell type, L for w = 1), and the correction is
  q = q* − w ΔV⁻¹ G φ. The step then ends with a pressure that balances this step's drag, with nothing lagged:
  this is the fixed point that repeated predictor-pressure passes would approach, reached by one solve to the
  Poisson tolerance (through a uniform porous channel Darcy's gradient is reached in one step,
  tests/gas/test_porous.py). L_w is assembled every step; CG on it is preconditioned by the AMG of L_w of a
  recent step, rebuilt when a solve needs more than `pressure.REFRESH_ITERATIONS` iterations (the weights
  it was built for are part of the state, so a restart rebuilds it bit for bit). Without it
  (`drag_weighted_projection = false`, the constant Laplacian) the pressure relaxes geometrically with ratio
  D/(1 + D) per step after any change of the drag: bounded, but at D ≈ 1-2 a bubbling bed's pressure trails
  its drag by most of a step. With `pressure_passes` = m > 1 the step repeats the predictor with the
  corrected pressure (only −∇p changed: q* −= G φ/(ΔV (1 + D)), no new convection or viscous terms) and
  solves the Poisson equation again, m times in all: the plain projection's lag becomes (D/(1 + D))^m per
  step. The mass balance below holds for the last pass.
* **The pressure's share** (`step(..., pressure_share=s)`, with the drag-weighted projection): the momentum
  carries s_i times this step's pressure change, −s_i ∇(p^{n+1} − p^n), with −∇p^n in the predictor and the
  rest of the old gradient, (1 − s_i)∇p^n, in `force`. The projection takes s into its weights
  (w_i = s_i/(1 + D_i) in L_w and in the correction), so the step ends with −s_i ∇p^{n+1} in the balance and
  nothing lagged. The coupled solver's nodal pressure-gradient reaction gives s = ε (the gas carries
  −ε∇p, model A). Passing (1 − ε)∇p^n in `force` alone would leave the share of the new gradient behind:
  after a change, the pressure would approach its balance by a factor 1 − ε per step (0.55 in a packed bed),
  one step's lag at the default gas step. With the constant Laplacian (`drag_weighted_projection = false`)
  s is not used: the operator cannot carry it.
* **LES**: Smagorinsky ν_t = (C_s Δ)² |S|, Δ = (mean volume of the cells around the node)^(1/d),
  |S| from the lumped nodal velocity gradient (switch `les`).
* **Convective sub-steps** (`convection_substeps` = k, default 1): the predictor is made of m ≤ k explicit
  sub-steps of Δt/m (each the predictor above: convection, viscosity, Taylor-Galerkin term at Δt/m, the
  old pressure gradient, the implicit drag), from q^n to q*, before one pressure solve and correction over
  Δt. m is the fewest sub-steps that keep CFL ≤ `cfl` and Fourier ≤ `fourier`:
  m = min(k, ⌈max(CFL/`cfl`, Fourier/`fourier`)⌉) with the numbers of the whole step at its start
  (`StepInfo.substeps`). So the gas step, the pressure solve and the coupling (the DEM sub-steps between
  two gas steps) take up to k times the convective step, and a step that `dt_max` holds below the
  convective step is one plain predictor (the arithmetic of k = 1). Sub-cycling the explicit part of a
  projection step is the idea of operator-integration-factor splitting (Maday, Patera and Rønquist 1990,
  J. Sci. Comput. 5); here each sub-step is the whole explicit predictor, with the step's pressure gradient
  and drag held, and the projection ends the step. The drag-weighted projection uses the sub-stepped
  predictor's response to a pressure gradient held through the sub-steps,
  w = (1/m) Σ_{j=1..m} (1 + D/m)^-j (1/(1 + D) for m = 1), so a steady drag balance is still reached in one
  step; the convection of the later sub-steps does not see the correction (first order, as the rest).
* **Time step**: CFL = max |u| Δt/Δ ≤ k `cfl`, Fourier = max ν_eff Δt/Δ² ≤ k `fourier`, within [dt_min, dt_max];
  optionally the drag number max K Δt/(ρ ε) ≤ `drag_number` (K of the previous step). In a packed bed of
  1 mm glass beads K/(ρε) is 3,000-10,000 /s: dt_max = 2e-4 s gives D ≈ 1-2.
* Temporal accuracy is first order overall (explicit viscous term, incremental pressure); spatial accuracy
  is second order on smooth meshes (tests/gas).
* The viscous term keeps ∇·(εμ∇u) and drops the transpose part ∇·(εμ∇uᵀ) (zero for constant ε and
  divergence-free u).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import ClassVar

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx.fem
import numpy as np

from febed.gas import kernels
from febed.gas.boundary import BoundarySpec, NodalBoundary
from febed.gas.operators import build_operators, nodal_family
from febed.gas.pressure import PressureSolver
from febed.schema import check_fields, schema_field


@dataclass
class VANSParameters:
    """Plain parameters of the gas solver (SI units); `VANSSolver.from_case` fills them from a case.

    Each field but `NOT_IN_CASE`'s is the case key `gas.<field>` (`gravity`: `run.gravity`), whose default and
    allowed range in `febed/schema.py` are the field's (see the module docstring for what they do).
    """

    # fields that are no single case key, and why
    NOT_IN_CASE: ClassVar[dict[str, str]] = {
        "boundaries": "built from the [gas.boundary.<tag>] tables (each checked by BoundarySpec.validate)",
        "prefix": "the PETSc options prefix of the solver's own solves",
    }

    density: float = schema_field("gas.density")
    viscosity: float = schema_field("gas.viscosity")
    les: str = schema_field("gas.les")
    smagorinsky_cs: float = schema_field("gas.smagorinsky_cs")
    cfl: float = schema_field("gas.cfl")
    fourier: float = schema_field("gas.fourier")
    dt_min: float = schema_field("gas.dt_min")
    dt_max: float = schema_field("gas.dt_max")
    drag_number: float = schema_field("gas.drag_number")  # largest K Δt/(ρ ε) of a step (0: no limit), "Time step"
    pressure_passes: int = schema_field("gas.pressure_passes")  # see "Drag and the pressure equation"
    convection_substeps: int = schema_field("gas.convection_substeps")  # see "Convective sub-steps"
    drag_weighted_projection: bool = schema_field("gas.drag_weighted_projection")  # operator weighted 1/(1+KΔt/(ρε))
    gravity: float = schema_field("run.gravity")  # magnitude [m/s^2], along -z (3D) / -y (2D)
    boundaries: dict[str, BoundarySpec] = field(default_factory=dict)
    taylor_galerkin: bool = schema_field("gas.taylor_galerkin")
    pressure_rtol: float = schema_field("gas.pressure_rtol")  # Poisson tolerance relative to ||b|| without inflow
    mass_tolerance: float = schema_field("gas.mass_tolerance")  # with inflow: |mass imbalance| <= this x inflow
    backflow: float = schema_field("gas.backflow")  # β of the outlet backflow stabilisation (0 switches it off)
    prefix: str = "febed_"

    def validate(self) -> None:
        """Raise ValueError naming the first bad parameter and what is allowed (the ranges of `febed/schema.py`)."""
        check_fields(self)
        if self.dt_min > self.dt_max:
            raise ValueError(f"VANSParameters.dt_min ({self.dt_min}) must not exceed dt_max ({self.dt_max})")


def apply_petsc_options(text: str) -> None:
    """Insert `-key value` pairs (e.g. "-febed_pressure_pc_type gamg") into the PETSc options database."""
    from petsc4py import PETSc

    tokens = text.split()
    opts = PETSc.Options()
    i = 0
    while i < len(tokens):
        key = tokens[i]
        if not key.startswith("-"):
            raise ValueError(f"gas.petsc_options: expected '-option value' pairs, got {key!r} in {text!r}")
        value = tokens[i + 1] if i + 1 < len(tokens) and not tokens[i + 1].startswith("-") else None
        opts[key.lstrip("-")] = "" if value is None else value
        i += 1 if value is None else 2


@dataclass
class StepInfo:
    """What one gas step did. Flows in m^3/s (m^2/s in 2D); mass imbalance in kg/s."""

    t: float
    dt: float
    cfl: float
    fourier: float
    poisson_iterations: int
    inflow: float
    outflow: float
    outflow_direct: float
    storage_rate: float  # d/dt ∫ ε dV
    mass_imbalance: float  # ρ (inflow − outflow − storage_rate)
    timings: dict[str, float]
    # explicit predictor sub-steps (more than 1 only with gas.convection_substeps > 1 and a CFL-limited step)
    substeps: int = 1


class VANSSolver:
    """Node-based VANS projection solver (see the module docstring for the scheme).

    Interface for the coupled loop (stable):

    * `VANSSolver(mesh_data, params, eps=1.0)` or `VANSSolver.from_case(case, mesh_data)`.
    * `Q`: the scalar nodal space (P1/Q1). Every nodal array is indexed by its local dofs, owned first
      (`n_owned`), then ghosts (`n_local` in all); `x` holds the node coordinates (n_local, 3).
    * `step(dt, eps=None, K=None, Kv=None, force=None, pressure_share=None) -> StepInfo` advances t → t + dt
      with `eps` = ε^{n+1} (n_local,) (ε^n is kept; None keeps ε), `K` the momentum-exchange coefficient
      [kg/(m^3 s)] (n_local,) or scalar, `Kv` = K·v̄ [kg/(m^2 s^2)] (n_local, gdim), `force` an explicit
      force density [N/m^3] (n_local, gdim), `pressure_share` s_i the share of this step's pressure change
      the momentum carries (default 1; see "The pressure's share"). Arrays of length n_owned are accepted too.
    * Outputs (read-only views, n_local rows): `u` interstitial velocity (n, gdim) [m/s], `q` = εu,
      `p` [Pa], `grad_p` (lumped L2 projection) [Pa/m], `eps`, `node_volume` = ∫φ_i dx [m^3].
    * `compute_dt()` from CFL/Fourier within [dt_min, dt_max]; `t` the current time; `functions()` the
      DOLFINx Functions (u, p, eps) for output; `effective_viscosity()` μ + ρν_t at the nodes.
    * Initial conditions: `set_void_fraction(eps)` (no ∂ε/∂t source), `set_pressure(p)`, and `q[:] = ...`
      (superficial velocity; boundary values are imposed at the next step).
    * `StepInfo`: t, dt, cfl, fourier, poisson_iterations, inflow / outflow / outflow_direct /
      storage_rate [m^3/s], mass_imbalance [kg/s] = ρ(inflow − outflow − storage_rate), timings [s].
    * PETSc options prefix of the pressure solve: `<prefix>pressure_` (default `febed_pressure_`).
    """

    def __init__(self, mesh_data, params: VANSParameters, eps: float | np.ndarray = 1.0):
        params.validate()
        self.params, self.comm = params, mesh_data.comm
        mesh = mesh_data.mesh
        # --- constant operators and boundary conditions (assembled once)
        self.ops = build_operators(mesh)
        self.Q, self.gdim = self.ops.Q, self.ops.gdim
        self.n_owned, self.n_local = self.ops.n_owned, self.ops.n_local
        self.V = dolfinx.fem.VectorFunctionSpace(mesh, (self._family(), 1))
        if not np.array_equal(self.V.dofmap.list.array, self.Q.dofmap.list.array):
            raise RuntimeError("vector and scalar nodal spaces do not share one node numbering")
        self.bc = NodalBoundary(mesh_data, self.ops, params.boundaries)
        self.x = self.Q.tabulate_dof_coordinates()
        self.g = np.zeros(self.gdim)
        self.g[-1] = -params.gravity
        # --- state at the nodes: Functions give ghost updates and XDMF output
        self._u = dolfinx.fem.Function(self.V, name="u")
        self._q = dolfinx.fem.Function(self.V, name="q")
        self._gradp = dolfinx.fem.Function(self.V, name="grad_p")
        self._p = dolfinx.fem.Function(self.Q, name="p")
        self._eps = dolfinx.fem.Function(self.Q, name="eps")
        self._nu = dolfinx.fem.Function(self.Q, name="nu")
        self._eps.x.array[:] = self._local(eps, "eps", scalar_ok=True)
        self._check_eps(self._eps.x.array)
        self.t = 0.0
        self.gp_owned = np.zeros((self.n_owned, self.gdim))  # Σ_j G_ij p_j (Galerkin)
        self._rhs = np.zeros((self.n_owned, self.gdim))
        self._div = np.zeros(self.n_owned)
        self._b = np.zeros(self.n_owned)
        self._g_phi = np.zeros((self.n_owned, self.gdim))
        self._p.x.array[:] = float(np.mean(self.bc.pressure_values)) if self.bc.pressure_values.size else 0.0
        self._p.x.array[self.bc.pressure_dofs] = self.bc.pressure_values
        self._p.x.scatter_forward()
        kernels.gradient(self.ops.indptr, self.ops.indices, self.ops.grad, self._ext("p", self._p), self.gp_owned)
        self.bc.apply_velocity(self.q, 0.0)
        self._q.x.scatter_forward()
        self._update_u()
        # --- pressure solver: constant Laplacian, AMG set up once
        self.pressure = PressureSolver(
            self.Q, self.bc.pressure_dofs, self.bc.has_outlet, params.prefix + "pressure_",
            weighted=params.drag_weighted_projection,
        )  # fmt: skip
        self._weights = dolfinx.fem.Function(self.Q)  # s/(1 + K Δt/(ρ ε)) of the step (drag-weighted projection)
        self._share = None  # the pressure's share s of the step (owned nodes), None: 1
        self._weighted = False  # this step's projection is drag-weighted (a drag K was given)
        self._wall_c = None  # the walls' implicit shear coefficient of the step [kg/(m^3 s)] (None: no such walls)
        self._substeps = 1  # the step's explicit predictor sub-steps (`_substeps_for`)
        self._outlet_rows = self.bc.pressure_dofs[self.bc.pressure_dofs < self.n_owned]
        self._backflow_c = np.empty(self._outlet_rows.size)  # `_with_backflow` scratch
        self._sqrt_n = np.sqrt(self.comm.allreduce(self.n_owned, op=MPI.SUM))
        self.phi = np.zeros(self.n_local)
        self._mu_cache = (None, None)
        self._rates_cache = (None, None)
        h2 = float(np.min(self.ops.width[: self.n_owned] ** 2, initial=np.inf))
        self._h2_min = self.comm.allreduce(h2, op=MPI.MIN)
        self._drag_rates = np.zeros(self.n_owned)  # K/(ρ ε) of the last step per owned node [1/s] (drag number)

    # ------------------------------------------------------------------------------------------ setup
    def _family(self) -> str:
        return nodal_family(self.Q.mesh)

    @classmethod
    def from_case(cls, case, mesh_data, eps: float | np.ndarray | None = None) -> VANSSolver:
        """Build the solver from a validated case (`case.gas`, `case.boundary`, `case.run.gravity`)."""
        g = case.gas
        specs = {}
        for name, b in case.boundary.items():
            d = b.as_dict()
            specs[name] = BoundarySpec(
                type=d["type"],
                velocity=d.get("velocity"),
                ramp_time=d.get("ramp_time", 0.0),
                slip=d.get("slip", False),
                pressure=d.get("pressure", 0.0),
                cross_section_tags=tuple(d.get("cross_section_tags", ()) or ()),
                slip_normals=tuple(d.get("slip_normals", ()) or ()),
                slip_length=d.get("slip_length"),
                wins_over=tuple(d.get("wins_over", ()) or ()),
                wall_law=d.get("wall_law", "brinkman"),
            )
        apply_petsc_options(g.petsc_options)
        params = VANSParameters(
            taylor_galerkin=g.taylor_galerkin,
            backflow=g.backflow,
            mass_tolerance=g.mass_tolerance,
            pressure_rtol=g.pressure_rtol,
            density=g.density,
            viscosity=g.viscosity,
            les=g.les,
            smagorinsky_cs=g.smagorinsky_cs,
            cfl=g.cfl,
            fourier=g.fourier,
            dt_min=g.dt_min,
            dt_max=g.dt_max,
            drag_number=g.drag_number,
            pressure_passes=g.pressure_passes,
            convection_substeps=g.convection_substeps,
            drag_weighted_projection=g.drag_weighted_projection,
            gravity=case.run.gravity,
            boundaries=specs,
        )
        return cls(mesh_data, params, g.void_fraction if eps is None else eps)

    def _local(self, a, name: str, scalar_ok: bool = False, vector: bool = False) -> np.ndarray:
        """Validate an input nodal array (n_owned or n_local rows) and return it over the local dofs."""
        shape_tail = (self.gdim,) if vector else ()
        if np.isscalar(a):
            if not scalar_ok:
                raise ValueError(f"{name} must be a nodal array of shape (n_local{', gdim' if vector else ''})")
            return np.full((self.n_local, *shape_tail), float(a))
        a = np.asarray(a, dtype=np.float64)
        if a.shape[1:] != shape_tail or a.shape[0] not in (self.n_owned, self.n_local):
            raise ValueError(
                f"{name} has shape {a.shape}; expected ({self.n_owned} or {self.n_local}"
                f"{', ' + str(self.gdim) if vector else ''}) (owned or owned + ghost nodes)"
            )
        if a.shape[0] == self.n_local:
            return a
        f = self._scratch_vector if vector else self._scratch_scalar
        f.x.array.reshape(self.n_local, -1)[: self.n_owned] = a.reshape(self.n_owned, -1)
        f.x.scatter_forward()
        return f.x.array.reshape((self.n_local, *shape_tail)).copy()

    @property
    def _scratch_scalar(self):
        if not hasattr(self, "_s1"):
            self._s1 = dolfinx.fem.Function(self.Q)
        return self._s1

    @property
    def _scratch_vector(self):
        if not hasattr(self, "_s2"):
            self._s2 = dolfinx.fem.Function(self.V)
        return self._s2

    def set_void_fraction(self, eps: float | np.ndarray) -> None:
        """Set ε at the current time (initial condition; no ∂ε/∂t source): scalar or nodal array."""
        e = self._local(eps, "eps", scalar_ok=True)
        self._check_eps(e)
        self.eps[:] = e
        self._update_u()
        self._mu_cache = (None, None)
        self._rates_cache = (None, None)

    def set_pressure(self, p: float | np.ndarray) -> None:
        """Set the pressure field (initial condition) [Pa]; outlet nodes keep their prescribed value."""
        self.p[:] = self._local(p, "p", scalar_ok=True)
        self.p[self.bc.pressure_dofs] = self.bc.pressure_values
        kernels.gradient(self.ops.indptr, self.ops.indices, self.ops.grad, self._ext("p", self._p), self.gp_owned)
        self.grad_p[: self.n_owned] = self.gp_owned / self.ops.mass[: self.n_owned, None]
        self._gradp.x.scatter_forward()

    def _check_eps(self, eps: np.ndarray) -> None:
        e = eps[: self.n_owned]
        if e.size and not (e.min() > 0.0 and e.max() <= 1.0):  # a NaN fails both
            raise ValueError("eps (void fraction) must lie in (0, 1] at every node")

    # ------------------------------------------------------------------------------------ checkpoint
    def get_state(self) -> dict[str, np.ndarray]:
        """Everything the next step reads, over the owned nodes: q, p, ε, ∇p, Gp, the last increment φ (and K/(ρε))."""
        n = self.n_owned
        return {
            "q": self.q[:n].copy(),
            "p": self.p[:n].copy(),
            "eps": self.eps[:n].copy(),
            "grad_p": self.grad_p[:n].copy(),
            "gp": self.gp_owned.copy(),
            "phi": self.pressure.x.array[:n].copy(),  # the warm start of the next pressure solve
            **({"drag_rate": self._drag_rates.copy()} if self.params.drag_number > 0.0 else {}),  # next step's limit
            **self.pressure.preconditioner_state(),  # the weighted solve's preconditioner, once built
        }

    def set_state(self, state: dict[str, np.ndarray], t: float) -> None:
        """Restore `get_state()` arrays (owned rows, in this rank's node order) at time t [s]."""
        n = self.n_owned
        for name, f in (("q", self._q), ("p", self._p), ("eps", self._eps), ("grad_p", self._gradp)):
            f.x.array.reshape(self.n_local, -1)[:n] = np.asarray(state[name]).reshape(n, -1)
            f.x.scatter_forward()
        self.gp_owned[:] = state["gp"]
        if "drag_rate" in state:  # the drag-number limit of the next step (absent: no limit for one step)
            self._drag_rates = np.asarray(state["drag_rate"], dtype=float).reshape(n).copy()
        if self.pressure.weighted is not None:  # the preconditioner the next weighted solve would have used
            self.pressure.pc_weights = self.pressure.interp_weights = None  # none saved: built at the next solve
            self.pressure.fresh_reuse = False
            if "pc_weights" in state:
                w, interp = self._local(state["pc_weights"], "pc_weights"), None
                if "pc_interp_weights" in state:  # refreshed keeping the interpolation of this full build
                    interp = self._local(state["pc_interp_weights"], "pc_interp_weights")
                self.pressure.restore_preconditioner(w, interp, fresh="pc_fresh" in state)
        self.pressure.x.array[:] = state["phi"]
        self.pressure.x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        self.t = float(t)
        self._update_u()
        self._mu_cache = (None, None)
        self._rates_cache = (None, None)

    # --------------------------------------------------------------------------------------- outputs
    @property
    def q(self) -> np.ndarray:
        """Superficial velocity εu at the nodes (n_local, gdim) [m/s]."""
        return self._q.x.array.reshape(-1, self.gdim)

    @property
    def u(self) -> np.ndarray:
        """Interstitial gas velocity at the nodes (n_local, gdim) [m/s]."""
        return self._u.x.array.reshape(-1, self.gdim)

    @property
    def p(self) -> np.ndarray:
        """Dynamic pressure at the nodes (n_local,) [Pa]."""
        return self._p.x.array

    @property
    def grad_p(self) -> np.ndarray:
        """Nodal pressure gradient, lumped L2 projection ΔV⁻¹ G p (n_local, gdim) [Pa/m]."""
        return self._gradp.x.array.reshape(-1, self.gdim)

    @property
    def eps(self) -> np.ndarray:
        """Void fraction at the nodes (n_local,)."""
        return self._eps.x.array

    @property
    def node_volume(self) -> np.ndarray:
        """Node control volumes ∫φ_i dx (n_local,) [m^3] (m^2 in 2D)."""
        return self.ops.mass

    def functions(self) -> dict[str, dolfinx.fem.Function]:
        """The DOLFINx Functions written to XDMF: u, p, eps."""
        return {"u": self._u, "p": self._p, "eps": self._eps}

    def _update_u(self) -> None:
        kernels.divide_rows(self.q, self.eps, self.u)

    def _ext(self, name: str, f: dolfinx.fem.Function) -> np.ndarray:
        """Values of a Function at the owned, ghost and extra column nodes of the sweeps (up to date ghosts)."""
        return self.ops.extension.extend(name, f.vector, f.x.array)

    # ---------------------------------------------------------------------------------- time step
    def effective_viscosity(self) -> np.ndarray:
        """Effective dynamic viscosity μ + ρ ν_t at the nodes (n_local,) [Pa s] (LES: Smagorinsky)."""
        return self._viscosity()[: self.n_local].copy()

    def _viscosity(self) -> np.ndarray:
        """μ + ρ ν_t [Pa s] over the extended nodes (computed once per time level)."""
        if self._mu_cache[0] == self.t:
            return self._mu_cache[1]
        par, ops = self.params, self.ops
        if par.les == "smagorinsky":
            s = np.zeros(self.n_owned)
            kernels.strain_rate_norm(ops.indptr, ops.indices, ops.grad, self._ext("u", self._u), ops.mass, s)
            self._nu.x.array[: self.n_owned] = (par.smagorinsky_cs * ops.width[: self.n_owned]) ** 2 * s
            self._nu.x.scatter_forward()
            mu = par.viscosity + par.density * self._ext("nu_t", self._nu)
        else:
            mu = np.full(ops.n_ext, par.viscosity)
        self._mu_cache = (self.t, mu)
        return mu

    def compute_dt(self) -> float:
        """Largest Δt with CFL ≤ cfl, Fourier ≤ fourier (and drag number ≤ drag_number), in [dt_min, dt_max] [s]."""
        par = self.params
        rate_c, rate_f = self._rates()
        k = par.convection_substeps  # each explicit sub-step within the limits
        dt = min(k * par.cfl / max(rate_c, 1e-300), k * par.fourier / max(rate_f, 1e-300))
        if par.drag_number > 0.0:
            rate_d = self.comm.allreduce(float(np.max(self._drag_rates, initial=0.0)), op=MPI.MAX)
            dt = min(dt, par.drag_number / max(rate_d, 1e-300))
        return float(min(max(dt, par.dt_min), par.dt_max))

    def _rates(self) -> tuple[float, float]:
        """Global max |u|/Δ and max ν_eff/Δ² [1/s]: CFL and Fourier numbers per unit Δt.

        Computed once per time level, like the viscosity: the end of a step and the next `compute_dt` share it.
        """
        if self._rates_cache[0] == self.t:
            return self._rates_cache[1]
        self._rates_cache = (self.t, self._global_rates())
        return self._rates_cache[1]

    def _global_rates(self) -> tuple[float, float]:
        n = self.n_owned
        mu = self._viscosity()
        rate_c, mu_h2 = kernels.max_rates(self.u, mu, self.ops.width, n)
        if self.params.les == "none":
            rate_f = self.params.viscosity / self.params.density / self._h2_min
            return self.comm.allreduce(rate_c, op=MPI.MAX), rate_f
        rate_f = mu_h2 / self.params.density
        buf = np.array([rate_c, rate_f])
        self.comm.Allreduce(MPI.IN_PLACE, buf, op=MPI.MAX)
        return float(buf[0]), float(buf[1])

    # ------------------------------------------------------------------------------------------- step
    def step(self, dt: float, eps=None, K=None, Kv=None, force=None, pressure_share=None) -> StepInfo:
        """Advance the gas from t to t + dt: predictor → pressure → correction (seed 001 eqs 35-39)."""
        if not dt > 0.0:
            raise ValueError(f"dt must be > 0, got {dt!r}")
        clock = {}
        t0 = time.perf_counter()
        eps_old = self._ext("eps", self._eps).copy()
        if eps is not None:
            e = self._local(eps, "eps", scalar_ok=True)
            self._check_eps(e)
            self.eps[:] = e
        self._weighted = self.params.drag_weighted_projection and K is not None
        K = self._local(0.0 if K is None else K, "K", scalar_ok=True)
        Kv = self._local(0.0 if Kv is None else Kv, "Kv", scalar_ok=True, vector=True)
        force = self._local(0.0 if force is None else force, "force", scalar_ok=True, vector=True)
        share = None
        if pressure_share is not None and self._weighted:
            share = self._local(pressure_share, "pressure_share", scalar_ok=True)[: self.n_owned]
            if not np.all((share > 0.0) & (share <= 1.0 + 1e-9)):  # ε from the coupling: 1 to round-off at most
                raise ValueError("pressure_share must lie in (0, 1] at every node")
        self._share = share
        if self.params.drag_number > 0.0:
            n = self.n_owned
            self._drag_rates = K[:n] / (self.params.density * self.eps[:n])
        clock["inputs"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        self._wall_c = None
        if self.bc.has_wall_friction:  # wall-law and partial-slip walls: their shear is implicit like the drag
            n = self.n_local
            eps_mu = self.eps * self._viscosity()[:n]
            if self.bc.has_inlet_corners:  # inlet corners slide as the wall-law walls beside them (gas.boundary)
                self.bc.set_wall_state(K, eps_mu)
            K_wall = self.bc.wall_friction(K, eps_mu, self.ops.mass[:n])
            self._wall_c, K = K_wall - K, K_wall
        q_star = self._predict(dt, eps_old, K, Kv, force)
        clock["predictor"] = time.perf_counter() - t0

        clock["pressure"] = clock["correction"] = 0.0
        iterations = 0
        for k in range(self.params.pressure_passes):
            t0 = time.perf_counter()
            if k > 0 and self._substeps > 1:  # the sub-stepped predictor's response to G φ
                n = self.n_owned
                r = self._response(K[:n], dt) if share is None else share * self._response(K[:n], dt)
                q_star[:n] -= (r / self.ops.mass[:n])[:, None] * self._g_phi
            elif k > 0:  # the predictor again, with the pressure the last pass corrected
                n = self.n_owned
                if self._weighted:  # the share of a pressure change the predictor passes on: w_i = s_i/(1 + D_i)
                    c = self._weights.x.array[:n]
                else:
                    c = 1.0 / (1.0 + K[:n] * dt / (self.params.density * self.eps[:n]))
                kernels.repredict(q_star, self._g_phi, self.ops.mass, c)
            if k > 0:
                self.bc.apply_velocity(q_star, self.t + dt)
                self._scratch_vector.x.scatter_forward()
            its, flux = self._solve_pressure(dt, eps_old, q_star)
            iterations += its
            t1 = time.perf_counter()
            self._correct(dt, q_star)
            clock["pressure"] += t1 - t0
            clock["correction"] += time.perf_counter() - t1

        self.t += dt
        rate_c, rate_f = self._rates()
        cfl, fo = rate_c * dt, rate_f * dt
        inflow, outflow, _, storage = flux
        q_flux = float(np.einsum("ij,ij->", self.ops.bnormal[: self.n_owned], self.q[: self.n_owned]))
        outflow_direct = self.comm.allreduce(q_flux, op=MPI.SUM) + inflow
        return StepInfo(
            t=self.t,
            dt=dt,
            cfl=cfl,
            fourier=fo,
            poisson_iterations=iterations,
            substeps=self._substeps,
            inflow=inflow,
            outflow=outflow,
            outflow_direct=outflow_direct,
            storage_rate=storage,
            mass_imbalance=self.params.density * (inflow - outflow - storage),
            timings=clock,
        )

    def _predict(self, dt, eps_old, K, Kv, force) -> np.ndarray:
        """Velocity predictor (seed 001 eq 36) with implicit diagonal momentum exchange; q* (n_local, gdim)."""
        par, ops = self.params, self.ops
        nu = eps_old * self._viscosity()
        q_star = self._scratch_vector.x.array.reshape(-1, self.gdim)
        self._substeps = self._substeps_for(dt)
        k = self._substeps
        if k > 1:
            K = self._with_backflow(K)
            self._predict_substeps(dt, nu, K, Kv, force, q_star)
        else:
            hdt = 0.5 * dt if par.taylor_galerkin else 0.0
            q, u = self._ext("q", self._q), self._ext("u", self._u)
            kernels.momentum_rhs(ops.edges, q, u, self.gp_owned, nu, par.density, hdt, self._rhs)
            K = self._with_backflow(K)
            kernels.predictor_update(
                self.q, self._rhs, ops.mass, self.eps, K, Kv, force, self.g, par.density, dt, q_star[: self.n_owned]
            )
        w = self._weights.x.array
        if self._weighted:  # the predictor's implicit diagonal ρ/Δt + K/ε, relative to ρ/Δt
            n = self.n_owned
            w[:n] = self._response(K[:n], dt) if k > 1 else 1.0 / (1.0 + K[:n] * dt / (par.density * self.eps[:n]))
            if self._share is not None:  # the momentum carries s_i of the pressure change
                w[:n] *= self._share
            self._weights.x.scatter_forward()
            self.pressure.set_weights(w)
        elif self._wall_c is not None:  # the walls' implicit shear also damps their nodes' correction
            wall = self._wall_c
            w[:] = self._response(wall, dt) if k > 1 else 1.0 / (1.0 + wall * dt / (par.density * self.eps))
        else:
            w[:] = 1.0
        self.bc.apply_velocity(q_star, self.t + dt)
        self._scratch_vector.x.scatter_forward()
        return q_star

    def _substeps_for(self, dt: float) -> int:
        """The step's explicit sub-steps: the fewest, up to `convection_substeps`, within `cfl` and `fourier`.

        Collective: from the rates at the step's start; 1 without sub-steps (no reduction then). A step that
        `compute_dt` made k convective steps long gives k (the ratio is k up to round-off, taken off before the
        ceiling).
        """
        k = self.params.convection_substeps
        if k == 1:
            return 1
        rate_c, rate_f = self._rates()
        need = dt * max(rate_c / self.params.cfl, rate_f / self.params.fourier)
        return int(min(k, max(1, math.ceil(need * (1.0 - 1e-9)))))

    def _predict_substeps(self, dt, nu, K, Kv, force, q_star) -> None:
        """The predictor as `_substeps` explicit sub-steps of dt/m into q_star (see "Convective sub-steps").

        Each sub-step is the one-step predictor over dt/m from the last sub-step's velocity (u = q/ε^{n+1}
        after the first), with the old pressure gradient, this step's K, K v̄ and force, and the velocity
        boundary conditions at its end time.
        """
        par, ops, n = self.params, self.ops, self.n_owned
        k = self._substeps
        sub = dt / k
        hdt = 0.5 * sub if par.taylor_galerkin else 0.0
        q, u = self._ext("q", self._q), self._ext("u", self._u)
        eps = self._ext("eps", self._eps)
        q_m = self.q[:n].copy()
        for m in range(k):
            kernels.momentum_rhs(ops.edges, q, u, self.gp_owned, nu, par.density, hdt, self._rhs)
            kernels.predictor_update(
                q_m, self._rhs, ops.mass, self.eps, K, Kv, force, self.g, par.density, sub, q_star[:n]
            )
            self.bc.apply_velocity(q_star, self.t + (m + 1) * sub)
            self._scratch_vector.x.scatter_forward()
            if m + 1 < k:
                q_m[:] = q_star[:n]
                q = self._ext("q_sub", self._scratch_vector)
                u = q / eps[:, None]

    def _response(self, c: np.ndarray, dt: float) -> np.ndarray:
        """How much of a pressure-gradient change the predictor passes on, per node, with the implicit coefficient c.

        One step: 1/(1 + D), D = c Δt/(ρ ε). With k sub-steps (the step's `_substeps`) each damped by
        a = 1/(1 + D/k), a gradient held through them moves q by (Δt/ρ) (1/k) Σ_{m=1..k} a^m of it.
        """
        k = self._substeps
        a = 1.0 / (1.0 + c * (dt / k) / (self.params.density * self.eps[: c.shape[0]]))
        power = np.ones_like(a)
        total = np.zeros_like(a)
        for _ in range(k):
            power *= a
            total += power
        return total / k

    def _with_backflow(self, K: np.ndarray) -> np.ndarray:
        """K plus the outlet backflow coefficient c_i = β ρ/2 max(−q_i·B_i, 0)/ΔV_i at outlet nodes.

        The force −c_i u_i is the nodal form of the traction β ρ/2 min(u·n, 0) u on the outlet (Moghadam
        et al. 2011 style backflow stabilisation); see the module docstring.
        """
        rows = self._outlet_rows
        if self.params.backflow == 0.0 or rows.size == 0:
            return K
        c = self._backflow_c
        coef = 0.5 * self.params.backflow * self.params.density
        if not kernels.backflow_coefficients(rows, self.ops.bnormal, self.q, self.ops.mass, coef, c):
            return K
        K = K.copy()
        K[rows] += c
        return K

    def _solve_pressure(self, dt, eps_old, q_star) -> tuple[int, tuple[float, float, float, float]]:
        """Poisson equation for φ = Δt δP/ρ (seed 001 eq 39) and the pressure update; mass balance."""
        par, ops, n = self.params, self.ops, self.n_owned
        kernels.divergence(ops.indptr, ops.indices, ops.grad, self._ext("q*", self._scratch_vector), self._div)
        storage_sum = kernels.pressure_rhs(self._div, ops.mass, self.eps, eps_old, dt, self._b)
        inflow = self.bc.inflow(self.t + dt)
        if inflow > 0.0:  # |Σ_i r_i| <= sqrt(N) ||r||_2 <= mass_tolerance * inflow
            rtol, atol = 1e-14, par.mass_tolerance * inflow / self._sqrt_n
        else:
            rtol, atol = par.pressure_rtol, 1e-300
        total_flux = float(np.einsum("ij,ij->", ops.bnormal[:n], q_star[:n]))
        c = self.comm
        buf = np.array([total_flux, storage_sum])
        c.Allreduce(MPI.IN_PLACE, buf, op=MPI.SUM)
        flux, storage_rate = float(buf[0]), float(buf[1])
        iterations = 0
        for _ in range(4):
            self.phi, its = self.pressure.solve(self._b, rtol, atol, weighted=self._weighted)
            self.phi_ext = self.ops.extension.extend("phi", self.pressure.x, self.phi)
            iterations += its
            # mass balance: exact inflow; outflow through the outlet faces of the outlet control volumes
            if self._weighted:  # the outlet rows of L_w φ (unmodified rows)
                flux_corr = float(np.sum(self.pressure.weighted.pressure_rows_product(self.phi)[self._outlet_rows]))
            else:
                flux_corr = kernels.rows_dot(ops.indptr, ops.indices, ops.laplacian, self._outlet_rows, self.phi_ext)
            corr = c.allreduce(flux_corr - float(np.sum(self._b[self._outlet_rows])))
            outflow = flux - corr + inflow
            # safety net: CG's recursive residual may drift from the true one; tighten and continue if so
            if inflow <= 0.0 or abs(inflow - outflow - storage_rate) <= par.mass_tolerance * inflow:
                break
            atol *= 0.1
        self._p.x.array[:] += par.density / dt * self.phi
        self._p.x.array[self.bc.pressure_dofs] = self.bc.pressure_values
        return iterations, (inflow, outflow, None, storage_rate)

    def _correct(self, dt, q_star) -> None:
        """Velocity correction (seed 001 eq 37): q = q* − ΔV⁻¹ G φ, then the boundary conditions."""
        par, ops = self.params, self.ops
        kernels.gradient(ops.indptr, ops.indices, ops.grad, self.phi_ext, self._g_phi)
        w = self._weights.x.array
        kernels.correct(q_star, self._g_phi, ops.mass, w, par.density / dt, self.gp_owned, self.q, self.grad_p)
        self.bc.apply_velocity(self.q, self.t + dt)
        self._q.x.scatter_forward()
        self._update_u()
        self._gradp.x.scatter_forward()
