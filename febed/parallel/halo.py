"""Which ranks need a ghost copy of a particle: a static bin table over the mesh partition (seed 001 sec 2.5).

Rank r needs a copy of every particle whose centre lies within the halo width h (>= largest diameter + skin)
of r's owned cells. The domain is covered by a uniform grid of bins; bin b carries the bit set of the ranks
whose owned cells, each inflated by h around its bounding box, overlap b (64 ranks per int64 word, as many
words as the rank count needs). A particle in bin b is sent as a
ghost to those ranks (except its owner). The table is a superset of the exact halo (bounding boxes, whole
bins), which costs a few extra ghosts and never misses a contact. It depends only on the partition and h,
so it is built once (collectively) and again only if the halo must grow.
"""

from __future__ import annotations

from mpi4py import MPI

import numpy as np
from numba import njit

MAX_BINS = 4_000_000
WORD = 64  # ranks per int64 word of a bin's bit set: rank r is bit r % 64 of word r // 64


@njit(cache=True)
def _mark(bbox, n_cells, h, lo, size, dims, word, bit, mask):
    """Set `bit` of word `word` of mask (nbins, words) in the bins overlapped by each cell box [lo - h, hi + h]."""
    for c in range(n_cells):
        k0 = np.empty(3, dtype=np.int64)
        k1 = np.empty(3, dtype=np.int64)
        for a in range(3):
            k0[a] = min(max(int((bbox[c, 0, a] - h - lo[a]) / size), 0), dims[a] - 1)
            k1[a] = min(max(int((bbox[c, 1, a] + h - lo[a]) / size), 0), dims[a] - 1)
        for i in range(k0[0], k1[0] + 1):
            for j in range(k0[1], k1[1] + 1):
                for k in range(k0[2], k1[2] + 1):
                    b = (i * dims[1] + j) * dims[2] + k
                    mask[b, word] |= bit


@njit(cache=True)
def bin_of(pos, n, lo, size, dims, out):
    """Bin index of pos[:n] (clamped into the grid)."""
    for p in range(n):
        b = 0
        for a in range(3):
            k = int((pos[p, a] - lo[a]) / size) if pos[p, a] > lo[a] else 0
            b = b * dims[a] + min(k, dims[a] - 1)
        out[p] = b


@njit(cache=True)
def ghost_targets(pos, n, lo, size, dims, mask, me, nr):
    """Send lists (start (nr+1,), rows, stray): rows[start[r]:start[r+1]] are the particles rank r needs.

    mask: (nbins, words) bit sets (rank r: bit r % 64 of word r // 64). stray counts the particles whose own
    bin lacks `me`'s bit (outside this rank's halo region: possible only for particles outside the mesh).
    """
    counts = np.zeros(nr, dtype=np.int64)
    start = np.zeros(nr + 1, dtype=np.int64)
    myword = me // WORD
    mybit = np.int64(1) << (me % WORD)
    stray = 0
    bins = np.empty(n, dtype=np.int64)
    bin_of(pos, n, lo, size, dims, bins)
    for p in range(n):
        b = bins[p]
        if not mask[b, myword] & mybit:
            stray += 1
        for w in range(mask.shape[1]):
            m = mask[b, w] & ~mybit if w == myword else mask[b, w]
            if m == 0:
                continue
            for k in range(min(WORD, nr - w * WORD)):
                if m & (np.int64(1) << k):
                    counts[w * WORD + k] += 1
    start[0] = 0
    for r in range(nr):
        start[r + 1] = start[r] + counts[r]
    rows = np.empty(start[nr], dtype=np.int64)
    fill = start[:nr].copy()
    for p in range(n):
        b = bins[p]
        for w in range(mask.shape[1]):
            m = mask[b, w] & ~mybit if w == myword else mask[b, w]
            if m == 0:
                continue
            for k in range(min(WORD, nr - w * WORD)):
                if m & (np.int64(1) << k):
                    r = w * WORD + k
                    rows[fill[r]] = p
                    fill[r] += 1
    return start, rows, stray


def neighbour_ranks(masks: np.ndarray, me: int, nr: int) -> list[int]:
    """The ranks other than `me` present in any of the bit sets masks (nbins, words), in increasing order."""
    union = np.bitwise_or.reduce(masks, axis=0) if masks.shape[0] else np.zeros(masks.shape[1], dtype=np.int64)
    return [r for r in range(nr) if r != me and (int(union[r // WORD]) >> (r % WORD)) & 1]


class HaloTable:
    """Bin grid over the global mesh box with, per bin, the bit set of ranks whose halo covers it.

    Attributes:
        width: halo width h (m) the table was built for.
        lo, size, dims: grid origin (3,), bin size (m) and bins per direction (3,).
        mask: (nbins, words) int64 rank bit sets (rank r: bit r % 64 of word r // 64); neighbours: ranks
            sharing at least one bin with this one.
    """

    def __init__(self, comm, bbox: np.ndarray, n_owned_cells: int, width: float):
        """Build collectively from the owned cells' bounding boxes (nc, 2, 3) for halo width `width` (m)."""
        if not width > 0:
            raise ValueError(f"width: the halo width must be > 0 (m), got {width}")
        self.comm = comm
        self.width = float(width)
        own = bbox[:n_owned_cells]
        lo_l = own[:, 0, :].min(axis=0) if n_owned_cells else np.full(3, np.inf)
        hi_l = own[:, 1, :].max(axis=0) if n_owned_cells else np.full(3, -np.inf)
        lo = np.empty(3)
        hi = np.empty(3)
        comm.Allreduce(lo_l, lo, op=MPI.MIN)
        comm.Allreduce(hi_l, hi, op=MPI.MAX)
        lo -= self.width
        hi += self.width
        size = self.width
        while True:
            dims = np.maximum(np.ceil((hi - lo) / size).astype(np.int64), 1)
            if int(np.prod(dims)) <= MAX_BINS:
                break
            size *= 1.25
        self.lo, self.size, self.dims = lo, float(size), dims
        words = (comm.size + WORD - 1) // WORD
        local = np.zeros((int(np.prod(dims)), words), dtype=np.int64)
        word, bit = comm.rank // WORD, np.int64(1) << (comm.rank % WORD)
        _mark(np.ascontiguousarray(bbox), n_owned_cells, self.width, lo, self.size, dims, word, bit, local)
        self.mask = np.zeros_like(local)
        comm.Allreduce(local, self.mask, op=MPI.BOR)
        self.neighbours = neighbour_ranks(self.mask[local[:, word] != 0], comm.rank, comm.size)

    def targets(self, pos: np.ndarray, n: int):
        """(start (nranks+1,), rows, stray count): the ghost send lists of particles pos[:n]."""
        return ghost_targets(pos, n, self.lo, self.size, self.dims, self.mask, self.comm.rank, self.comm.size)
