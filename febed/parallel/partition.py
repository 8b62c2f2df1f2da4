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


def slab_partitioner(period: int | None = None):
    """A DOLFINx cell partitioner giving rank r the r-th block of global cell indices, with ghosts.

    On `dolfinx.mesh.create_box` hexahedra/quadrilaterals the blocks are slabs across the slowest index (z in 3D,
    y in 2D), so the partition boundaries are known planes (for tests and reproducible benchmarks). With
    `period` = the number of cells along x, the blocks are taken of the index modulo `period`: slabs across x.
    """
    if period is not None and period < 1:
        raise ValueError(f"period: must be >= 1 (cells along x), got {period}")
    import dolfinx.mesh
    from dolfinx import cpp

    def part(comm, nparts, graph, ghosting):
        n = graph.num_nodes
        off = comm.exscan(n) or 0
        tot = comm.allreduce(n)

        def owner(c):
            return (c % period) * nparts // period if period else c * nparts // tot

        own = owner(np.arange(off, off + n, dtype=np.int64))
        data = []
        offs = [0]
        for c in range(n):
            d = [int(own[c])]
            if ghosting:
                for nb in graph.links(c):
                    r = int(owner(int(nb)))
                    if r not in d:
                        d.append(r)
            data += d
            offs.append(len(data))
        return cpp.graph.AdjacencyList_int32(np.array(data, dtype=np.int32), np.array(offs, dtype=np.int32))

    return dolfinx.mesh.create_cell_partitioner(part)
