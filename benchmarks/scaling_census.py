"""A census of the work of each rank of a coupled run on P ranks, computed on one process (for scaling_projection.py).

For a case's mesh and a particle snapshot, and a number of parts P, the census repeats febed's decomposition:

* cells: `febed.meshing.rcb_owners` on the cell centroids, cutting the horizontal axes only, on the cells in the
  order the mesh reader hands them to DOLFINx (the partition a run on P ranks gets); or, for a gas partition
  decoupled from the particles, cutting every axis (compact blocks);
* gas nodes (the Q1 nodes are the mesh vertices): each rank holds its owned cells and, as ghosts, the cells
  sharing a facet with them (DOLFINx's shared-facet ghost mode); a vertex of the cells of k ranks counts 1/k
  to each (DOLFINx spreads the shared vertices evenly: 13,979 and 13,993 owned nodes of 27,972 on 2 ranks of
  the intermediate mesh); the halo of a rank is its local vertices that it does not own (the values it
  receives at each scatter), its neighbours the other ranks owning cells that touch its local vertices;
* particles: owned by the rank owning the cell holding their centre; ghost copies go to every other rank whose
  owned cells, each cell's bounding box inflated by the halo width 1.2 (d_max + skin), overlap the particle's
  bin of a grid of bins of that width (`febed.parallel.halo`, the same kernel);
* pairs: every pair among a rank's owned and ghost particles closer than r_i + r_j + skin is listed (the
  rank's `PairList.size`); the forces are computed for the pairs with at least one owned particle.
"""

from __future__ import annotations

from pathlib import Path
from unittest import mock

from mpi4py import MPI

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

import febed.meshing as meshing
from febed.case import load_case
from febed.parallel.halo import MAX_BINS, _mark


class HexGrid:
    """A mesh of axis-aligned hexahedra on a tensor grid (the built-in pseudo-2D meshes), in reader order.

    Attributes: cells (nc, 8) vertex indices, x (nn, 3) vertex coordinates, centroid (nc, 3), bbox (nc, 2, 3),
    axes: the grid lines along x, y, z; ijk_cell: cell index by grid position (nx, ny, nz).
    """

    def __init__(self, cells: np.ndarray, x: np.ndarray):
        self.cells = np.asarray(cells, dtype=np.int64)
        x = np.asarray(x, dtype=np.float64)
        self.x = np.pad(x, ((0, 0), (0, 3 - x.shape[1])))
        used = np.unique(self.cells)
        xc = self.x[self.cells]
        self.centroid = xc.mean(axis=1)
        self.bbox = np.ascontiguousarray(np.stack([xc.min(axis=1), xc.max(axis=1)], axis=1))
        self.num_nodes = used.size
        self.axes = [np.unique(np.round(self.x[used, a], 12)) for a in range(3)]
        dims = tuple(a.size - 1 for a in self.axes)
        if self.cells.shape[1] != 8 or int(np.prod(dims)) != self.cells.shape[0]:
            raise ValueError(
                f"mesh: the census needs hexahedra on a tensor grid, got {self.cells.shape[0]} cells "
                f"of {self.cells.shape[1]} vertices on grid lines {[a.size for a in self.axes]}"
            )
        ijk = [np.searchsorted(self.axes[a], np.round(self.bbox[:, 0, a], 12)) for a in range(3)]
        self.ijk_cell = np.full(dims, -1, dtype=np.int64)
        self.ijk_cell[ijk[0], ijk[1], ijk[2]] = np.arange(self.cells.shape[0])
        if (self.ijk_cell < 0).any():
            raise ValueError("mesh: the cells do not fill the tensor grid of their vertices")
        inc = sparse.csr_matrix(
            (np.ones(self.cells.size), (np.repeat(np.arange(self.cells.shape[0]), 8), self.cells.ravel())),
            shape=(self.cells.shape[0], self.x.shape[0]),
        )
        shared = (inc @ inc.T).tocoo()
        face = (shared.data == 4) & (shared.row != shared.col)  # hexahedra sharing a facet share 4 vertices
        self.facet_nbr = (shared.row[face], shared.col[face])

    def locate(self, pos: np.ndarray) -> np.ndarray:
        """Cell of each point (nearest cell for points outside the grid)."""
        ijk = [np.clip(np.searchsorted(self.axes[a], pos[:, a]) - 1, 0, self.axes[a].size - 2) for a in range(3)]
        return self.ijk_cell[ijk[0], ijk[1], ijk[2]]


def case_mesh(case_path: str | Path, cache_dir: Path) -> HexGrid:
    """The mesh of a case as `febed.meshing.load_case_mesh` hands it to DOLFINx (cells in reader order)."""
    case = load_case(case_path)
    got = {}
    original = meshing._create_mesh_rcb

    def capture(comm, cells, x, domain, *args, **kwargs):
        got["cells"], got["x"] = np.array(cells), np.array(x)
        return original(comm, cells, x, domain, *args, **kwargs)

    with mock.patch.object(meshing, "_create_mesh_rcb", capture):
        meshing.load_case_mesh(case, MPI.COMM_SELF, cache_dir=cache_dir)
    return HexGrid(got["cells"], got["x"])


def partition(mesh: HexGrid, nparts: int, axes: tuple[int, ...] = (0, 1)) -> np.ndarray:
    """Owner part of each cell: febed's partition on `nparts` ranks (cut across the horizontal axes), or one
    cutting `axes` (0, 1, 2: compact blocks, for a gas partition that particles need not follow)."""
    return meshing.rcb_owners(mesh.centroid, nparts, axes=axes)


def node_census(mesh: HexGrid, owner: np.ndarray, nparts: int) -> dict[str, np.ndarray]:
    """Per part: owned cells, ghost cells, owned nodes, halo (ghost) nodes, neighbour parts of the halo."""
    nc = mesh.cells.shape[0]
    a, b = mesh.facet_nbr
    cross = owner[a] != owner[b]
    # ghost cells of part p: cells not owned by p sharing a facet with a cell p owns
    ghost = sparse.csr_matrix((np.ones(int(cross.sum()), dtype=bool), (owner[b[cross]], a[cross])), shape=(nparts, nc))
    out = {k: np.zeros(nparts) for k in ("cells", "ghost_cells", "nodes", "halo", "halo_nbrs")}
    out["cells"][:] = np.bincount(owner, minlength=nparts)
    # parts touching each vertex (through their owned cells): a vertex of k parts counts 1/k to each
    touch = np.unique(np.stack([mesh.cells.ravel(), np.repeat(owner, 8)], axis=1), axis=0)
    k = np.bincount(touch[:, 0], minlength=mesh.x.shape[0])
    out["nodes"][:] = np.bincount(touch[:, 1], weights=1.0 / k[touch[:, 0]], minlength=nparts)
    for p in range(nparts):
        gc = ghost.indices[ghost.indptr[p] : ghost.indptr[p + 1]]
        out["ghost_cells"][p] = np.unique(gc).size
        local = np.unique(np.concatenate([mesh.cells[owner == p].ravel(), mesh.cells[gc].ravel()]))
        out["halo"][p] = local.size - out["nodes"][p]
        nbrs = touch[np.isin(touch[:, 0], local), 1]
        out["halo_nbrs"][p] = np.unique(nbrs).size - 1
    return out


class HaloBins:
    """febed's ghost rule for a partition: per part, the bins its inflated owned cells overlap.

    `part_boxes` (nparts, 2, 3) replaces the owned cells by one box per part (a decomposition of the
    particles that does not follow the cells, `work_census`), clipped to the mesh.
    """

    def __init__(self, mesh: HexGrid, owner: np.ndarray, nparts: int, width: float, part_boxes=None):
        lo = mesh.bbox[:, 0, :].min(axis=0) - width
        hi = mesh.bbox[:, 1, :].max(axis=0) + width
        size = width
        while True:
            dims = np.maximum(np.ceil((hi - lo) / size).astype(np.int64), 1)
            if int(np.prod(dims)) <= MAX_BINS:
                break
            size *= 1.25
        self.lo, self.size, self.dims = lo, float(size), dims
        self.marked = np.zeros((nparts, int(np.prod(dims))), dtype=bool)
        lo_mesh, hi_mesh = mesh.bbox[:, 0, :].min(axis=0), mesh.bbox[:, 1, :].max(axis=0)
        for p in range(nparts):
            if part_boxes is None:
                box = np.ascontiguousarray(mesh.bbox[owner == p])
            else:
                box = np.clip(part_boxes[p], lo_mesh, hi_mesh)[None].copy()
            m = np.zeros((self.marked.shape[1], 1), dtype=np.int64)
            _mark(box, box.shape[0], width, lo, self.size, dims, 0, np.int64(1), m)
            self.marked[p] = m[:, 0] != 0

    def bins(self, pos: np.ndarray) -> np.ndarray:
        k = np.clip(((pos - self.lo) / self.size).astype(np.int64), 0, self.dims - 1)
        k[pos <= self.lo] = 0
        return (k[:, 0] * self.dims[1] + k[:, 1]) * self.dims[2] + k[:, 2]


def particle_census(
    mesh: HexGrid,
    owner: np.ndarray,
    nparts: int,
    halo: HaloBins,
    pos: np.ndarray,
    diameter: np.ndarray,
    skin: float,
    pairs: tuple[np.ndarray, np.ndarray],
) -> dict[str, np.ndarray]:
    """Per part: owned and ghost particles, ghosts sent, listed pairs, force pairs, ghost neighbour parts."""
    powner = owner[mesh.locate(pos)]
    b = halo.bins(pos)
    i, j = pairs
    keys = ("owned", "ghosts", "sent", "pairs", "force_pairs", "ghost_nbrs")
    out = {k: np.zeros(nparts, dtype=np.int64) for k in keys}
    out["owned"][:] = np.bincount(powner, minlength=nparts)
    for p in range(nparts):
        member = halo.marked[p][b]
        g = member & (powner != p)
        out["ghosts"][p] = int(g.sum())
        out["ghost_nbrs"][p] = np.unique(powner[g]).size
        send_to = halo.marked[:, b[powner == p]]  # (nparts, owned particles of p)
        send_to[p] = False
        out["sent"][p] = int(send_to.sum())
        rows = member | (powner == p)
        listed = rows[i] & rows[j]
        out["pairs"][p] = int(listed.sum())
        out["force_pairs"][p] = int((listed & ((powner[i] == p) | (powner[j] == p))).sum())
    out["powner"] = powner
    return out


def weighted_rcb(points: np.ndarray, weights: np.ndarray, nparts: int, axes: tuple[int, ...]):
    """Recursive coordinate bisection balancing summed weights: part of each point and each part's box.

    Each cut halves the longest extent (of `axes`) of its points where the cumulative weight reaches the
    share of the parts on the lower side; the boxes are the cut planes (unbounded at the outer faces).
    """
    owner = np.zeros(points.shape[0], dtype=np.int32)
    boxes = np.empty((nparts, 2, points.shape[1]))
    inf = np.full(points.shape[1], np.inf)
    stack = [(np.arange(points.shape[0]), 0, int(nparts), -inf, inf)]
    while stack:
        idx, first, k, lo, hi = stack.pop()
        if k == 1:
            owner[idx] = first
            boxes[first] = lo, hi
            continue
        k0 = k // 2
        if idx.size == 0:
            axis, cut = axes[0], lo[axes[0]] if np.isfinite(lo[axes[0]]) else 0.0
            left = right = idx
        else:
            pts = points[idx]
            axis = axes[int(np.argmax(np.ptp(pts[:, list(axes)], axis=0)))]
            order = idx[np.argsort(points[idx, axis], kind="stable")]
            cw = np.cumsum(weights[order])
            m = int(np.searchsorted(cw, cw[-1] * k0 / k))
            x = points[order, axis]
            cut = x[m] if m == 0 else (x[-1] if m >= x.size else 0.5 * (x[m - 1] + x[m]))
            left, right = order[:m], order[m:]
        hi_l, lo_r = hi.copy(), lo.copy()
        hi_l[axis] = lo_r[axis] = cut
        stack += [(left, first, k0, lo, hi_l), (right, first + k0, k - k0, lo_r, hi)]
    return owner, boxes


def work_census(
    mesh: HexGrid,
    cell_owner: np.ndarray,
    nparts: int,
    pos: np.ndarray,
    pairs: tuple[np.ndarray, np.ndarray],
    width: float,
    axes: tuple[int, ...] = (0, 2),
    cells: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """The particle census of a decomposition of the particles by DEM work, decoupled from the mesh's.

    Particles are owned by a weighted RCB of their positions (weight: the listed pairs a particle is in,
    half each, plus 0.1 for its own integration), cutting `axes` (default the width and the height: compact
    parts instead of columns), re-cut at every snapshot. Ghosts follow febed's rule with each part's box in
    place of its cells (`HaloBins`). The coupling stays with the gas partition: a particle whose cell
    another rank owns goes there at every gas step and its forces come back (`transfer_out`, `transfer_in`,
    `transfer_nbrs`); `cell_owner` is the owner of each particle's cell.

    With `cells` (each particle's cell) it also counts, for a coupling done by the particles' owners, the
    nodes of their particles' cells that other ranks' cells hold (`foreign_nodes`: the gas values a rank
    receives and the nodal sums it sends back each gas step) and those ranks (`node_nbrs`).
    """
    i, j = pairs
    deg = np.bincount(np.concatenate([i, j]), minlength=pos.shape[0])
    owner, boxes = weighted_rcb(pos, 0.1 + 0.5 * deg, nparts, axes)
    halo = HaloBins(mesh, None, nparts, width, part_boxes=boxes)
    near = halo.marked[:, halo.bins(pos)]  # (nparts, particles): inside the part's inflated box's bins
    keys = ("owned", "ghosts", "sent", "pairs", "force_pairs", "ghost_nbrs", "transfer_out", "transfer_in")
    extra = ("transfer_nbrs", "foreign_nodes", "node_nbrs") if cells is not None else ("transfer_nbrs",)
    out = {k: np.zeros(nparts, dtype=np.int64) for k in (*keys, *extra)}
    out["owned"][:] = np.bincount(owner, minlength=nparts)
    for p in range(nparts):
        g = near[p] & (owner != p)
        out["ghosts"][p] = int(g.sum())
        out["ghost_nbrs"][p] = np.unique(owner[g]).size
        to = near[:, owner == p]
        to[p] = False
        out["sent"][p] = int(to.sum())
        rows = near[p] | (owner == p)
        listed = rows[i] & rows[j]
        out["pairs"][p] = int(listed.sum())
        out["force_pairs"][p] = int((listed & ((owner[i] == p) | (owner[j] == p))).sum())
        away = (owner == p) & (cell_owner != p)
        come = (cell_owner == p) & (owner != p)
        out["transfer_out"][p] = int(away.sum())
        out["transfer_in"][p] = int(come.sum())
        out["transfer_nbrs"][p] = np.unique(np.concatenate([cell_owner[away], owner[come]])).size
        if cells is not None:
            out["foreign_nodes"][p] = np.unique(mesh.cells[cells[away]]).size
            out["node_nbrs"][p] = np.unique(cell_owner[away]).size
    out["powner"] = owner
    return out


def all_pairs(pos: np.ndarray, diameter: np.ndarray, skin: float) -> tuple[np.ndarray, np.ndarray]:
    """Every pair i < j closer than r_i + r_j + skin (the pair list's criterion)."""
    r = 0.5 * diameter
    ij = cKDTree(pos).query_pairs(2 * r.max() + skin, output_type="ndarray")
    d = np.linalg.norm(pos[ij[:, 0]] - pos[ij[:, 1]], axis=1)
    keep = d < r[ij[:, 0]] + r[ij[:, 1]] + skin
    return ij[keep, 0], ij[keep, 1]


if __name__ == "__main__":
    print("scaling_census.py is the census library of scaling_projection.py: run that script")
