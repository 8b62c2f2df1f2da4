"""Meshes: gmsh builders for the seed geometries, and `.msh` -> distributed DOLFINx mesh + named tags.

Built-in geometries (SI units), each with named facet groups:

* `pseudo2d` — seed 001's bed, box x in [0, 0.08], y in [0, 0.015], z in [0, 0.25]. Structured hexahedra
  with exactly the cell counts of seed 001 Table 2 (coarse 17x3x55, intermediate 35x6x110, fine
  70x12x220) and a centred `bottom_wall` patch of 3x3 / 5x4 / 10x8 bottom cells where no gas enters;
  or unstructured tetrahedra of a chosen size. Tags `inlet`, `bottom_wall`, `walls`, `outlet`.
* `wang2d` — seed 000's 2D bed, 0.09 m x 0.5 m, 18 x 100 quadrilaterals (5 mm), or the same grid split
  into triangles. Tags `inlet`, `walls`, `outlet`.
* `cylinder` — a cylindrical bed (diameter 0.05 m, height 0.15 m, axis z) in tetrahedra of a chosen size,
  to show that any gmsh geometry works. Tags `inlet`, `walls`, `outlet`.

Any other `.msh` works if its cells and boundary facets carry *named* physical groups. The gmsh sources
of the built-in meshes are written by `write_geo` into `meshes/` for reference; the builders below are
the same geometry through gmsh's Python API.
"""

from __future__ import annotations

import os
import signal
import threading
from dataclasses import dataclass
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed.io.atomic import atomic_path

# Seed 001 Table 2: cells (Nx, Ny, Nz) and bottom-wall patch cells (Nx, Ny).
PSEUDO2D_BOX = (0.08, 0.015, 0.25)
PSEUDO2D_LEVELS = {
    "coarse": ((17, 3, 55), (3, 3)),
    "intermediate": ((35, 6, 110), (5, 4)),
    "fine": ((70, 12, 220), (10, 8)),
}
WANG2D_BOX = (0.09, 0.5)
WANG2D_CELLS = (18, 100)
CYLINDER = {"diameter": 0.05, "height": 0.15}
GEOMETRIES = ("pseudo2d", "wang2d", "cylinder", "box")


CUTS = ("columns", "blocks")  # how `load_msh` shares the cells among the ranks


class MeshError(ValueError):
    """A mesh that cannot be used, with a message naming the file and what is wrong."""


@dataclass
class MeshData:
    """A distributed DOLFINx mesh with its facet tags addressed by name."""

    mesh: object  # dolfinx.mesh.Mesh
    facet_tags: object  # dolfinx.mesh.MeshTags on facets, values = physical-group ids
    cell_tags: object  # dolfinx.mesh.MeshTags on cells
    tags: dict[str, int]  # facet tag name -> physical id
    source: str = ""

    @property
    def gdim(self) -> int:
        """Geometric dimension (2 or 3)."""
        return self.mesh.geometry.dim

    @property
    def comm(self):
        """The mesh's MPI communicator."""
        return self.mesh.comm

    def facets(self, name: str) -> np.ndarray:
        """Local facet indices (this rank) carrying the tag `name`."""
        tag = self.tag_id(name)
        return self.facet_tags.indices[self.facet_tags.values == tag]

    def tag_id(self, name: str) -> int:
        """The physical id of facet tag `name`; MeshError listing the tags if it does not exist."""
        if name not in self.tags:
            raise MeshError(f"{self.source}: no facet tag {name!r}; the mesh has: {', '.join(sorted(self.tags))}")
        return self.tags[name]

    def ds(self, names):
        """The measure ds over the facets of the named tags (a `ufl.Measure` restricted to them), or None if none.

        The chosen facets are marked 1 in tags of their own, so that a form over them is the same whichever
        tags they are: DOLFINx compiles it once per cell type, not once per set of tag ids.
        """
        import dolfinx.mesh
        import ufl

        ids = [self.tag_id(nm) for nm in names]
        if not ids:
            return None
        facets = np.unique(self.facet_tags.indices[np.isin(self.facet_tags.values, ids)]).astype(np.int32)
        fdim = self.mesh.topology.dim - 1
        chosen = dolfinx.mesh.meshtags(self.mesh, fdim, facets, np.ones(facets.size, dtype=np.int32))
        return ufl.Measure("ds", domain=self.mesh, subdomain_data=chosen)(1)

    def require_tags(self, names, what: str = "the case") -> None:
        """Raise MeshError if any of `names` is not a facet tag of the mesh."""
        missing = [n for n in names if n not in self.tags]
        if missing:
            raise MeshError(
                f"{self.source}: {what} names facet tag(s) {', '.join(map(repr, missing))} that the mesh "
                f"lacks; the mesh has: {', '.join(sorted(self.tags)) or '(no named facet groups)'}"
            )

    def boundary_facet_coords(self, names) -> np.ndarray:
        """Vertex coordinates (nf, nv, 3) of every facet tagged with one of `names`, whole mesh, every rank.

        Each facet appears exactly once (owned facets gathered from all ranks). nv = 3 (triangle) or
        4 (quadrilateral, in cyclic order) in 3D, 2 in 2D; the z column is 0 in 2D.
        """
        from dolfinx.cpp.mesh import entities_to_geometry

        mesh = self.mesh
        tdim = mesh.topology.dim
        fdim = tdim - 1
        mesh.topology.create_connectivity(fdim, tdim)
        imap = mesh.topology.index_map(fdim)
        facets = np.concatenate([self.facets(n) for n in names]) if names else np.empty(0, np.int32)
        facets = np.unique(facets[facets < imap.size_local]).astype(np.int32)
        nv = {"triangle": 2, "quadrilateral": 2, "tetrahedron": 3, "hexahedron": 4}[mesh.topology.cell_type.name]
        if facets.size:
            geom = entities_to_geometry(mesh._mesh, fdim, facets, False)
            if nv == 4:
                geom = geom[:, [0, 1, 3, 2]]  # DOLFINx quad facets are tensor-ordered; make them cyclic
            coords = mesh.geometry.x[geom]
        else:
            coords = np.empty((0, nv, 3))
        parts = mesh.comm.allgather(np.ascontiguousarray(coords, dtype=np.float64).reshape(-1, nv, 3))
        return np.concatenate(parts, axis=0)


# -------------------------------------------------------------------------------------------- building


_GMSH_READY = False
_GMSH_IMPORT = threading.Lock()


def _import_gmsh():
    """Import gmsh, also from a thread other than the main one.

    gmsh's Python module sets and restores the SIGINT handler while it loads, which Python allows in the main
    thread only; elsewhere (a run started from a worker thread) the import would fail. There, the import runs
    with `signal.signal` only reporting the current handler, so nothing is changed.
    """
    import sys

    if "gmsh" in sys.modules or threading.current_thread() is threading.main_thread():
        import gmsh

        return gmsh
    with _GMSH_IMPORT:
        real = signal.signal
        signal.signal = lambda sig, handler: signal.getsignal(sig)
        try:
            import gmsh
        finally:
            signal.signal = real
    return gmsh


def _gmsh():
    """The gmsh module, initialised once per process (gmsh 4.8 has no isInitialized())."""
    global _GMSH_READY
    gmsh = _import_gmsh()

    if not _GMSH_READY:
        gmsh.initialize([], False)
        _GMSH_READY = True
    gmsh.option.setNumber("General.Terminal", 0)
    return gmsh


def _split(n: int, k: int) -> list[int]:
    """Cell counts of the three strips [side, patch, side] of a centred patch of k cells among n."""
    if k > n or (n - k) % 2:
        raise MeshError(f"a patch of {k} cells cannot be centred among {n}")
    s = (n - k) // 2
    return [c for c in (s, k, s) if c > 0] if s else [k]


def _pseudo2d(gmsh, level: str, cell: str, size: float) -> None:
    lx, ly, lz = PSEUDO2D_BOX
    (nx, ny, nz), (px, py) = PSEUDO2D_LEVELS[level]
    geo = gmsh.model.geo
    sx, sy = _split(nx, px), _split(ny, py)
    xs = np.concatenate([[0], np.cumsum(sx)]) * lx / nx
    ys = np.concatenate([[0], np.cumsum(sy)]) * ly / ny
    structured = cell == "hexahedron"
    h = lx / nx if structured else size
    pts = {(i, j): geo.addPoint(xs[i], ys[j], 0.0, h) for i in range(len(xs)) for j in range(len(ys))}
    hl = {(i, j): geo.addLine(pts[i, j], pts[i + 1, j]) for i in range(len(sx)) for j in range(len(ys))}
    vl = {(i, j): geo.addLine(pts[i, j], pts[i, j + 1]) for i in range(len(xs)) for j in range(len(sy))}
    surfaces = {}
    for i in range(len(sx)):
        for j in range(len(sy)):
            loop = geo.addCurveLoop([hl[i, j], vl[i + 1, j], -hl[i, j + 1], -vl[i, j]])
            surfaces[i, j] = geo.addPlaneSurface([loop])
    if structured:
        for (i, _j), line in hl.items():
            geo.mesh.setTransfiniteCurve(line, sx[i] + 1)
        for (_i, j), line in vl.items():
            geo.mesh.setTransfiniteCurve(line, sy[j] + 1)
        for s in surfaces.values():
            geo.mesh.setTransfiniteSurface(s)
            geo.mesh.setRecombine(2, s)
    dimtags = [(2, s) for s in surfaces.values()]
    if structured:
        geo.extrude(dimtags, 0, 0, lz, numElements=[nz], recombine=True)
    else:
        geo.extrude(dimtags, 0, 0, lz)
    geo.synchronize()
    patch = (len(sx) // 2, len(sy) // 2)
    patch_surface = surfaces[patch]
    _tag_boundaries(
        gmsh,
        3,
        lambda c, tag: (
            ("bottom_wall" if tag == patch_surface else "inlet")
            if np.isclose(c[2], 0)
            else "outlet"
            if np.isclose(c[2], lz)
            else "walls"
            if (np.isclose(c[0], 0) or np.isclose(c[0], lx) or np.isclose(c[1], 0) or np.isclose(c[1], ly))
            else None
        ),
    )
    if not structured:
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)


def _wang2d(gmsh, cell: str) -> None:
    lx, ly = WANG2D_BOX
    nx, ny = WANG2D_CELLS
    geo = gmsh.model.geo
    p = [geo.addPoint(*xy, 0.0) for xy in ((0, 0), (lx, 0), (lx, ly), (0, ly))]
    lines = [geo.addLine(p[i], p[(i + 1) % 4]) for i in range(4)]
    s = geo.addPlaneSurface([geo.addCurveLoop(lines)])
    for k, line in enumerate(lines):
        geo.mesh.setTransfiniteCurve(line, (nx if k % 2 == 0 else ny) + 1)
    geo.mesh.setTransfiniteSurface(s)
    if cell == "quadrilateral":
        geo.mesh.setRecombine(2, s)
    geo.synchronize()
    _tag_boundaries(
        gmsh,
        2,
        lambda c, tag: "inlet" if np.isclose(c[1], 0) else "outlet" if np.isclose(c[1], ly) else "walls",
    )


def _cylinder(gmsh, size: float) -> None:
    d, h = CYLINDER["diameter"], CYLINDER["height"]
    gmsh.model.occ.addCylinder(0, 0, 0, 0, 0, h, d / 2)
    gmsh.model.occ.synchronize()
    _tag_boundaries(
        gmsh,
        3,
        lambda c, tag: "inlet" if np.isclose(c[2], 0) else "outlet" if np.isclose(c[2], h) else "walls",
    )
    gmsh.option.setNumber("Mesh.MeshSizeMax", size)
    gmsh.option.setNumber("Mesh.MeshSizeMin", size / 2)


def _box(gmsh, extent, cell: str, size: float) -> int:
    """A structured box [0, extent] of cells of about `size`; bottom (along gravity) `inlet`, top `outlet`."""
    extent = [float(e) for e in extent]
    dim = len(extent)
    n = [max(1, round(e / size)) for e in extent]
    geo = gmsh.model.geo
    p = [geo.addPoint(*xy, 0.0) for xy in ((0, 0), (extent[0], 0), (extent[0], extent[1]), (0, extent[1]))]
    lines = [geo.addLine(p[i], p[(i + 1) % 4]) for i in range(4)]
    s = geo.addPlaneSurface([geo.addCurveLoop(lines)])
    for k, line in enumerate(lines):
        geo.mesh.setTransfiniteCurve(line, n[k % 2] + 1)
    geo.mesh.setTransfiniteSurface(s)
    if cell in ("quadrilateral", "hexahedron"):
        geo.mesh.setRecombine(2, s)
    if dim == 3:
        geo.extrude([(2, s)], 0, 0, extent[2], numElements=[n[2]], recombine=cell == "hexahedron")
    geo.synchronize()
    up, top = dim - 1, extent[dim - 1]
    _tag_boundaries(
        gmsh, dim, lambda c, tag: "inlet" if np.isclose(c[up], 0) else "outlet" if np.isclose(c[up], top) else "walls"
    )
    return dim


def _tag_boundaries(gmsh, dim: int, classify) -> None:
    """Name the facet entities by the centre of their bounding box; one physical group for all cells."""
    groups: dict[str, list[int]] = {}
    for _, tag in gmsh.model.getEntities(dim - 1):
        bb = gmsh.model.getBoundingBox(dim - 1, tag)
        centre = 0.5 * (np.array(bb[:3]) + np.array(bb[3:]))
        name = classify(centre, tag)
        if name:
            groups.setdefault(name, []).append(tag)
    for k, name in enumerate(sorted(groups), start=1):
        gmsh.model.addPhysicalGroup(dim - 1, groups[name], k)
        gmsh.model.setPhysicalName(dim - 1, k, name)
    vols = [t for _, t in gmsh.model.getEntities(dim)]
    gmsh.model.addPhysicalGroup(dim, vols, 100)
    gmsh.model.setPhysicalName(dim, 100, "fluid")


def _check_builtin(name: str, level: str, cell: str | None, size: float) -> str:
    """Validate a built-in mesh request; return the cell type (default per geometry)."""
    if name not in GEOMETRIES:
        raise MeshError(f"unknown built-in mesh {name!r}; choose one of {', '.join(GEOMETRIES)}")
    cell = cell or {"pseudo2d": "hexahedron", "wang2d": "quadrilateral", "cylinder": "tetrahedron"}.get(name)
    allowed = {
        "pseudo2d": ("hexahedron", "tetrahedron"),
        "wang2d": ("quadrilateral", "triangle"),
        "cylinder": ("tetrahedron",),
        "box": ("hexahedron", "tetrahedron", "quadrilateral", "triangle"),
    }[name]
    cell = cell or "hexahedron"
    if cell not in allowed:
        raise MeshError(f"built-in mesh {name!r} comes in {', '.join(allowed)} cells, not {cell!r}")
    if name == "pseudo2d" and level not in PSEUDO2D_LEVELS:
        raise MeshError(f"pseudo2d level {level!r}: choose one of {', '.join(PSEUDO2D_LEVELS)}")
    if not size > 0:
        raise MeshError(f"mesh size must be > 0, got {size}")
    return cell


def _build_model(gmsh, name: str, level: str, cell: str, size: float, extent=None) -> int:
    """Build the geometry, meshing constraints and physical groups of `name`; return its dimension."""
    gmsh.clear()
    gmsh.model.add(name)
    if name == "box":
        if extent is None or len(extent) != (2 if cell in ("quadrilateral", "triangle") else 3):
            raise MeshError(f"box: extent must give one length per dimension of {cell} cells, got {extent}")
        return _box(gmsh, extent, cell, size)
    if name == "pseudo2d":
        _pseudo2d(gmsh, level, cell, size)
        return 3
    if name == "wang2d":
        _wang2d(gmsh, cell)
        return 2
    _cylinder(gmsh, size)
    return 3


def _atomic_write(gmsh, out: Path) -> Path:
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out, suffix=".tmp" + out.suffix) as tmp:  # gmsh picks the format by the extension
        gmsh.write(str(tmp))
    return out


def build_msh(
    name: str,
    out: str | os.PathLike,
    level: str = "coarse",
    cell: str | None = None,
    size: float = 0.005,
    extent=None,
) -> Path:
    """Mesh built-in geometry `name` with gmsh and write it to `out` (.msh 4.1, written atomically).

    `box` is a structured box [0, extent] (2 or 3 lengths, m) of cells of about `size`, with `inlet` at the
    bottom (y = 0 in 2D, z = 0 in 3D), `outlet` at the top and `walls` around.
    """
    cell = _check_builtin(name, level, cell, size)
    gmsh = _gmsh()
    try:
        dim = _build_model(gmsh, name, level, cell, size, extent)
        gmsh.model.mesh.generate(dim)
        gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
        return _atomic_write(gmsh, Path(out))
    finally:
        gmsh.clear()


# --------------------------------------------------------------------------------------------- loading


def load_msh(path: str | os.PathLike, comm=MPI.COMM_WORLD, gdim: int | None = None, cut: str = "columns") -> MeshData:
    """Read a gmsh `.msh` on rank 0 and distribute it: DOLFINx mesh, cell and facet tags, tag names.

    Args:
        path: the .msh file; its cells must form a physical group and its boundary facets should carry
            named physical groups.
        comm: communicator to distribute the mesh over.
        gdim: geometric dimension; by default 2 if every node has z = 0, else 3.
        cut: how the cells are shared among the ranks (`CUTS`): "columns", bisected across the horizontal
            axes only, or "blocks", across every axis (`_create_mesh_rcb`).
    """
    if cut not in CUTS:
        raise ValueError(f"cut: one of {', '.join(map(repr, CUTS))}, got {cut!r}")
    path = Path(path)
    err, names, dim = None, {}, 3
    gmsh = None
    if comm.rank == 0:
        if not path.is_file():
            err = f"mesh file not found: {path}"
        else:
            gmsh = _gmsh()
            gmsh.clear()
            try:
                gmsh.merge(str(path))
                tdim = gmsh.model.getDimension()
                for d, tag in gmsh.model.getPhysicalGroups(tdim - 1):
                    nm = gmsh.model.getPhysicalName(d, tag)
                    names[nm or f"tag{tag}"] = tag
                if not gmsh.model.getPhysicalGroups(tdim):
                    err = f"{path}: the cells carry no physical group (add one, e.g. Physical Volume('fluid'))"
                _, xyz, _ = gmsh.model.mesh.getNodes()
                dim = 2 if tdim == 2 and np.allclose(np.asarray(xyz)[2::3], 0) else 3
            except Exception as e:  # gmsh raises plain Exceptions with its own message
                err = f"{path}: gmsh cannot read it: {e}"
    err, names, dim = comm.bcast((err, names, dim), root=0)
    if err:
        if gmsh is not None:
            gmsh.clear()
        raise MeshError(err)
    try:
        mesh, ct, ft = _model_to_mesh(gmsh.model if comm.rank == 0 else None, comm, gdim or dim, cut)
    finally:
        if gmsh is not None:
            gmsh.clear()
    return MeshData(mesh=mesh, facet_tags=ft, cell_tags=ct, tags=names, source=str(path))


def _model_to_mesh(model, comm, gdim: int, cut: str = "columns"):
    """The DOLFINx mesh, cell tags and facet tags of the gmsh `model` held by rank 0 (None elsewhere) (collective).

    What `dolfinx.io.gmshio.model_to_mesh` does, with the cells distributed by `_create_mesh_rcb` (DOLFINx 0.5's
    model_to_mesh takes no partitioner): the cells of the highest dimension and their physical tags, and the
    facets of the dimension below with theirs, read on rank 0 by gmshio's `extract_geometry` and
    `extract_topology_and_markers`, reordered to DOLFINx's node order (`cell_perm_array`) and distributed by
    `dolfinx.mesh.create_mesh`; the tags follow through `distribute_entity_data`.
    """
    import dolfinx.graph
    import dolfinx.io.utils
    import dolfinx.mesh

    _import_gmsh()  # before gmshio, which imports gmsh too
    from dolfinx.io import gmshio

    root = 0
    has_facets = False
    cell_id = num_nodes = num_facet_nodes = None
    if comm.rank == root:
        x = gmshio.extract_geometry(model)
        topologies = gmshio.extract_topology_and_markers(model)
        kinds = {}  # gmsh element type -> (dimension, nodes per element)
        for element in topologies:
            _, edim, _, nn, _, _ = model.mesh.getElementProperties(element)
            kinds[element] = (edim, nn)
        by_dim = sorted(kinds, key=lambda e: kinds[e][0])
        cell_id = by_dim[-1]
        tdim, num_nodes = kinds[cell_id]
        cells = np.asarray(topologies[cell_id]["topology"], dtype=np.int64)
        cell_values = np.asarray(topologies[cell_id]["cell_data"], dtype=np.int32)
        has_facets = len(by_dim) > 1 and kinds[by_dim[-2]][0] == tdim - 1
        if has_facets:
            facet_id = by_dim[-2]
            num_facet_nodes = kinds[facet_id][1]
            facets = np.asarray(topologies[facet_id]["topology"], dtype=np.int64)
            facet_values = np.asarray(topologies[facet_id]["cell_data"], dtype=np.int32)
    cell_id, num_nodes, has_facets, num_facet_nodes = comm.bcast(
        (cell_id, num_nodes, has_facets, num_facet_nodes), root=root
    )
    if comm.rank != root:
        x = np.empty((0, gdim))
        cells = np.empty((0, num_nodes), dtype=np.int64)
        cell_values = np.empty(0, dtype=np.int32)
        if has_facets:
            facets = np.empty((0, num_facet_nodes), dtype=np.int64)
            facet_values = np.empty(0, dtype=np.int32)

    domain = gmshio.ufl_mesh(cell_id, gdim)
    cell_type = dolfinx.mesh.to_type(str(domain.ufl_cell()))
    cells = cells[:, gmshio.cell_perm_array(cell_type, num_nodes)]
    mesh = _create_mesh_rcb(comm, cells, x[:, :gdim], domain, cut=cut)
    topology = mesh.topology
    tdim = topology.dim

    entities, values = dolfinx.io.utils.distribute_entity_data(mesh, tdim, cells, cell_values)
    topology.create_connectivity(tdim, 0)
    cell_tags = dolfinx.mesh.meshtags_from_entities(
        mesh, tdim, dolfinx.graph.create_adjacencylist(entities), values.astype(np.int32)
    )
    cell_tags.name = "Cell tags"
    if has_facets:
        CT = dolfinx.mesh.CellType
        facet_type = {CT.triangle: CT.interval, CT.quadrilateral: CT.interval, CT.tetrahedron: CT.triangle,
                      CT.hexahedron: CT.quadrilateral}.get(cell_type)  # fmt: skip
        if facet_type is None:
            raise MeshError(f"{cell_type.name} cells are not supported: use triangles, quadrilaterals, tetrahedra "
                            "or hexahedra")  # fmt: skip
        facets = facets[:, gmshio.cell_perm_array(facet_type, num_facet_nodes)]
        entities, values = dolfinx.io.utils.distribute_entity_data(mesh, tdim - 1, facets, facet_values)
        topology.create_connectivity(tdim - 1, tdim)
        facet_tags = dolfinx.mesh.meshtags_from_entities(
            mesh, tdim - 1, dolfinx.graph.create_adjacencylist(entities), values.astype(np.int32)
        )
    else:
        empty = np.empty(0, dtype=np.int32)
        facet_tags = dolfinx.mesh.meshtags(mesh, tdim - 1, empty, empty)
    facet_tags.name = "Facet tags"
    return mesh, cell_tags, facet_tags


def rcb_owners(points: np.ndarray, nparts: int, axes: tuple[int, ...] | None = None) -> np.ndarray:
    """Recursive coordinate bisection: the part (0..nparts-1) of each point, halving the longest extent.

    Only `axes` are cut (default all). Deterministic (stable sorts, no random seed), balanced to one point.
    """
    owner = np.zeros(points.shape[0], dtype=np.int32)
    axes = tuple(range(points.shape[1])) if axes is None else tuple(axes)
    stack = [(np.arange(points.shape[0]), 0, int(nparts))]
    while stack:
        idx, first, k = stack.pop()
        if k == 1 or idx.size == 0:
            owner[idx] = first
            continue
        pts = points[idx]
        extent = pts.max(axis=0) - pts.min(axis=0)
        axis = axes[int(np.argmax(extent[list(axes)]))]
        order = idx[np.argsort(pts[:, axis], kind="stable")]
        k0 = k // 2
        m = (idx.size * k0) // k
        stack += [(order[:m], first, k0), (order[m:], first + k0, k - k0)]
    return owner


def _create_mesh_rcb(comm, cells, x, domain, *args, cut: str = "columns", **kwargs):
    """`dolfinx.mesh.create_mesh` with cells distributed by recursive coordinate bisection of their centroids.

    With cut = "columns" only the horizontal directions are cut (febed's gravity is along the last axis), so a
    bed resting at the bottom of a tall mesh is shared between the ranks instead of falling to the lowest one
    (particles owned by the ranks of their cells). With "blocks" every axis is cut: compact parts with the
    smallest halos, for runs whose particles are shared by their own work (`[run] particle_partition`).

    DOLFINx 0.5's default parallel partitioner (PT-SCOTCH) gives a different partition from run to run
    (message timing), so two runs on the same ranks, or a run and its restart, would differ at round-off
    and a fluidized bed's chaos would amplify that. RCB on rank 0 (which holds every cell) is reproducible;
    the cell's owner and, with ghosting, the owners of its neighbours are its destinations.
    """
    import dolfinx.graph
    import dolfinx.mesh

    if comm.rank == 0:  # columns: cut across the directions normal to gravity (the last axis)
        centroids = np.asarray(x)[np.asarray(cells)].mean(axis=1)
        gdim = np.asarray(x).shape[1]
        columns = cut == "columns" and gdim > 1
        owner = rcb_owners(centroids, comm.size, axes=tuple(range(gdim - 1)) if columns else None)
    else:
        owner = None
    owner = comm.bcast(owner, root=0)

    def partition(_comm, nparts, graph, ghosting):
        n = graph.num_nodes
        first = comm.exscan(n) or 0  # the graph's rows are cells first..first+n-1 of the input order
        own = owner[first : first + n]
        if not ghosting:
            return dolfinx.graph.create_adjacencylist(own.astype(np.int32), np.arange(n + 1, dtype=np.int32))
        row = np.repeat(np.arange(n), np.diff(graph.offsets))
        nbr = owner[graph.array]
        keep = nbr != own[row]
        pairs = np.unique(np.stack([row[keep], nbr[keep]], axis=1), axis=0)  # (cell, ghost rank), sorted
        count = 1 + np.bincount(pairs[:, 0], minlength=n)
        offsets = np.concatenate([[0], np.cumsum(count)]).astype(np.int32)
        dest = np.empty(offsets[-1], dtype=np.int32)
        dest[offsets[:-1]] = own  # the owner first, then the ranks that ghost the cell
        mask = np.ones(offsets[-1], dtype=bool)
        mask[offsets[:-1]] = False
        dest[mask] = pairs[:, 1]
        return dolfinx.graph.create_adjacencylist(dest, offsets)

    kwargs["partitioner"] = dolfinx.mesh.create_cell_partitioner(partition)
    return dolfinx.mesh.create_mesh(comm, cells, x, domain, *args, **kwargs)


def builtin_msh_path(name: str, level: str, cell: str, size: float, cache_dir: Path, extent=()) -> Path:
    """Path of the cached .msh of a built-in mesh (built on rank 0 on first use)."""
    tag = f"{name}-{level}-{cell}" if name == "pseudo2d" and cell == "hexahedron" else f"{name}-{cell}"
    if cell == "tetrahedron" or name == "box":
        tag += f"-h{size:g}"
    if name == "pseudo2d" and cell != "hexahedron":
        tag = f"{name}-{cell}-h{size:g}"
    if name == "box":
        tag += "-" + "x".join(f"{e:g}" for e in extent)
    return cache_dir / f"{tag}.msh"


def case_cut(case) -> str:
    """How a case's cells are shared among ranks: "blocks" for a coupled run whose particles are shared by work."""
    return "blocks" if case.run.mode == "cfd-dem" and case.run.particle_partition == "work" else "columns"


def load_case_mesh(case, comm=MPI.COMM_WORLD, cache_dir: Path | None = None) -> MeshData:
    """The mesh a validated case names (`[mesh] file` or `builtin`), checked against its boundary tags.

    Args:
        case: a validated `Case`.
        comm: the MPI communicator the mesh is distributed over.
        cache_dir: where a built-in mesh's .msh file is written (default: `mesh/` in the case's output folder).

    Returns:
        `MeshData`: the distributed DOLFINx mesh with its facet and cell tags, the facet tags by name.

    Raises:
        MeshError: a missing or unreadable mesh file, or a boundary naming a tag the mesh lacks.
    """
    m = case.mesh
    cut = case_cut(case)
    if m.file:
        md = load_msh(case.resolve_path(m.file), comm, cut=cut)
    else:
        cell = m.cell
        flat = m.builtin == "wang2d" or (m.builtin == "box" and len(m.extent) == 2)
        if flat and cell in ("hexahedron", "tetrahedron"):
            cell = "quadrilateral" if cell == "hexahedron" else "triangle"
        cache_dir = cache_dir or (case.output_dir() / "mesh")
        path = builtin_msh_path(m.builtin, m.level, cell, m.size, cache_dir, m.extent)
        err = None
        if comm.rank == 0 and not path.is_file():
            try:
                build_msh(m.builtin, path, level=m.level, cell=cell, size=m.size, extent=m.extent or None)
            except MeshError as e:
                err = str(e)
        err = comm.bcast(err, root=0)
        if err:
            raise MeshError(f"[mesh] builtin = {m.builtin!r}: {err}")
        md = load_msh(path, comm, cut=cut)
    md.require_tags(list(case.boundary), "[gas.boundary.*]")
    for tag, b in case.boundary.items():  # the keys that name other tags
        for key in ("cross_section_tags", "wins_over"):
            md.require_tags(list(b.as_dict().get(key) or ()), f"[gas.boundary.{tag}] {key}")
    return md


def mesh_volume(md: MeshData) -> float:
    """Total volume (area in 2D) of the mesh, summed over ranks with compensated summation."""
    import math

    import dolfinx.fem
    import dolfinx.fem.petsc
    import ufl

    dg0 = dolfinx.fem.FunctionSpace(md.mesh, ("DG", 0))
    v = ufl.TestFunction(dg0)
    vec = dolfinx.fem.petsc.assemble_vector(dolfinx.fem.form(v * ufl.dx))
    n_owned = md.mesh.topology.index_map(md.mesh.topology.dim).size_local
    local = vec.array[:n_owned].copy()
    vec.destroy()
    return math.fsum(np.concatenate(md.comm.allgather(local)))


def facet_area(md: MeshData, name: str) -> float:
    """Total area (length in 2D) of the facets tagged `name`, summed over ranks."""
    import dolfinx.fem

    one = dolfinx.fem.Constant(md.mesh, 1.0)
    local = dolfinx.fem.assemble_scalar(dolfinx.fem.form(one * md.ds([name])))
    return md.comm.allreduce(local, op=MPI.SUM)


def global_cell_count(md: MeshData) -> int:
    """Number of cells of the whole mesh."""
    imap = md.mesh.topology.index_map(md.mesh.topology.dim)
    return imap.size_global
