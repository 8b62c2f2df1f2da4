"""Gas boundary conditions by facet-tag name, applied to nodal arrays.

Each named facet tag gets a `BoundarySpec`:

* `inlet` — a *superficial* velocity U_f (optionally ramped linearly from 0 over `ramp_time`) along the
  inward normal of the tag. The nodal superficial velocity q = ε u is scaled so that the discrete inflow
  Σ_j q_j·(−B_j) over the inlet nodes (B_j = ∫_∂Ω φ_j n ds) is exactly U_f A, whatever ε is there. A is the
  tag's area plus the areas of `cross_section_tags` (seed 001's bottom-wall patch: U_f is defined over
  the whole cross-section, so the open part carries U_f A_total / A_open; seed 001 §3.2).
  Where the inlet meets a wall with the porous wall law (below, the default), the shared nodes are the
  inlet's, each with the share f_j = B_j^inlet·n / (B_j^inlet + B_j^wall)·n of its boundary weight that the
  inlet facets give (1/2 at the edge of a coplanar wall patch on a uniform mesh), and the velocity
  U_o f_j n: the gas then enters through exactly the inlet's facets (A_open = Σ_j f_j B_j·n is the inlet's
  own area), so the gas-free strip over a wall patch is the patch itself on every mesh. Where two inlets meet,
  the shared nodes carry both: each inlet gives them its speed times its own facets' share f_j, so each inlet's
  gas enters through its facets and two inlets at one speed give a uniform inflow. At a corner with a
  wall-law wall across the inlet (a side wall) the weight is f_j times that wall's slide s_j = λ/δ (0 in
  clear gas, where the corner is held like the wall; 1 − 2δ/h in a packed bed), from the drag of each step.
  Where the inlet meets a strict no-slip wall (`wall_law = "no_slip"`), no-slip wins;
  with `wins_over` (strict no-slip wall tags) those shared nodes take the inlet's velocity instead (they
  stay no-slip if they also touch another strict no-slip wall). A node-based no-slip condition cannot give a
  wall patch exactly its cells: with no-slip at the patch's edge nodes the inflow ramps from U to 0 over
  the cell beside the patch, so no gas enters over the patch's cells plus one; with `wins_over`, over the
  patch's cells minus one.
* `wall` without slip — by default the **porous wall law** (`wall_law = "brinkman"`): the wall nodes carry
  no normal velocity and slide along the wall against the shear of the Brinkman layer of the local drag.
  Why: a node held at rest makes the gas of half a cell stand still along the wall. In a packed or
  bubbling bed the real wall layer is the Brinkman layer, of thickness δ = √(ε μ_eff / K) (≈ 40 µm for
  1 mm beads at 0.3 m/s), far thinner than any cell, so a no-slip node over-resists by a first-order error:
  the pressure gradient through a packed channel 15 mm wide is 1.72x Ergun on 3 cells, 1.27x on 6, 1.12x
  on 12 (tests/gas/test_fixed_bed_walls.py). The law is the Navier condition ε μ_eff ∂u_t/∂n = ε μ_eff u_t/λ
  with a local slip length λ = δ (1 − 2/√(4 + (h/δ)²)) (`porous_slip_inverse`), h = 2 ΔV_i/a_i the
  wall-normal size of the wall node's cell (a_i = ∫φ_i ds). This λ makes the lumped node-based
  discretisation of the 1D Brinkman problem ε μ_eff u'' = K u − G on a uniform mesh carry exactly the
  flow deficit U δ (and so the wall shear ε μ_eff U/δ = K U δ) of its continuous solution
  u = U (1 − e^{−y/δ}), for any h/δ: λ → δ when δ ≪ h (a packed bed: the Navier slip of Brinkman's
  equation at a wall, Brinkman 1947; the form of Beavers & Joseph's 1967 slip condition), and
  λ → h²/(8δ) → 0 when δ ≫ h (clear gas: no-slip, the nodes held at rest to round-off). The
  shear is implicit, like the drag and a partial slip's (`wall_friction`), and it also damps the wall
  nodes' pressure correction by 1/(1 + c_i Δt/(ρ ε_i)), so that in clear gas the wall nodes stay at rest
  after the correction too. `wall_law = "no_slip"` holds the wall nodes at rest (q = 0) whatever the drag.
  Wall-law nodes on an outlet are held at rest (the outlet's mass balance counts a plain correction there).
* `wall` with `slip` — zero normal velocity: at each node the directions of
  ∫ φ_i n⊗n ds with a significant weight are removed (so corners and edges are handled). With
  `slip_normals` (axes, e.g. ("y",)) only the tag's facets whose normal lies along those axes slip: a node
  that touches any other facet of the tag stays strictly no-slip. With `slip_length` λ [m] the slip is
  partial (Navier): the tangential gas velocity u_t at the wall feels the shear μ_eff u_t/λ (no normal
  velocity, as for a free slip). λ → 0 is no-slip, λ → ∞ free slip. At a node the shear ε μ_eff u_t/λ of the
  volume-averaged equations (their viscous flux is ε μ_eff ∇u) acts on the lumped wall area a_i = ∫φ_i ds
  of the partial-slip facets and is implicit in the predictor, like the drag: the coefficient
  ε_i μ_eff,i a_i/(λ ΔV_i) [kg/(m^3 s)] is added to K_i (`NodalBoundary.wall_friction`).
* `outlet` — pressure `pressure` [Pa] (Dirichlet for p, zero increment); the velocity is free, except that
  gas flowing back in is braked (backflow stabilisation, `VANSParameters.backflow`, see `febed.gas.vans`).
* `symmetry` — zero normal velocity, like a slip wall.

Tags of the mesh that the specs do not name are walls with the porous wall law. Where tags meet, a node
takes the first of: strict no-slip (but an inlet's `wins_over` walls yield to it), inlet (every inlet of the
node, each adding its part), wall law, slip/symmetry, free. Pressure nodes are all the nodes of outlet facets.
"""

from __future__ import annotations

from dataclasses import dataclass

from mpi4py import MPI

import dolfinx.fem
import numpy as np

from febed.gas import kernels
from febed.gas.operators import normal_tensor_weights, tag_normal_weights
from febed.meshing import facet_area

BOUNDARY_TYPES = ("inlet", "wall", "outlet", "symmetry")
AXES = ("x", "y", "z")
WALL_LAWS = ("brinkman", "no_slip")


@dataclass
class BoundarySpec:
    """Condition on one facet tag (units: m/s, s, Pa)."""

    type: str = "wall"
    velocity: float | None = None
    ramp_time: float = 0.0
    slip: bool = False
    pressure: float = 0.0
    cross_section_tags: tuple[str, ...] = ()
    slip_normals: tuple[str, ...] = ()
    slip_length: float | None = None  # Navier slip length [m] of a slip wall; None: free slip
    wins_over: tuple[str, ...] = ()  # inlet: no-slip wall tags whose nodes shared with it take its velocity
    wall_law: str = "brinkman"  # no-slip wall: "brinkman" (porous wall law, see the module docstring) or "no_slip"

    def validate(self, name: str) -> None:
        """Raise ValueError naming the tag and the bad field."""
        if self.type not in BOUNDARY_TYPES:
            raise ValueError(f"boundary {name!r}: type {self.type!r} is not one of {', '.join(BOUNDARY_TYPES)}")
        if self.type == "inlet" and (self.velocity is None or not self.velocity >= 0.0):
            raise ValueError(f"boundary {name!r}: an inlet needs velocity >= 0 (superficial, m/s)")
        bad = [a for a in self.slip_normals if a not in AXES]
        if bad:
            raise ValueError(f"boundary {name!r}: slip_normals {bad} are not axes; allowed: {', '.join(AXES)}")
        if self.slip_normals and not (self.type == "wall" and self.slip):
            raise ValueError(f"boundary {name!r}: slip_normals needs type = 'wall' with slip = true")
        if self.slip_length is not None:
            if not (self.type == "wall" and self.slip):
                raise ValueError(f"boundary {name!r}: slip_length needs type = 'wall' with slip = true")
            if not self.slip_length > 0.0:
                msg = f"slip_length must be > 0 m (omit it for a free slip), got {self.slip_length!r}"
                raise ValueError(f"boundary {name!r}: {msg}")
        if self.wall_law not in WALL_LAWS:
            raise ValueError(f"boundary {name!r}: wall_law {self.wall_law!r} is not one of {', '.join(WALL_LAWS)}")
        if self.wins_over and self.type != "inlet":
            raise ValueError(f"boundary {name!r}: wins_over is for an inlet (type = 'inlet'), not a {self.type}")
        if self.ramp_time < 0.0:
            raise ValueError(f"boundary {name!r}: ramp_time must be >= 0 s, got {self.ramp_time}")


def _dofs(mesh_data, Q, name: str) -> np.ndarray:
    fdim = mesh_data.mesh.topology.dim - 1
    facets = np.asarray(mesh_data.facets(name), dtype=np.int32)
    return dolfinx.fem.locate_dofs_topological(Q, fdim, facets)


class NodalBoundary:
    """Node sets and values of the gas boundary conditions (see the module docstring)."""

    def __init__(self, mesh_data, ops, specs: dict[str, BoundarySpec]):
        for name, spec in specs.items():
            spec.validate(name)
        mesh_data.require_tags(list(specs), "the gas boundary conditions")
        for spec in specs.values():
            mesh_data.require_tags(list(spec.cross_section_tags), "an inlet's cross_section_tags")
            mesh_data.require_tags(list(spec.wins_over), "an inlet's wins_over")
        Q, comm = ops.Q, mesh_data.comm
        self.comm = comm
        self.n_owned = ops.n_owned
        specs = {n: specs.get(n, BoundarySpec()) for n in sorted(mesh_data.tags)} | specs
        self.specs = specs
        dofs = {n: _dofs(mesh_data, Q, n) for n in specs}
        empty = np.empty(0, np.int32)
        for n, s in specs.items():
            for w in s.wins_over:
                if not (specs[w].type == "wall" and not specs[w].slip):
                    msg = f"wins_over {w!r} is not a no-slip wall (type = 'wall', slip = false)"
                    raise ValueError(f"boundary {n!r}: {msg}")
                if specs[w].wall_law != "no_slip":
                    msg = (
                        f"wins_over {w!r} needs wall_law = 'no_slip' on it (an inlet already shares its nodes "
                        "with a wall of the porous wall law by facet)"
                    )
                    raise ValueError(f"boundary {n!r}: {msg}")
        # (the assemblies below are collective: every rank takes part, whether or not it has such nodes)
        outlet_nodes = [dofs[n] for n, s in specs.items() if s.type == "outlet"]
        outlet_nodes = np.unique(np.concatenate(outlet_nodes)) if outlet_nodes else empty
        law = [n for n, s in specs.items() if s.type == "wall" and not s.slip and s.wall_law == "brinkman"]
        law_nodes = np.unique(np.concatenate([dofs[n] for n in law])) if law else empty
        # strict no-slip: walls without the law, the non-slipping facets of slip_normals walls, and the
        # wall-law nodes on an outlet (the outlet's mass balance assumes a plain correction there)
        noslip = [(n, dofs[n]) for n, s in specs.items() if s.type == "wall" and not s.slip and n not in law]
        for n, s in specs.items():  # slip only on the facets normal to slip_normals: the other nodes stay no-slip
            if s.type == "wall" and s.slip and s.slip_normals:
                keep = [AXES.index(a) for a in s.slip_normals]
                if max(keep) >= ops.gdim:
                    raise ValueError(f"boundary {n!r}: slip_normals {list(s.slip_normals)} in a {ops.gdim}D mesh")
                other = [d for d in range(ops.gdim) if d not in keep]
                nn = normal_tensor_weights(mesh_data, Q, [n])[dofs[n]]
                weight = nn[:, other, other].sum(axis=1)  # Σ ∫φ_i n_d² ds over the other axes d
                noslip.append((n, dofs[n][weight > 1e-9 * np.trace(nn, axis1=1, axis2=2)]))
        noslip.append(("", np.intersect1d(law_nodes, outlet_nodes)))
        self.noslip = np.unique(np.concatenate([d for _, d in noslip])) if noslip else empty
        for n, s in specs.items():  # an inlet's edge nodes on the walls it wins over: free for the inlet
            if s.wins_over:
                over = [d for w, d in noslip if w in s.wins_over]
                others = [d for w, d in noslip if w not in s.wins_over]
                edge = np.intersect1d(dofs[n], np.concatenate(over))
                if others:
                    edge = np.setdiff1d(edge, np.concatenate(others))
                self.noslip = np.setdiff1d(self.noslip, edge)
        taken = self.noslip
        # inlets: nodes, inward normal, superficial speed factor A_total / A_open (discrete), and per node the
        # inlet's share f_j of its boundary weight along the normal: 1 inside the inlet, the inlet facets'
        # share on an edge shared with a wall-law wall or another inlet (so that Σ_j f_j B_j·n is the inlet's
        # own area); a node two inlets share carries both, each inlet adding its part (`apply_velocity`)
        self.inlets = []
        b_law = tag_normal_weights(mesh_data, Q, law)
        a_law = np.trace(normal_tensor_weights(mesh_data, Q, law), axis1=1, axis2=2) if law else np.zeros(ops.n_local)
        inlet_names = [n for n, s in specs.items() if s.type == "inlet"]
        b_inlet = {n: tag_normal_weights(mesh_data, Q, [n]) for n in inlet_names}
        inlet_nodes = []
        for n in inlet_names:
            s = specs[n]
            nodes = np.setdiff1d(dofs[n], taken)
            inlet_nodes.append(nodes)
            bw = b_inlet[n]
            normal = -np.array([comm.allreduce(bw[: ops.n_owned, d].sum(), op=MPI.SUM) for d in range(ops.gdim)])
            normal /= np.linalg.norm(normal)
            own_flux = -(bw[nodes] @ normal)  # ∫_inlet φ_j ds (projected on the inward normal)
            beside = -(b_law[nodes] @ normal)  # the coplanar wall-law facets' part beside it
            for m in inlet_names:  # and the coplanar facets of the other inlets
                if m != n:
                    beside = beside + np.maximum(-(b_inlet[m][nodes] @ normal), 0.0)
            share = np.ones(nodes.size)
            shared = beside > 1e-12 * np.maximum(own_flux, 1e-300)
            share[shared] = own_flux[shared] / (own_flux[shared] + beside[shared])
            # corners with wall-law walls across the inlet (side walls): the wall area a and wall-normal size h
            side_area = a_law[nodes] - np.abs(b_law[nodes] @ normal)
            side = side_area > 1e-9 * np.maximum(a_law[nodes], 1e-300)
            side_h = 2.0 * ops.mass[nodes[side]] / side_area[side]
            a_total = facet_area(mesh_data, n) + sum(facet_area(mesh_data, c) for c in s.cross_section_tags)
            self.inlets.append(_Inlet(nodes, normal, s, a_total, share, side, side_h, ops.bnormal, ops.n_owned, comm))
        self.inlet_nodes = np.unique(np.concatenate(inlet_nodes)) if inlet_nodes else empty
        taken = np.union1d(taken, self.inlet_nodes)
        self.law_nodes = np.setdiff1d(law_nodes, taken)
        taken = np.union1d(taken, self.law_nodes)
        slip_names = [n for n, s in specs.items() if s.type == "symmetry" or (s.type == "wall" and s.slip)]
        slip = [dofs[n] for n in slip_names]
        slip = np.setdiff1d(np.unique(np.concatenate(slip)), taken) if slip else empty
        # slip projector per node (slip, symmetry and wall-law nodes): remove every direction in which the
        # adjacent facets have a significant normal (one on a flat wall; all at a 2D corner; two along a 3D edge)
        self.slip = np.union1d(slip, self.law_nodes)
        self.slip_proj = np.zeros((self.slip.size, ops.gdim, ops.gdim))
        if slip_names or law:
            nn = normal_tensor_weights(mesh_data, Q, slip_names + law)[self.slip]
            w, vec = np.linalg.eigh(nn)
            keep = w < 0.2 * w[:, -1:]
            self.slip_proj = np.einsum("nik,nk,njk->nij", vec, keep.astype(float), vec)

        def wall_area(tags):  # ∫φ_i ds over the tags' facets: the trace of ∫φ_i n⊗n ds (n·n = 1)
            return np.trace(normal_tensor_weights(mesh_data, Q, tags), axis1=1, axis2=2)

        # partial slip: per slip node, Σ over the tags with a slip length of ∫φ_i ds / λ [m]
        self.friction_nodes, self.friction_area = empty, np.empty(0)
        partial = [(n, s) for n, s in specs.items() if s.type == "wall" and s.slip and s.slip_length is not None]
        if partial:
            a = sum(wall_area([n]) / s.slip_length for n, s in partial)[self.slip]
            sel = a > 0.0
            self.friction_nodes, self.friction_area = self.slip[sel], a[sel]
        # the porous wall law: wall area a_i of the law facets and the wall-normal cell size h_i = 2 ΔV_i / a_i
        self.law_area = wall_area(law)[self.law_nodes] if law else np.empty(0)
        self.law_h = 2.0 * ops.mass[self.law_nodes] / self.law_area if law else np.empty(0)
        # the same on every rank, so that the caller's collective work for the shear (μ_eff) is too
        self.has_wall_friction = comm.allreduce(self.friction_nodes.size + self.law_nodes.size, op=MPI.SUM) > 0
        self.has_inlet_corners = any(inlet.has_side for inlet in self.inlets)
        outs = [(dofs[n], s.pressure) for n, s in specs.items() if s.type == "outlet"]
        self.pressure_dofs = np.unique(np.concatenate([d for d, _ in outs])) if outs else empty
        self.pressure_values = np.zeros(self.pressure_dofs.size)
        for d, val in outs:
            self.pressure_values[np.searchsorted(self.pressure_dofs, d)] = val
        self.has_outlet = comm.allreduce(self.pressure_dofs.size, op=MPI.SUM) > 0

    def inflow(self, t: float) -> float:
        """Volumetric superficial inflow Σ U_f(t) A_total over the inlets at time t [m^3/s] (m^2/s in 2D)."""
        return sum(inlet.speed(t) * inlet.a_total for inlet in self.inlets)

    def set_wall_state(self, K: np.ndarray, eps_mu: np.ndarray) -> None:
        """Let the inlets' corners with wall-law walls slide as those walls do under the drag K (collective)."""
        for inlet in self.inlets:
            inlet.set_corner_slide(K, eps_mu)

    def apply_velocity(self, q: np.ndarray, t: float) -> None:
        """Impose the velocity conditions on the superficial nodal velocity q (n, gdim) in place, at time t."""
        kernels.zero_rows(q, self.noslip)
        kernels.zero_rows(q, self.inlet_nodes)
        for inlet in self.inlets:  # a node two inlets share gets both parts
            kernels.add_rows(q, inlet.nodes, inlet.speed(t) * inlet.a_total / inlet.a_open, inlet.weight, inlet.normal)
        if self.slip.size:
            kernels.project_rows(q, self.slip, self.slip_proj)

    def wall_friction(self, K: np.ndarray, eps_mu: np.ndarray, volume: np.ndarray) -> np.ndarray:
        """K plus the walls' implicit shear coefficient c_i = ε_i μ_eff,i a_i/(λ_i ΔV_i) [kg/(m^3 s)] (a copy if any).

        λ_i is the partial-slip walls' slip length, or on wall-law nodes the porous slip length of
        `porous_slip_inverse` at this K. `eps_mu` is ε μ_eff [Pa s] and `volume` ΔV_i [m^3] at the local nodes;
        K is not changed in place.
        """
        if self.friction_nodes.size == 0 and self.law_nodes.size == 0:
            return K
        K = np.array(K, dtype=float, copy=True)
        kernels.add_wall_friction(
            K, eps_mu, volume, self.friction_nodes, self.friction_area, self.law_nodes, self.law_area, self.law_h
        )
        return K

    def dirichlet_velocity_nodes(self) -> np.ndarray:
        """Local nodes whose whole velocity is prescribed (no-slip walls and inlets)."""
        parts = [self.noslip] + [inlet.nodes for inlet in self.inlets]
        return np.unique(np.concatenate(parts))


def porous_slip_inverse(K, eps_mu, h):
    """1/λ [1/m] of the porous wall law: the slip length that gives a wall node the Brinkman layer's shear.

    With δ = √(ε μ_eff / K) the Brinkman length of the local drag K [kg/(m^3 s)] and h the wall-normal size
    of the wall node's cell, λ = δ (1 − 2/√(4 + (h/δ)²)): the slip length with which the lumped node-based
    discretisation of ε μ_eff u'' = K u − G on a uniform mesh of spacing h carries the exact flow deficit
    U δ of the continuous Brinkman layer u = U (1 − e^{−y/δ}) (and so its wall shear ε μ_eff U/δ) for any
    h/δ. It tends to δ in a packed bed (δ ≪ h: Navier slip with the Brinkman length) and to h²/(8δ) → 0 in
    clear gas (no-slip). Written with κ = 1/δ and A = √(4 + κ²h²): 1/λ = A (A + 2)/(κ h²); κ is kept above
    1e-12/h so that clear gas gives a finite, no-slip-sized coefficient.
    """
    kappa = np.sqrt(np.maximum(K, 0.0) / eps_mu)
    kappa = np.maximum(kappa, 1e-12 / h)
    a = np.sqrt(4.0 + (kappa * h) ** 2)
    return a * (a + 2.0) / (kappa * h * h)


class _Inlet:
    """One inlet's nodes and the weights of their velocity (see the module docstring, `inlet`).

    The node j gets the superficial velocity U_f (A_total / A_open) w_j n, w_j = f_j s_j: f_j its share of the
    inlet's facets (coplanar walls), s_j the slide of a wall-law wall across the inlet at a corner (1 elsewhere),
    and A_open = Σ_j w_j (−B_j·n), so that the inflow is U_f A_total exactly whatever the weights.
    """

    def __init__(self, nodes, normal, spec, a_total, share, side, side_h, bnormal, n_owned, comm):
        self.nodes, self.normal, self.spec, self.a_total = nodes, normal, spec, a_total
        self.share, self.side, self.side_h = share, side, side_h
        self.comm = comm
        owned = nodes < n_owned
        self._flux = np.where(owned, -(bnormal[nodes] @ normal), 0.0)  # −B_j·n, owned nodes only
        self.has_side = comm.allreduce(int(side.sum()), op=MPI.SUM) > 0
        self.weight = share.copy()
        self.weight[side] = 0.0  # no drag known yet: the corners are held like the clear-gas wall
        self._share_area = comm.allreduce(float(np.dot(share, self._flux)), op=MPI.SUM)
        self._update_area()

    def _update_area(self) -> None:
        self.a_open = self.comm.allreduce(float(np.dot(self.weight, self._flux)), op=MPI.SUM)
        if self.a_open <= 1e-9 * self._share_area:
            self.weight = self.share.copy()  # an inlet of corners only (one cell wide): they carry the inflow
            self.a_open = self.comm.allreduce(float(np.dot(self.weight, self._flux)), op=MPI.SUM)

    def speed(self, t: float) -> float:
        """U_f at time t (the ramp applied) [m/s]."""
        ramp = 1.0 if self.spec.ramp_time <= 0.0 else min(1.0, t / self.spec.ramp_time)
        return self.spec.velocity * ramp

    def set_corner_slide(self, K: np.ndarray, eps_mu: np.ndarray) -> None:
        """Set the corners' slide s_j = λ_j/δ_j = 1 − 2/√(4 + (h_j/δ_j)²) for the drag K (collective).

        s_j is a wall-law node's speed relative to the bed's in the discrete Brinkman layer
        (`porous_slip_inverse`): 0 in clear gas, 1 − 2δ/h in a packed bed.
        """
        if not self.has_side:
            return
        idx = self.nodes[self.side]
        kappa_h = np.sqrt(np.maximum(K[idx], 0.0) / eps_mu[idx]) * self.side_h
        self.weight[self.side] = self.share[self.side] * (1.0 - 2.0 / np.sqrt(4.0 + kappa_h**2))
        self._update_area()
