"""Mesh partition helpers: the owner rank of each local cell, and a deterministic slab partitioner (tests, benchmarks).

Particles belong to the rank owning the cell that holds their centre, so the particle decomposition is the
mesh partition DOLFINx made (ParMETIS/SCOTCH/KaHIP by default).
"""

from __future__ import annotations

import numpy as np


def cell_owners(mesh) -> np.ndarray:
    """Owner rank (int32) of each local cell, owned cells first then ghosts (DOLFINx local order)."""
    tdim = mesh.topology.dim
    imap = mesh.topology.index_map(tdim)
    own = np.full(imap.size_local + imap.num_ghosts, mesh.comm.rank, dtype=np.int32)
    own[imap.size_local :] = imap.owners
    return own


def _destinations(graph, owner, offset: int, ghosting: bool):
    """The destinations DOLFINx's partitioner returns for this rank's cells of the dual `graph`.

    Cell c (global index offset + c) goes first to `owner(global index)`, then, with `ghosting`, to the other
    owners of its neighbours.
    """
    from dolfinx import cpp

    own = owner(np.arange(offset, offset + graph.num_nodes, dtype=np.int64))
    data = []
    offs = [0]
    for c in range(graph.num_nodes):
        d = [int(own[c])]
        if ghosting:
            for nb in graph.links(c):
                r = int(owner(np.int64(nb)))
                if r not in d:
                    d.append(r)
        data += d
        offs.append(len(data))
    return cpp.graph.AdjacencyList_int32(np.array(data, dtype=np.int32), np.array(offs, dtype=np.int32))


def slab_partitioner(period: int | None = None):
    """A DOLFINx cell partitioner giving rank r the r-th block of global cell indices, with ghosts.

    The blocks are slabs across the slowest cell index, so the partition boundaries are known planes (for tests
    and reproducible benchmarks): z = const on `dolfinx.mesh.create_box` hexahedra (x fastest), x = const on
    `dolfinx.mesh.create_rectangle` quadrilaterals (y fastest). With `period` = the number of cells along the
    fastest axis (x in 3D, y in 2D), the blocks are taken of the index modulo `period`: slabs across that axis.
    `block_partitioner` cuts along several axes at once.
    """
    if period is not None and period < 1:
        raise ValueError(f"period: must be >= 1 (cells along the fastest axis: x in 3D, y in 2D), got {period}")
    import dolfinx.mesh

    def part(comm, nparts, graph, ghosting):
        n = graph.num_nodes
        off = comm.exscan(n) or 0
        tot = comm.allreduce(n)

        def owner(c):
            return (c % period) * nparts // period if period else c * nparts // tot

        return _destinations(graph, owner, off, ghosting)

    return dolfinx.mesh.create_cell_partitioner(part)


def block_partitioner(cells, blocks):
    """A DOLFINx cell partitioner cutting a `dolfinx.mesh.create_box`/`create_rectangle` mesh into a grid of blocks.

    cells: cells along each axis of the mesh, (nx, ny, nz) or (nx, ny); blocks: blocks along each axis, e.g.
    (2, 2, 1) for four columns meeting at a line, (2, 2, 2) for eight blocks meeting at a point, or
    `mpi4py.MPI.Compute_dims(nranks, 3)` for any rank count. Block (bx, by, bz) goes to rank
    (bz * blocks_y + by) * blocks_x + bx (by * blocks_x + bx in 2D); the mesh must be partitioned on as many ranks
    as there are blocks. Block bx holds the cells [bx * nx // blocks_x, (bx + 1) * nx // blocks_x) along x, and so
    on: where nx is a multiple of blocks_x, the partition boundaries are the planes x = k lx / blocks_x (for tests
    and benchmarks whose particles must sit at partition corners).

    Raises ValueError for cells and blocks of different lengths or more blocks than cells along an axis, and (at
    the partitioning) when the number of blocks is not the number of ranks.
    """
    cells = [int(c) for c in cells]
    blocks = [int(b) for b in blocks]
    if len(cells) not in (2, 3) or len(blocks) != len(cells):
        raise ValueError(f"cells, blocks: need 2 or 3 numbers each, one per axis, got {cells} and {blocks}")
    if min(cells) < 1 or min(blocks) < 1 or any(b > c for b, c in zip(blocks, cells, strict=True)):
        raise ValueError(f"blocks: need 1 <= blocks <= cells along each axis, got blocks {blocks} for cells {cells}")
    import dolfinx.mesh

    nb = int(np.prod(blocks))

    fastest_first = [1, 0] if len(cells) == 2 else [0, 1, 2]  # create_rectangle: y fastest; create_box: x fastest
    stride = np.cumprod([1] + blocks[:-1])  # rank = sum over axes of block index * stride

    def owner(c):
        """Rank of global cell indices c, in the order create_box/create_rectangle number the cells."""
        rank = np.zeros_like(c)
        for a in fastest_first:
            rank += (c % cells[a]) * blocks[a] // cells[a] * stride[a]
            c = c // cells[a]
        return rank

    def part(comm, nparts, graph, ghosting):
        if nparts != nb:
            raise ValueError(f"blocks: {blocks} make {nb} blocks, but the mesh is partitioned on {nparts} ranks")
        n = graph.num_nodes
        off = comm.exscan(n) or 0
        return _destinations(graph, owner, off, ghosting)

    return dolfinx.mesh.create_cell_partitioner(part)
