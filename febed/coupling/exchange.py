"""Coupling steps for the time loop (`febed/solver.py`; docs/theory.md, data flow; seed 001 §2.3-2.4).

At the start of a gas step (gas fields of step n frozen over its DEM sub-steps):
    `Coupler.locate(x)`            -> cells and weights (one pass); particles outside the local mesh reported
    `Coupler.forces_into(...)`     -> one fused pass: u_@p, ε_@p, ∇p_@p (seed 001 eq 28), K_p (kg/s),
                                      F_D = K_p (u_@p - v_p), F_P = -V_p ∇p_@p (eqs 20, 27) into each particle's
                                      record, and min m_p/K_p
    (`gas_at_particles`, `particle_forces`, `forces`: the same in separate steps / new arrays, for tests and
    the coarse-graining criteria)
Once per gas step, after the sub-steps:
    `Coupler.project_to_gas(...)`  -> α_p, ε (floored), K_i/ΔV_i, (K v)_i/ΔV_i, F_i/ΔV_i (eqs 29-34): projection,
                                      filter passes and division by ΔV_i in kernels on reused nodal arrays

The gas momentum source at node i is then -K_i/ΔV_i u_i + (K v)_i/ΔV_i (implicit in u: the predictor's
diagonal gets + K_i/ΔV_i) plus the explicit force density F_i/ΔV_i the gas receives, the projection of -F_P
(seed 001 eq 29 projects -(F_D + F_P); F_D enters through K and K v). Without filtering (0 passes) what the gas gets is
exactly minus what the particles get (tests/coupling/test_projection.py); with filtering, Σ K_i, Σ (K v)_i and
Σ F_i are conserved and the drag exchange is exact for a uniform gas velocity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from febed.coupling.drag import (
    RECORD_COLUMNS,
    AtParticles,
    GasForces,
    NodalGas,
    drag_forces,
    gas_forces_into,
    gas_forces_kernel,
    get_drag_law,
    pressure_gradient_kernel,
)
from febed.coupling.interpolate import interpolate
from febed.coupling.locate import FOUND, locate
from febed.coupling.mesh_arrays import NUM_VERTICES, MeshArrays
from febed.coupling.projection import (
    exchange_finish_kernel,
    exchange_project_kernel,
    filter_kernel,
    neighbour_filter_transpose,
)


@dataclass
class NodalExchange:
    """Nodal fields for the gas step (local dofs, ghosts current); densities are per unit volume.

    Attributes:
        alpha: (nd,) solid fraction α_p; eps: (nd,) void fraction 1 - α_p floored; clipped: nodes floored.
        K: (nd,) momentum-exchange coefficient density K_i/ΔV_i (kg/(m^3 s)).
        Kv: (nd, gdim) (K v)_i/ΔV_i (N/m^3): the particle-velocity part of the drag exchange.
        F: (nd, gdim) explicit force density the gas receives (N/m^3): minus the projected particle force,
            e.g. +V_p ∇p, the reaction to F_P = -V_p ∇p.
    """

    alpha: np.ndarray
    eps: np.ndarray
    clipped: int
    K: np.ndarray
    Kv: np.ndarray
    F: np.ndarray


class Coupler:
    """Per-run coupling state: particle cells/weights buffers and the chosen drag law (arrays grow on demand).

    With MPI (particles distributed by `febed.parallel.ParticleExchange`) every rank passes its owned particles
    only (rows [0, n_owned) of the DEM): they lie in the rank's owned cells at the last pair-list rebuild and
    in its local (owned or ghost) cells since, so `locate` finds them and the interpolation reads the rank's
    local nodal values (ghost dofs current after a forward scatter). `project_to_gas` sums the contributions
    of every rank at the nodes (reverse scatter with addition over ghost dofs, then forward scatter) before
    the filter and the division by the node volumes, so the nodal fields equal the serial ones to round-off
    (tests/parallel/test_mpi_coupling.py). Take the cells from `particles.cell` (`reset_cells`) before
    locating: they follow the rows through sorting and migration, arrivals from other ranks carry -1.
    Particles shared by work instead are coupled by `febed.coupling.owners.OwnerCoupler`.
    """

    def __init__(self, ma: MeshArrays, drag: str, rho_g: float, mu_g: float, filter_passes: int = 1,
                 void_floor: float = 0.3, pressure_gradient: bool = True):  # fmt: skip
        """Set up for mesh arrays `ma`, drag law name, gas density (kg/m^3) and viscosity (Pa s)."""
        if int(filter_passes) != filter_passes or filter_passes < 0:
            raise ValueError(f"filter_passes: must be an integer >= 0, got {filter_passes!r}")
        if not 0.0 <= void_floor <= 1.0:
            raise ValueError(f"void_floor: the void-fraction floor must be in [0, 1], got {void_floor}")
        self.ma = ma
        self.gas_ma = ma  # the nodal fields' mesh arrays (`febed.coupling.owners.OwnerCoupler`: another mesh's)
        self.law = get_drag_law(drag)
        self.rho_g, self.mu_g = float(rho_g), float(mu_g)
        self.filter_passes = int(filter_passes)
        self.void_floor = float(void_floor)
        self.pressure_gradient = bool(pressure_gradient)
        self.cell = np.full(0, -1, np.int32)
        self._resize(0)
        self._nodal = {}  # columns -> two (nd, columns) scratch arrays for the projection and the filter

    def _resize(self, n: int) -> None:
        nv = NUM_VERTICES[self.ma.kind]
        old = self.cell
        self.cell = np.full(n, -1, np.int32)
        self.cell[: min(n, old.size)] = old[: min(n, old.size)]
        self.ref = np.zeros((n, 3))
        self.w = np.zeros((n, nv))
        self.status = np.zeros(n, np.int8)
        self.exit_facet = np.full(n, -1, np.int32)

    def reset_cells(self, cell: np.ndarray | None = None) -> None:
        """Forget (or set) the particles' previous cells, e.g. after particles were added, removed or migrated."""
        if cell is None:
            self.cell[:] = -1
            return
        if cell.size != self.cell.size:
            self._resize(cell.size)  # the per-particle buffers follow the particle count
        self.cell[:] = cell

    def locate(self, x: np.ndarray) -> np.ndarray:
        """Locate particles x (N, 3) (m) and compute their weights; returns the indices of those not found.

        `self.status` / `self.exit_facet` classify the misses (OUTSIDE_DOMAIN with the local facet crossed,
        e.g. the outlet, or OUTSIDE_LOCAL: on another rank). Keep particle order between calls, or call
        `reset_cells` after reordering: the walk starts from the previous cell of each index.
        """
        n = x.shape[0]
        if n != self.cell.size:
            self._resize(n)
        missing = locate(self.ma, x, self.cell, self.ref, self.status, self.exit_facet, w=self.w)[4]
        return np.nonzero(self.status != FOUND)[0] if missing else np.zeros(0, np.int64)

    def gas_at_particles(self, u_nodes: np.ndarray, eps_nodes: np.ndarray, gradp_nodes: np.ndarray):
        """u_@p (N, 3) m/s, ε_@p (N,), ∇p_@p (N, 3) Pa/m from nodal u (nd, gdim), ε (nd,), ∇p (nd, gdim)."""
        g = self.ma.gdim
        n = self.cell.size
        u = np.zeros((n, 3))
        gp = np.zeros((n, 3))
        u[:, :g] = interpolate(self.ma, self.cell, self.w, u_nodes)
        gp[:, :g] = interpolate(self.ma, self.cell, self.w, gradp_nodes)
        eps = interpolate(self.ma, self.cell, self.w, eps_nodes)
        return u, eps, gp

    def particle_forces(self, u_p, eps_p, gradp_p, v, d_orig, n_orig):
        """K (N,) kg/s, drag F_D (N, 3) N and pressure-gradient force F_P (N, 3) N on each particle.

        K_p = n_orig law(ε, |u - v|, d_orig) (drag of n_orig originals at the parcel velocity);
        F_P = -V_p ∇p with V_p = n_orig π d_orig^3 / 6 the solid volume represented (seed 001 eq 27).
        """
        K, F_d = drag_forces(self.law, eps_p, u_p, v, d_orig, n_orig, self.rho_g, self.mu_g)
        F_p = np.zeros_like(F_d)
        if self.pressure_gradient:
            pressure_gradient_kernel(solid_volume(d_orig, n_orig), gradp_p, F_p)
        return K, F_d, F_p

    def forces(self, u_nodes, eps_nodes, gradp_nodes, v, d_orig, n_orig):
        """Fused `gas_at_particles` + `particle_forces` (one pass; the per-sub-step hot path).

        Returns K (N,) kg/s, F_D (N, 3) N, F_P (N, 3) N (zero if the pressure-gradient force is off), ε_@p (N,).
        """
        n = self.cell.size
        K = np.empty(n)
        F_d = np.empty((n, 3))
        F_p = np.empty((n, 3))
        eps_p = np.empty(n)
        gas_forces_kernel(self.law, self._at(v, d_orig, n_orig), self._gas(u_nodes, eps_nodes, gradp_nodes),
                          GasForces.of(K, F_d, F_p, eps_p))  # fmt: skip
        return K, F_d, F_p, eps_p

    def forces_into(self, u_nodes, eps_nodes, gradp_nodes, v, d_orig, n_orig, record, mass, drag=None) -> float:
        """`forces` writing each particle's exchange record instead of new arrays; returns min m_p/K_p (s).

        Row p of `record` (N, RECORD_COLUMNS) gets K_p, F_D + F_P, v_p, F_P and 1 in the `RECORD_*` columns of
        `febed.coupling.drag` (the solver's per-particle auxiliary array); mass (N,) kg gives the shortest
        relaxation time τ_p = m_p/K_p (NaN if any is NaN, inf without particles); `drag` (N, 3), if given,
        receives F_D (N).
        """
        n = self.cell.size
        c = RECORD_COLUMNS
        out = GasForces.of(F_d=drag, record=record, mass=mass)
        if record.shape != (n, c) or mass.shape != (n,) or v.shape != (n, 3) or out.F_d.shape[0] not in (0, n):
            raise ValueError(f"record, mass, v, drag: need shapes ({n}, {c}), ({n},), ({n}, 3), ({n}, 3), got "
                             f"{record.shape}, {mass.shape}, {v.shape}, {out.F_d.shape}")  # fmt: skip
        return gas_forces_into(self.law, self._at(v, d_orig, n_orig), self._gas(u_nodes, eps_nodes, gradp_nodes), out)

    def _at(self, v, d_orig, n_orig) -> AtParticles:
        return AtParticles.of(self.ma.cell_dofs, self.cell, self.w, v, d_orig, n_orig)

    def _gas(self, u_nodes, eps_nodes, gradp_nodes) -> NodalGas:
        return NodalGas(u_nodes, eps_nodes, gradp_nodes, self.rho_g, self.mu_g, self.pressure_gradient)

    def project_to_gas(self, d_orig, n_orig, K, v, F_explicit=None, owned=None) -> NodalExchange:
        """Project solid volume, K, K v and an explicit particle force onto the nodes; filter; divide (collective).

        Args:
            d_orig: (N,) original particle diameters (m).
            n_orig: (N,) number of original particles each particle represents.
            K: (N,) momentum-exchange coefficients (kg/s) from `particle_forces`.
            v: (N, 3) particle velocities (m/s).
            F_explicit: (N, 3) N force the particles receive that the gas must return (e.g. F_P), or None.
            owned: (N,) bool, particles this rank owns (ghost particles are not projected); None = all.
        """
        ma = self.ma
        g = ma.gdim
        cell = self.cell if owned is None else np.where(owned, self.cell, -1).astype(np.int32)
        n = cell.size
        d3 = np.asarray(d_orig, dtype=np.float64) ** 3  # NumPy's power, as `solid_volume` (bit-identical)
        n_orig = np.ascontiguousarray(n_orig, dtype=np.float64)  # C-contiguous float64: one compiled signature
        K = np.ascontiguousarray(K, dtype=np.float64)
        v = np.ascontiguousarray(v, dtype=np.float64)
        F = np.zeros((0, 3)) if F_explicit is None else np.ascontiguousarray(F_explicit, dtype=np.float64)
        for name, a, shape in (("d_orig", d3, (n,)), ("n_orig", n_orig, (n,)), ("K", K, (n,)), ("v", v, (n, 3)),
                               ("F_explicit", F, (n if F_explicit is not None else 0, 3))):  # fmt: skip
            if a.shape != shape:
                raise ValueError(f"{name}: must have shape {shape}, got {a.shape}")
        cur, nxt = self._scratch(2 + g + (g if F_explicit is not None else 0))
        self._deposit(cell, d3, n_orig, K, v, F, g, cur)
        ma = self.gas_ma
        for _ in range(self.filter_passes):  # seed 001 eqs 31-34
            filter_kernel(ma.cell_dofs, ma.num_owned_cells, *ma.filter_weights(), cur, nxt)
            ma.accumulate(nxt)
            cur, nxt = nxt, cur
        nd = ma.num_dofs
        alpha, eps, Ki, Kv, Fi = np.empty(nd), np.empty(nd), np.empty(nd), np.empty((nd, g)), np.empty((nd, g))
        clipped = exchange_finish_kernel(
            cur, ma.node_volume, self.void_floor, ma.num_owned_dofs, alpha, eps, Ki, Kv, Fi
        )
        if ma.parallel:
            clipped = ma.comm.allreduce(clipped)
        return NodalExchange(alpha, eps, int(clipped), Ki, Kv, Fi)

    def filter_transpose(self, nodal: np.ndarray) -> np.ndarray:
        """A nodal field (nd, k) averaged `filter_passes` times by the void-fraction filter's transpose (collective).

        Interpolated at the particles, it gives them in total what the filtered nodal sums give the gas against
        the field itself (`neighbour_filter_transpose`); the nodal pressure-gradient reaction relies on it.
        """
        return neighbour_filter_transpose(self.gas_ma, nodal, self.filter_passes)

    def _deposit(self, cell, d3, n_orig, K, v, F, g, out) -> None:
        """Project the particles' [V_p, K_p, K_p v_p, -F_p] onto `out` (nd, cols), summed over ranks (collective)."""
        exchange_project_kernel(self.ma.cell_dofs, cell, self.w, d3, n_orig, K, v, F, g, out)
        self.gas_ma.accumulate(out)

    def _scratch(self, cols: int):
        """Two (nd, cols) nodal arrays reused between calls (the projection and the filter's ping-pong)."""
        s = self._nodal.get(cols)
        if s is None:
            nd = self.gas_ma.num_dofs
            s = self._nodal[cols] = (np.zeros((nd, cols)), np.zeros((nd, cols)))
        return s


def solid_volume(d_orig: np.ndarray, n_orig: np.ndarray) -> np.ndarray:
    """Solid volume each particle represents, n_orig π d_orig^3 / 6 (m^3)."""
    return n_orig * (np.pi / 6.0) * d_orig**3
