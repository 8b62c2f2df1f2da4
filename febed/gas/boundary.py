"""Gas boundary conditions by facet-tag name, applied to nodal arrays.

Each named facet tag gets a `BoundarySpec`:

* `inlet` — a *superficial* velocity U_f (optionally ramped linearly from 0 over `ramp_time`) along the
  inward normal of the tag. The nodal superficial velocity q = ε u is scaled so that the discrete inflow
  Σ_j q_j·(−B_j) over the inlet nodes (B_j = ∫_∂Ω φ_j n ds) is exactly U_f A, whatever ε is there. A is the
  tag's area plus the areas of `cross_section_tags` (seed 001's bottom-wall patch: U_f is defined over
  the whole cross-section, so the open part carries U_f A_total / A_open, DESIGN.md "Readings"). With
  `wins_over` (no-slip wall tags) the nodes the inlet shares with those walls take the inlet's velocity
  instead of no-slip (they stay no-slip if they also touch another no-slip wall).
  Why: a node-based condition cannot give a wall patch exactly its cells: with no-slip at the patch's edge
  nodes the inflow ramps from U to 0 over the cell beside the patch, so no gas is missing over the patch's
  cells plus one; with the edge nodes the inlet's, the ramp lies inside the patch's edge cells, so the
  patch's cells minus one. Seed 001's coarse patch of 3 cells is then 4 or 2 cells wide for the gas.
* `wall` — no-slip (q = 0) or, with `slip`, zero normal velocity: at each node the directions of
  ∫ φ_i n⊗n ds with a significant weight are removed (so corners and edges are handled). With
  `slip_normals` (axes, e.g. ("y",)) only the tag's facets whose normal lies along those axes slip: a node
  that touches any other facet of the tag stays no-slip (a pseudo-2D bed's front and back walls slip, its
  side walls do not: `demos/pseudo2d/C1-slip-front-back.toml`). With `slip_length` λ [m] the slip is
  partial (Navier): the tangential gas velocity u_t at the wall feels the shear μ_eff u_t/λ (no normal
  velocity, as for a free slip). λ → 0 is no-slip, λ → ∞ free slip. At a node the shear ε μ_eff u_t/λ of the
  volume-averaged equations (their viscous flux is ε μ_eff ∇u) acts on the lumped wall area a_i = ∫φ_i ds
  of the partial-slip facets and is implicit in the predictor, like the drag: the coefficient
  ε_i μ_eff,i a_i/(λ ΔV_i) [kg/(m^3 s)] is added to K_i (`NodalBoundary.wall_friction`).
  Why: on a coarse mesh a no-slip node holds the gas still over a whole cell, as if the wall layer were a
  cell thick. A slip length lets the gas at the wall node move and still feel a wall shear. In seed 001's
  C1 (coarse mesh, front/back walls) λ = 1 mm, one particle diameter, keeps the bed bubbling; λ = 3.4e-5 m,
  the packed bed's Brinkman length, throttles it again (`demos/pseudo2d/C1-partial-slip-front-back.toml`).
* `outlet` — pressure `pressure` [Pa] (Dirichlet for p, zero increment); the velocity is free, except that
  gas flowing back in is braked (backflow stabilisation, `VANSParameters.backflow`, see `febed.gas.vans`).
* `symmetry` — zero normal velocity, like a slip wall.

Tags of the mesh that the specs do not name are no-slip walls. Where tags meet, a node takes the first of:
no-slip wall (but an inlet's `wins_over` walls yield to it), inlet, slip/symmetry, free. Pressure nodes are
all the nodes of outlet facets.
"""

from __future__ import annotations

from dataclasses import dataclass

from mpi4py import MPI

import dolfinx.fem
import numpy as np

from febed.gas.operators import normal_tensor_weights, tag_normal_weights

BOUNDARY_TYPES = ("inlet", "wall", "outlet", "symmetry")
AXES = ("x", "y", "z")


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
        if self.wins_over and self.type != "inlet":
            raise ValueError(f"boundary {name!r}: wins_over is for an inlet (type = 'inlet'), not a {self.type}")
        if self.ramp_time < 0.0:
            raise ValueError(f"boundary {name!r}: ramp_time must be >= 0 s, got {self.ramp_time}")


def _dofs(mesh_data, Q, name: str) -> np.ndarray:
    fdim = mesh_data.mesh.topology.dim - 1
    facets = np.asarray(mesh_data.facets(name), dtype=np.int32)
    return dolfinx.fem.locate_dofs_topological(Q, fdim, facets)


def _area(mesh_data, Q, name: str) -> float:
    """Area of the facets of tag `name` [m^2] (length in 2D)."""
    import ufl

    ds = ufl.Measure("ds", domain=mesh_data.mesh, subdomain_data=mesh_data.facet_tags)
    one = dolfinx.fem.Constant(mesh_data.mesh, 1.0)
    local = dolfinx.fem.assemble_scalar(dolfinx.fem.form(one * ds(mesh_data.tag_id(name))))
    return mesh_data.comm.allreduce(local, op=MPI.SUM)


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
        noslip = [(n, dofs[n]) for n, s in specs.items() if s.type == "wall" and not s.slip]
        for n, s in specs.items():  # slip only on the facets normal to slip_normals: the other nodes stay no-slip
            if s.type == "wall" and s.slip and s.slip_normals:
                keep = [AXES.index(a) for a in s.slip_normals]
                if max(keep) >= ops.gdim:
                    raise ValueError(f"boundary {n!r}: slip_normals {list(s.slip_normals)} in a {ops.gdim}D mesh")
                other = [d for d in range(ops.gdim) if d not in keep]
                nn = normal_tensor_weights(mesh_data, Q, [n])[dofs[n]]
                weight = nn[:, other, other].sum(axis=1)  # Σ ∫φ_i n_d² ds over the other axes d
                noslip.append((n, dofs[n][weight > 1e-9 * np.trace(nn, axis1=1, axis2=2)]))
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
        # inlets: nodes, inward normal, superficial speed factor A_total / A_open (discrete)
        self.inlets = []
        for n, s in specs.items():
            if s.type != "inlet":
                continue
            nodes = np.setdiff1d(dofs[n], taken)
            taken = np.union1d(taken, nodes)
            bw = tag_normal_weights(mesh_data, Q, [n])
            normal = -np.array([comm.allreduce(bw[: ops.n_owned, d].sum(), op=MPI.SUM) for d in range(ops.gdim)])
            normal /= np.linalg.norm(normal)
            owned = nodes[nodes < ops.n_owned]
            a_open = comm.allreduce(float(-(ops.bnormal[owned] @ normal).sum()), op=MPI.SUM)
            a_total = _area(mesh_data, Q, n) + sum(_area(mesh_data, Q, c) for c in s.cross_section_tags)
            self.inlets.append((nodes, normal, s, a_total, a_open))
        slip = [dofs[n] for n, s in specs.items() if s.type == "symmetry" or (s.type == "wall" and s.slip)]
        self.slip = np.setdiff1d(np.unique(np.concatenate(slip)), taken) if slip else empty
        # slip projector per node: remove every direction in which the adjacent slip facets have a
        # significant normal (one on a flat wall; all at a 2D corner; two along a 3D edge)
        # (the assemblies below are collective: every rank takes part, whether or not it has slip nodes)
        self.slip_proj = np.zeros((self.slip.size, ops.gdim, ops.gdim))
        names = [n for n, s in specs.items() if s.type == "symmetry" or (s.type == "wall" and s.slip)]
        if names:
            nn = normal_tensor_weights(mesh_data, Q, names)[self.slip]
            w, vec = np.linalg.eigh(nn)
            keep = w < 0.2 * w[:, -1:]
            self.slip_proj = np.einsum("nik,nk,njk->nij", vec, keep.astype(float), vec)
        # partial slip: per slip node, Σ over the tags with a slip length of ∫φ_i ds / λ [m]
        self.friction_nodes, self.friction_area = empty, np.empty(0)
        partial = [(n, s) for n, s in specs.items() if s.type == "wall" and s.slip and s.slip_length is not None]
        if partial:

            def wall_area(tag):  # ∫φ_i ds over the tag's facets: the trace of ∫φ_i n⊗n ds (n·n = 1)
                return np.trace(normal_tensor_weights(mesh_data, Q, [tag]), axis1=1, axis2=2)

            a = sum(wall_area(n) / s.slip_length for n, s in partial)[self.slip]
            sel = a > 0.0
            self.friction_nodes, self.friction_area = self.slip[sel], a[sel]
        # the same on every rank, so that the caller's collective work for the shear (μ_eff) is too
        self.has_wall_friction = comm.allreduce(self.friction_nodes.size, op=MPI.SUM) > 0
        outs = [(dofs[n], s.pressure) for n, s in specs.items() if s.type == "outlet"]
        self.pressure_dofs = np.unique(np.concatenate([d for d, _ in outs])) if outs else empty
        self.pressure_values = np.zeros(self.pressure_dofs.size)
        for d, val in outs:
            self.pressure_values[np.searchsorted(self.pressure_dofs, d)] = val
        self.has_outlet = comm.allreduce(self.pressure_dofs.size, op=MPI.SUM) > 0

    def inflow(self, t: float) -> float:
        """Volumetric superficial inflow Σ U_f(t) A_total over the inlets at time t [m^3/s] (m^2/s in 2D)."""
        return sum(self._speed(s, t) * a_total for _, _, s, a_total, _ in self.inlets)

    @staticmethod
    def _speed(spec: BoundarySpec, t: float) -> float:
        ramp = 1.0 if spec.ramp_time <= 0.0 else min(1.0, t / spec.ramp_time)
        return spec.velocity * ramp

    def apply_velocity(self, q: np.ndarray, t: float) -> None:
        """Impose the velocity conditions on the superficial nodal velocity q (n, gdim) in place, at time t."""
        q[self.noslip] = 0.0
        for nodes, normal, spec, a_total, a_open in self.inlets:
            q[nodes] = self._speed(spec, t) * a_total / a_open * normal
        if self.slip.size:
            q[self.slip] = np.einsum("nij,nj->ni", self.slip_proj, q[self.slip])

    def wall_friction(self, K: np.ndarray, eps_mu: np.ndarray, volume: np.ndarray) -> np.ndarray:
        """K plus the partial-slip walls' implicit coefficient ε_i μ_eff,i a_i/(λ ΔV_i) [kg/(m^3 s)] (a copy if any).

        `eps_mu` is ε μ_eff [Pa s] and `volume` ΔV_i [m^3] at the local nodes; K is not changed in place.
        """
        if self.friction_nodes.size == 0:
            return K
        K = np.array(K, dtype=float, copy=True)
        nodes = self.friction_nodes
        K[nodes] += eps_mu[nodes] * self.friction_area / volume[nodes]
        return K

    def dirichlet_velocity_nodes(self) -> np.ndarray:
        """Local nodes whose whole velocity is prescribed (no-slip walls and inlets)."""
        parts = [self.noslip] + [nodes for nodes, *_ in self.inlets]
        return np.unique(np.concatenate(parts))
