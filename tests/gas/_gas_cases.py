"""Small tagged meshes and solver factories shared by the gas tests (imported as `_gas_cases`)."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import numpy as np

from febed.gas import BoundarySpec, VANSParameters, VANSSolver
from febed.meshing import MeshData


def tagged_mesh(mesh, tags: dict[str, callable]) -> MeshData:
    """MeshData with facet tags given as name -> predicate on facet-midpoint coordinates (first match wins)."""
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, tdim)
    idx, val, taken = [], [], np.empty(0, np.int32)
    names = {}
    for k, (name, pred) in enumerate(tags.items(), start=1):
        f = dolfinx.mesh.locate_entities_boundary(mesh, tdim - 1, pred)
        f = np.setdiff1d(f, taken)
        taken = np.union1d(taken, f)
        idx.append(f)
        val.append(np.full(f.size, k, np.int32))
        names[name] = k
    idx, val = np.concatenate(idx), np.concatenate(val)
    order = np.argsort(idx)
    ft = dolfinx.mesh.meshtags(mesh, tdim - 1, idx[order].astype(np.int32), val[order])
    return MeshData(mesh=mesh, facet_tags=ft, cell_tags=None, tags=names, source="test")


def channel(length, height, nx, ny, comm=MPI.COMM_WORLD, cell=dolfinx.mesh.CellType.quadrilateral, patch=None):
    """2D channel along x: `inlet` at x = 0, `walls` at y = 0, H, `outlet` at x = L; optional inlet `patch`."""
    mesh = dolfinx.mesh.create_rectangle(comm, [[0.0, 0.0], [length, height]], [nx, ny], cell)
    tags = {}
    if patch is not None:
        lo, hi = patch
        tags["patch"] = lambda x: np.isclose(x[0], 0.0) & (x[1] >= lo - 1e-12) & (x[1] <= hi + 1e-12)
    tags["inlet"] = lambda x: np.isclose(x[0], 0.0)
    tags["walls"] = lambda x: np.isclose(x[1], 0.0) | np.isclose(x[1], height)
    tags["outlet"] = lambda x: np.isclose(x[0], length)
    return tagged_mesh(mesh, tags)


def channel_solver(md, velocity, rho=1.0, mu=0.1, eps=1.0, slip=False, **kw) -> VANSSolver:
    """A VANS solver on a `channel` mesh with an inlet, walls and an outlet."""
    bcs = {
        "inlet": BoundarySpec("inlet", velocity=velocity, cross_section_tags=("patch",) if "patch" in md.tags else ()),
        "walls": BoundarySpec("wall", slip=slip),
        "outlet": BoundarySpec("outlet", pressure=0.0),
    }
    par = VANSParameters(gravity=0.0, density=rho, viscosity=mu, dt_max=1.0, boundaries=bcs, **kw)
    return VANSSolver(md, par, eps=eps)


def owned(solver, a):
    """Owned rows of a nodal array."""
    return a[: solver.n_owned]


def darcy_errors(md, velocity, rho, mu, eps, dt, jump, steps=2, **kw):
    """Uniform flow at `velocity` through a porous `channel` (slip walls) with D = K dt/(rho eps) = 4, or 4 and 0.4
    on either side of x = 0.05125 (between two node columns) with `jump`: per gas step, the largest relative
    error of the pressure gradient against Darcy's -K U/eps in each part, over the ranks, and the mass
    imbalance relative to the inflow. `kw` go to `VANSParameters`.
    """
    from mpi4py import MPI

    s = channel_solver(md, velocity, rho=rho, mu=mu, eps=eps, slip=True, **kw)
    x = s.x[:, 0]
    D = np.where(x > 0.05125, 0.4, 4.0) if jump else np.full(x.size, 4.0)
    K = D * rho * eps / dt
    s.q[:, 0] = velocity
    s.set_void_fraction(eps)
    xo = owned(s, s.x)[:, 0]
    # bounds between node columns (every 0.0025 m): a node on a bound would be in or out by its coordinate's
    # last bit, which differs between partitions
    parts = [(xo > 0.01625) & (xo < 0.03875), (xo > 0.06125) & (xo < 0.08375)]
    out = []
    for _ in range(steps):
        info = s.step(dt, K=K)
        errs = []
        for inner in parts:
            target = -owned(s, K)[inner] * velocity / eps
            local = np.abs(owned(s, s.grad_p)[inner, 0] / target - 1.0).max(initial=0.0)
            errs.append(MPI.COMM_WORLD.allreduce(float(local), op=MPI.MAX))
        out.append((max(errs), abs(info.mass_imbalance) / (rho * info.inflow)))
    return out
