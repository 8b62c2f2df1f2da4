"""Small meshes for the coupling tests: unstructured non-uniform (gmsh) and distorted structured (dolfinx)."""

from functools import cache

from mpi4py import MPI

import numpy as np
from dolfinx import mesh

from febed.coupling.mesh_arrays import extract_mesh_arrays


def _gmsh_mesh(dim: int):
    """Unstructured triangles (dim 2) or tetrahedra (dim 3), cell size graded 4:1 across the domain."""
    from dolfinx.io import gmshio

    from febed.meshing import _gmsh  # initialises gmsh once per process, shared with the mesh builders

    comm = MPI.COMM_WORLD
    gmsh = _gmsh()
    gmsh.clear()
    if comm.rank == 0:
        gmsh.model.add("graded")
        if dim == 2:
            gmsh.model.occ.addRectangle(0.0, 0.0, 0.0, 0.09, 0.2)
        else:
            gmsh.model.occ.addBox(0.0, 0.0, 0.0, 0.08, 0.03, 0.1)
        gmsh.model.occ.synchronize()
        ents = gmsh.model.getEntities(dim)
        gmsh.model.addPhysicalGroup(dim, [e[1] for e in ents], 1)
        # graded size: fine near the origin, coarse far away
        field = gmsh.model.mesh.field
        f = field.add("MathEval")
        field.setString(f, "F", "0.003 + 0.15*(x + y + z)" if dim == 2 else "0.006 + 0.12*(x + y + z)")
        field.setAsBackgroundMesh(f)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        gmsh.model.mesh.generate(dim)
    m, _, _ = gmshio.model_to_mesh(gmsh.model, comm, 0, gdim=dim)
    gmsh.clear()
    return m


def _sheared(kind: str):
    """Structured quads/hexes sheared into parallelograms/parallelepipeds (affine maps, not axis-aligned)."""
    comm = MPI.COMM_WORLD
    ct = getattr(mesh.CellType, kind)
    if kind == "quadrilateral":
        m = mesh.create_rectangle(comm, [np.array([0.0, 0.0]), np.array([0.09, 0.12])], [7, 10], ct)
    else:
        m = mesh.create_box(comm, [np.array([0.0, 0.0, 0.0]), np.array([0.08, 0.03, 0.1])], [5, 3, 6], ct)
    x = m.geometry.x
    x[:, 0] += 0.3 * x[:, 1] - 0.2 * x[:, 2]
    x[:, 1] += 0.1 * x[:, 0]
    return m


def _distorted(kind: str, comm=None):
    """Structured quads/hexes (non-affine after distortion) or simplices on a smoothly distorted box."""
    comm = comm or MPI.COMM_WORLD
    ct = getattr(mesh.CellType, kind)
    if kind in ("triangle", "quadrilateral"):
        m = mesh.create_rectangle(comm, [np.array([0.0, 0.0]), np.array([0.09, 0.12])], [9, 12], ct)
        scale = 0.09
    else:
        m = mesh.create_box(comm, [np.array([0.0, 0.0, 0.0]), np.array([0.08, 0.03, 0.1])], [6, 3, 7], ct)
        scale = 0.08
    x = m.geometry.x
    s = x / scale
    dx = 0.04 * scale * np.sin(2.0 * np.pi * s[:, 0]) * np.sin(1.5 * np.pi * s[:, 1] + 0.3)
    dy = 0.03 * scale * np.sin(1.3 * np.pi * s[:, 0] + 1.0) * np.sin(np.pi * s[:, 1])
    x[:, 0] += dx
    x[:, 1] += dy
    return m


@cache
def mesh_and_arrays(name: str):
    """(dolfinx mesh, MeshArrays) for a named test mesh: 'tri-unstructured', 'tet-unstructured', 'quad', 'hex',
    'tri-distorted', 'tet-distorted', 'quad-affine', 'hex-affine'. Cached per process."""
    if name == "tri-unstructured":
        m = _gmsh_mesh(2)
    elif name == "tet-unstructured":
        m = _gmsh_mesh(3)
    elif name in ("quad", "hex"):
        m = _distorted({"quad": "quadrilateral", "hex": "hexahedron"}[name])
    elif name in ("quad-affine", "hex-affine"):
        m = _sheared({"quad-affine": "quadrilateral", "hex-affine": "hexahedron"}[name])
    elif name in ("tri-distorted", "tet-distorted"):
        m = _distorted({"tri-distorted": "triangle", "tet-distorted": "tetrahedron"}[name])
    else:
        raise ValueError(name)
    return m, extract_mesh_arrays(m, depth=0.01)


ALL_MESHES = ("tri-unstructured", "tet-unstructured", "quad", "hex")


def random_points(ma, n: int, seed: int = 0, margin: float = 0.0) -> np.ndarray:
    """n points (n, 3) uniformly in the global bounding box of the mesh (the same on every rank)."""
    lo, hi = np.empty(3), np.empty(3)
    ma.comm.Allreduce(ma.x_dofs.min(axis=0), lo, op=MPI.MIN)
    ma.comm.Allreduce(ma.x_dofs.max(axis=0), hi, op=MPI.MAX)
    rng = np.random.default_rng(seed)
    pts = lo - margin + (hi - lo + 2 * margin) * rng.random((n, 3))
    if ma.gdim == 2:
        pts[:, 2] = 0.0
    return pts
