"""Plain arrays extracted once from a DOLFINx mesh for the coupling hot path (setup half of the coupling).

Everything the Numba kernels of `febed.coupling` need is here as numpy arrays: cell -> dof connectivity of
the scalar nodal space Q (P1 / Q1), dof coordinates, face adjacency for the walk, bounding boxes and a
uniform-grid index for the fallback search, node control volumes ΔV_i = ∫φ_i dx (lumped), cell volumes and
each cell's share ∫_K φ_i dx of its nodes' control volumes (neighbour filter, seed 001 eqs 31-34).

Reference-cell conventions are DOLFINx's (basix): vertex k of a quadrilateral/hexahedron sits at the bits of
k (bit 0 -> ξ, bit 1 -> η, bit 2 -> ζ); facet k of a simplex is opposite vertex k. Local numbering: owned
cells/dofs first, then ghosts. In 2D every volume is an area times `depth` (m), so volumes are always m^3.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from mpi4py import MPI

import numpy as np
from numba import njit

# Cell kinds used by the kernels (ints, so they can be passed to Numba).
TRIANGLE, QUADRILATERAL, TETRAHEDRON, HEXAHEDRON = 0, 1, 2, 3
CELL_KINDS = {
    "triangle": TRIANGLE,
    "quadrilateral": QUADRILATERAL,
    "tetrahedron": TETRAHEDRON,
    "hexahedron": HEXAHEDRON,
}
NUM_VERTICES = {TRIANGLE: 3, QUADRILATERAL: 4, TETRAHEDRON: 4, HEXAHEDRON: 8}
NUM_FACETS = {TRIANGLE: 3, QUADRILATERAL: 4, TETRAHEDRON: 4, HEXAHEDRON: 6}

# Neighbour codes in `cell_nbr` for facets without a neighbour cell.
NBR_DOMAIN_BOUNDARY = -1  # facet on the boundary of the whole domain
NBR_PARTITION_BOUNDARY = -2  # facet on the boundary of this rank's local (owned + ghost) mesh only


@dataclass
class MeshArrays:
    """Plain-array view of the mesh and the nodal space Q, built once per run by `extract_mesh_arrays`.

    Attributes:
        gdim: geometric dimension (2 or 3).
        kind: cell kind (TRIANGLE, QUADRILATERAL, TETRAHEDRON, HEXAHEDRON).
        cell_dofs: (nc, nv) int32, local dofs of Q per cell (owned + ghost cells), reference vertex order.
        num_owned_cells: cells [0, num_owned_cells) are owned by this rank.
        x_dofs: (nd, 3) float64, dof coordinates (m), z = 0 in 2D.
        num_owned_dofs: dofs [0, num_owned_dofs) are owned by this rank.
        cell_affine: (nc,) bool, quadrilateral/hexahedron whose map is affine (True for every simplex).
        cell_nbr: (nc, nf) int32, cell across reference facet k, or NBR_DOMAIN_BOUNDARY / NBR_PARTITION_BOUNDARY.
        cell_facets: (nc, nf) int32, local topology facet index of reference facet k (for facet tags).
        bbox: (nc, 2, 3) float64, min/max corners of each cell (m).
        grid_origin, grid_h: (3,) float64, uniform search grid origin and bin size (m).
        grid_n: (3,) int64, bins per direction.
        grid_start: (nbins + 1,) int64 CSR offsets; grid_cells: cells overlapping each bin.
        cell_volume: (nc,) float64, |K| (m^3; area * depth in 2D).
        cell_node_share: (nc, nv) float64, ∫_K φ_i dx (m^3): cell K's share of its node i's control volume.
        node_volume: (nd,) float64, ΔV_i = ∫φ_i dx summed over ranks; owned and ghost dofs hold the full value.
        depth: 2D depth (m) turning areas into volumes (1.0 in 3D, unused).
        comm: the mesh communicator; index_map: DOLFINx IndexMap of Q's dofs (for ghost updates).
    """

    gdim: int
    kind: int
    cell_dofs: np.ndarray
    num_owned_cells: int
    x_dofs: np.ndarray
    num_owned_dofs: int
    cell_affine: np.ndarray
    cell_nbr: np.ndarray
    cell_facets: np.ndarray
    bbox: np.ndarray
    grid_origin: np.ndarray
    grid_h: np.ndarray
    grid_n: np.ndarray
    grid_start: np.ndarray
    grid_cells: np.ndarray
    cell_volume: np.ndarray
    cell_node_share: np.ndarray
    node_volume: np.ndarray
    depth: float
    comm: Any = None
    index_map: Any = None
    _vectors: dict = field(default_factory=dict, repr=False)

    @property
    def num_cells(self) -> int:
        """Number of local cells (owned + ghost)."""
        return self.cell_dofs.shape[0]

    @property
    def num_dofs(self) -> int:
        """Number of local dofs (owned + ghost)."""
        return self.x_dofs.shape[0]

    @property
    def parallel(self) -> bool:
        """True when the mesh is distributed over more than one rank."""
        return self.comm is not None and self.comm.size > 1

    def accumulate(self, nodal: np.ndarray) -> np.ndarray:
        """Sum per-rank nodal contributions over ranks in place (reverse scatter, add; then forward scatter).

        After it, owned and ghost dofs hold the full sum. `nodal` is (nd,) or (nd, k); a no-op in serial.
        """
        if not self.parallel:
            return nodal
        vec = self._vector(1 if nodal.ndim == 1 else nodal.shape[1])
        import dolfinx.la

        vec.array[:] = nodal.reshape(-1)
        vec.scatter_reverse(dolfinx.la.ScatterMode.add)
        vec.scatter_forward()
        nodal.reshape(-1)[:] = vec.array
        return nodal

    def update_ghosts(self, nodal: np.ndarray) -> np.ndarray:
        """Copy owned values to the ghost dofs of other ranks in place (forward scatter); no-op in serial."""
        if not self.parallel:
            return nodal
        vec = self._vector(1 if nodal.ndim == 1 else nodal.shape[1])
        vec.array[:] = nodal.reshape(-1)
        vec.scatter_forward()
        nodal.reshape(-1)[:] = vec.array
        return nodal

    def owned_sum(self, nodal: np.ndarray) -> np.ndarray:
        """Sum over the owned dofs of every rank (collective): a float for (nd,), a (k,) array for (nd, k)."""
        local = np.asarray(nodal[: self.num_owned_dofs].sum(axis=0), dtype=np.float64)
        if self.comm is None:
            return local
        out = np.zeros_like(np.atleast_1d(local))
        self.comm.Allreduce(np.atleast_1d(local), out, op=MPI.SUM)
        return out if nodal.ndim > 1 else float(out[0])

    def filter_weights(self) -> tuple[np.ndarray, np.ndarray]:
        """(gather, scatter), both (nc, nv): S_{K,j}/ΔV_j and S_{K,i}/|K| of the neighbour filter (cached).

        Computed once with the divisions of the filter's formula (seed 001 eqs 31-34, `febed.coupling.projection`),
        so a filter pass only multiplies and adds.
        """
        if "filter" not in self._vectors:
            gather = self.cell_node_share / self.node_volume[self.cell_dofs]
            scatter = self.cell_node_share * (1.0 / self.cell_volume)[:, None]
            self._vectors["filter"] = (gather, scatter)
        return self._vectors["filter"]

    def _vector(self, bs: int):
        if bs not in self._vectors:
            import dolfinx.la

            self._vectors[bs] = dolfinx.la.vector(self.index_map, bs)
        return self._vectors[bs]


# ------------------------------------------------------------------------------------ geometry helpers


def _gauss2(dim: int) -> tuple[np.ndarray, np.ndarray]:
    """2-point Gauss rule per direction on [0, 1]^dim: points (nq, dim) and weights (nq,)."""
    g = np.array([0.5 - 0.5 / np.sqrt(3.0), 0.5 + 0.5 / np.sqrt(3.0)])
    pts = np.array(np.meshgrid(*([g] * dim), indexing="ij")).reshape(dim, -1).T
    return pts, np.full(pts.shape[0], 0.5**dim)


def _tensor_basis(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Q1 basis values (nq, nv) and reference gradients (nq, nv, dim) at points xi (nq, dim), DOLFINx order."""
    nq, dim = xi.shape
    nv = 2**dim
    phi = np.ones((nq, nv))
    dphi = np.ones((nq, nv, dim))
    for k in range(nv):
        for a in range(dim):
            bit = (k >> a) & 1
            f = xi[:, a] if bit else 1.0 - xi[:, a]
            df = 1.0 if bit else -1.0
            phi[:, k] *= f
            for b in range(dim):
                dphi[:, k, b] *= df if a == b else f
    return phi, dphi


def cell_geometry(kind: int, xc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cell measures (nc,) and exact shares ∫_K φ_i dx (nc, nv) from vertex coordinates xc (nc, nv, gdim)."""
    nc, nv, gdim = xc.shape
    if kind in (TRIANGLE, TETRAHEDRON):
        tdim = nv - 1
        jac = xc[:, 1:, :] - xc[:, :1, :]  # (nc, tdim, gdim)
        if tdim == gdim:
            det = np.abs(np.linalg.det(jac))
        else:  # manifold (not used by febed, kept general)
            det = np.sqrt(np.abs(np.linalg.det(jac @ jac.transpose(0, 2, 1))))
        vol = det / (1.0 if tdim == 1 else (2.0 if tdim == 2 else 6.0))
        return vol, np.repeat((vol / nv)[:, None], nv, axis=1)
    tdim = 2 if kind == QUADRILATERAL else 3
    pts, w = _gauss2(tdim)  # exact: φ_i |det J| has degree <= 3 per direction
    phi, dphi = _tensor_basis(pts)
    jac = np.einsum("cvg,qvt->cqgt", xc, dphi)  # (nc, nq, gdim, tdim)
    det = np.abs(np.linalg.det(jac))  # (nc, nq)
    share = np.einsum("q,qv,cq->cv", w, phi, det)
    return share.sum(axis=1), share


# ------------------------------------------------------------------------------------ search grid


@njit(cache=True)
def _grid_fill(bbox, origin, h, n, start, cells, count_only):
    """Count (count_only) or fill the CSR lists of cells whose bounding box overlaps each grid bin."""
    fill = np.zeros(start.size - 1, dtype=np.int64)
    for c in range(bbox.shape[0]):
        lo = np.empty(3, dtype=np.int64)
        hi = np.empty(3, dtype=np.int64)
        for a in range(3):
            lo[a] = min(max(int(np.floor((bbox[c, 0, a] - origin[a]) / h[a])), 0), n[a] - 1)
            hi[a] = min(max(int(np.floor((bbox[c, 1, a] - origin[a]) / h[a])), 0), n[a] - 1)
        for i in range(lo[0], hi[0] + 1):
            for j in range(lo[1], hi[1] + 1):
                for k in range(lo[2], hi[2] + 1):
                    b = (i * n[1] + j) * n[2] + k
                    if count_only:
                        start[b + 1] += 1
                    else:
                        cells[start[b] + fill[b]] = c
                        fill[b] += 1


def _build_grid(bbox: np.ndarray, gdim: int):
    """Uniform grid over the local mesh, bins about one mean cell size wide, with the cells overlapping each bin."""
    lo = bbox[:, 0, :].min(axis=0)
    hi = bbox[:, 1, :].max(axis=0)
    ext = np.maximum(hi - lo, 1e-300)
    mean_size = np.mean(bbox[:, 1, :gdim] - bbox[:, 0, :gdim], axis=0)
    n = np.ones(3, dtype=np.int64)
    n[:gdim] = np.clip(np.ceil(ext[:gdim] / np.maximum(mean_size, 1e-300)).astype(np.int64), 1, 1 << 20)
    # keep the number of bins near the number of cells
    while np.prod(n) > 4 * bbox.shape[0] + 8:
        n[:gdim] = np.maximum(n[:gdim] // 2, 1)
    h = ext / n
    h[gdim:] = 1.0
    origin = lo.copy()
    origin[gdim:] = -0.5
    start = np.zeros(int(np.prod(n)) + 1, dtype=np.int64)
    _grid_fill(bbox, origin, h, n, start, np.zeros(0, dtype=np.int32), True)
    np.cumsum(start, out=start)
    cells = np.empty(int(start[-1]), dtype=np.int32)
    _grid_fill(bbox, origin, h, n, start, cells, False)
    return origin, h, n, start, cells


# ------------------------------------------------------------------------------------ extraction


def extract_mesh_arrays(mesh, Q=None, depth: float = 1.0) -> MeshArrays:
    """Extract the coupling arrays of `mesh` and its scalar P1/Q1 space `Q` (built if None) once per run.

    Args:
        mesh: dolfinx.mesh.Mesh of triangles, quadrilaterals, tetrahedra or hexahedra (affine geometry).
        Q: dolfinx.fem.FunctionSpace(mesh, ("Lagrange", 1)); created when None.
        depth: 2D only: depth (m) turning cell areas into volumes (docs/theory.md, 2D cases); ignored in 3D.

    Returns:
        MeshArrays; collective over the mesh communicator.
    """
    import dolfinx.fem
    import dolfinx.mesh

    name = dolfinx.mesh.to_string(mesh.topology.cell_type)
    if name not in CELL_KINDS:
        raise ValueError(f"mesh: cell type {name!r} is not supported; use one of {', '.join(CELL_KINDS)}")
    kind = CELL_KINDS[name]
    gdim = mesh.geometry.dim
    tdim = mesh.topology.dim
    if gdim != tdim:
        raise ValueError(f"mesh: geometric dimension {gdim} must equal the topological dimension {tdim}")
    if gdim == 2 and not depth > 0.0:
        raise ValueError(f"depth: must be > 0 (m) for a 2D mesh, got {depth}")
    if Q is None:
        Q = dolfinx.fem.FunctionSpace(mesh, ("Lagrange", 1))
    nv = NUM_VERTICES[kind]
    if Q.dofmap.index_map_bs != 1 or Q.dofmap.dof_layout.num_dofs != nv:
        raise ValueError("Q: must be the scalar Lagrange degree-1 space (P1/Q1) of the mesh")

    comm = mesh.comm
    cell_map = mesh.topology.index_map(tdim)
    nc = cell_map.size_local + cell_map.num_ghosts
    cell_dofs = np.ascontiguousarray(Q.dofmap.list.array.reshape(-1, nv)[:nc], dtype=np.int32)
    x_dofs = np.ascontiguousarray(Q.tabulate_dof_coordinates(), dtype=np.float64)
    dof_map = Q.dofmap.index_map
    if gdim == 2:
        x_dofs[:, 2] = 0.0

    # face adjacency in reference facet order
    mesh.topology.create_connectivity(tdim, tdim - 1)
    mesh.topology.create_connectivity(tdim - 1, tdim)
    nf = NUM_FACETS[kind]
    c2f = mesh.topology.connectivity(tdim, tdim - 1)
    f2c = mesh.topology.connectivity(tdim - 1, tdim)
    cell_facets = np.ascontiguousarray(c2f.array.reshape(-1, nf)[:nc], dtype=np.int32)
    f2c_off, f2c_arr = f2c.offsets, f2c.array
    nfac = f2c_off.size - 1
    other = np.full((nfac, 2), -1, dtype=np.int64)
    cnt = np.diff(f2c_off)
    other[:, 0] = f2c_arr[f2c_off[:-1]]
    two = cnt == 2
    other[two, 1] = f2c_arr[f2c_off[:-1][two] + 1]
    exterior = np.zeros(nfac, dtype=bool)
    exterior[dolfinx.mesh.exterior_facet_indices(mesh.topology)] = True
    cf = cell_facets.astype(np.int64)
    cid = np.arange(nc)[:, None]
    nbr = np.where(other[cf, 0] == cid, other[cf, 1], other[cf, 0])
    lonely = nbr < 0
    nbr[lonely] = np.where(exterior[cf[lonely]], NBR_DOMAIN_BOUNDARY, NBR_PARTITION_BOUNDARY)
    cell_nbr = np.ascontiguousarray(nbr, dtype=np.int32)

    xc = x_dofs[cell_dofs][:, :, :gdim]
    bbox = np.zeros((nc, 2, 3))
    bbox[:, 0, :gdim] = xc.min(axis=1)
    bbox[:, 1, :gdim] = xc.max(axis=1)
    grid = _build_grid(bbox, gdim)

    vol, share = cell_geometry(kind, xc)
    cell_affine = np.ones(nc, dtype=np.bool_)
    if kind in (QUADRILATERAL, HEXAHEDRON):  # affine iff every vertex is x0 + Σ_b bit_b(k) (x_{2^b} - x0)
        edges = xc[:, [1 << b for b in range(tdim)], :] - xc[:, :1, :]
        bits = np.array([[(k >> b) & 1 for b in range(tdim)] for k in range(nv)], dtype=float)
        pred = xc[:, :1, :] + np.einsum("kb,cbg->ckg", bits, edges)
        size = np.abs(edges).max(axis=(1, 2))
        cell_affine = np.abs(pred - xc).max(axis=(1, 2)) <= 1e-11 * size  # rounding-level deviations
    scale = depth if gdim == 2 else 1.0
    vol = vol * scale
    share = share * scale
    node_volume = np.zeros(x_dofs.shape[0])
    nown = cell_map.size_local
    np.add.at(node_volume, cell_dofs[:nown].ravel(), share[:nown].ravel())
    ma = MeshArrays(
        gdim=gdim,
        kind=kind,
        cell_dofs=cell_dofs,
        num_owned_cells=nown,
        x_dofs=x_dofs,
        num_owned_dofs=dof_map.size_local,
        cell_affine=cell_affine,
        cell_nbr=cell_nbr,
        cell_facets=cell_facets,
        bbox=bbox,
        grid_origin=grid[0],
        grid_h=grid[1],
        grid_n=grid[2],
        grid_start=grid[3],
        grid_cells=grid[4],
        cell_volume=np.ascontiguousarray(vol),
        cell_node_share=np.ascontiguousarray(share),
        node_volume=node_volume,
        depth=float(depth) if gdim == 2 else 1.0,
        comm=comm,
        index_map=dof_map,
    )
    ma.accumulate(ma.node_volume)
    return ma


def facet_tag_lookup(mesh, facet_tags) -> np.ndarray:
    """Tag value of every local facet (-1 if untagged), to name the facet a particle left through.

    Use with `locate`: `lookup[exit_facet[p]]` for particles with status OUTSIDE_DOMAIN (e.g. the outlet id).
    """
    tdim = mesh.topology.dim
    mesh.topology.create_entities(tdim - 1)
    imap = mesh.topology.index_map(tdim - 1)
    lookup = np.full(imap.size_local + imap.num_ghosts, -1, dtype=np.int32)
    lookup[facet_tags.indices] = facet_tags.values
    return lookup
