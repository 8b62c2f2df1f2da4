"""Particle ownership by boxes: a weighted recursive coordinate bisection (RCB) of the particle positions.

The ranks' boxes tile space (the outermost extend to infinity, so every point has an owner). `bisect` builds
them collectively: the box of a group of n ranks is cut by a plane across the longest extent of the particles
it holds into two boxes for n // 2 and n - n // 2 ranks, at the coordinate where the particles' weight
divides in that ratio; the two halves are cut in turn until each box has one rank (Berger and Bokhari 1987,
IEEE Trans. Comput. 36; the particle partition of LIGGGHTS/LAMMPS `balance rcb` works the same way). The
weighted quantile is found by rounds of a `HIST_BINS`-bin histogram reduced over the ranks, each refining the
bin that holds it, until that bin holds at most `BIN_SHARE` of the weight (two rounds for a bed; more when a
far outlier stretches the bins): a few reductions per level whatever the number of particles.

`box_ghost_targets` lists, for each other rank, the particles within a halo width of its box: the ghost
copies that rank needs for the contacts across the box faces.
"""

from __future__ import annotations

from dataclasses import dataclass

from mpi4py import MPI

import numpy as np
from numba import njit

HIST_BINS = 256
BIN_SHARE = 1e-3  # the cut's bin holds at most this share of its group's weight (else another round) ...
MAX_ROUNDS = 4  # ... within this many rounds


@dataclass
class BoxTree:
    """The bisection: inner nodes cut along `axis` at `cut` (x < cut: `left`), leaves hold a rank.

    Attributes:
        axis, cut, left, right: per node; axis -1 at a leaf.
        rank: per node, the leaf's rank (-1 at inner nodes).
        boxes: (ranks, 2, 3) each rank's box [lo, hi] (±inf where it reaches the outside).
    """

    axis: np.ndarray
    cut: np.ndarray
    left: np.ndarray
    right: np.ndarray
    rank: np.ndarray
    boxes: np.ndarray

    def owner(self, pos: np.ndarray) -> np.ndarray:
        """Rank (int64) of the box holding each point of pos (n, 3)."""
        pos = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
        node = np.zeros(pos.shape[0], dtype=np.int64)
        while True:
            inner = np.flatnonzero(self.axis[node] >= 0)
            if inner.size == 0:
                return self.rank[node].astype(np.int64)
            nd = node[inner]
            go_left = pos[inner, self.axis[nd]] < self.cut[nd]
            node[inner] = np.where(go_left, self.left[nd], self.right[nd])


def _cut_fraction(comm, slot, x, w, lo, hi, frac):
    """Per group g, the coordinate below which frac[g] of the group's weight lies (histogram rounds).

    slot: group of each particle (-1: none), x: its coordinate along its group's axis, lo/hi: the groups'
    extents along that axis. Each round refines the bin holding the quantile, until that bin holds at most
    `BIN_SHARE` of its group's weight (a far outlier stretches the first round's bins) or `MAX_ROUNDS` are
    made. Collective (one reduction per round, the same decisions on every rank).
    """
    groups = lo.size
    a, b = lo.copy(), hi.copy()
    below = np.zeros(groups)
    target = total = None
    for _ in range(MAX_ROUNDS):
        width = np.where(b > a, b - a, 1.0)
        h = np.zeros((groups, HIST_BINS))
        sel = slot >= 0
        s = slot[sel]
        k = np.floor((x[sel] - a[s]) / width[s] * HIST_BINS)
        inside = (k >= 0) & (k < HIST_BINS)
        np.add.at(h, (s[inside], k[inside].astype(np.int64)), w[sel][inside])
        if target is None:  # the first round covers every particle of the group: its total weight
            hi_edge = (x[sel] - a[s]) >= width[s]
            np.add.at(h[:, HIST_BINS - 1], s[hi_edge], w[sel][hi_edge])
        comm.Allreduce(MPI.IN_PLACE, h, op=MPI.SUM)
        if target is None:
            total = h.sum(axis=1)
            target = frac * total
        cum = below[:, None] + np.cumsum(h, axis=1)
        k = np.array([min(int(np.searchsorted(cum[g], target[g] * (1 - 1e-12))), HIST_BINS - 1) for g in range(groups)])
        step = width / HIST_BINS
        below = np.where(k > 0, cum[np.arange(groups), np.maximum(k - 1, 0)], below)
        a, b = a + k * step, a + (k + 1) * step
        if np.all(h[np.arange(groups), k] <= BIN_SHARE * total):
            break
    return b


def _inside(lo: float, hi: float) -> float:
    """A coordinate inside the interval [lo, hi] (either end may be infinite)."""
    if np.isfinite(lo) and np.isfinite(hi):
        return 0.5 * (lo + hi)
    if np.isfinite(lo):
        return lo + 1.0
    return hi - 1.0 if np.isfinite(hi) else 0.0


def bisect(comm, pos: np.ndarray, weights: np.ndarray | None = None, dim: int = 3) -> BoxTree:
    """The RCB of this rank's points pos (n, 3) with `weights` (n,) (default 1) together with every rank's (collective).

    The cut axes are the first `dim` (x, y in 2D). A group whose box holds no particle at all is cut at its
    box's middle (or at 0 where the box is unbounded).
    """
    pos = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
    w = np.ones(pos.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    size = comm.size
    axis, cut, left, right, rank = [-1], [np.nan], [-1], [-1], [-1]
    ranks = [(0, size)]
    box = [np.array([[-np.inf] * 3, [np.inf] * 3])]
    at = np.zeros(pos.shape[0], dtype=np.int64)  # each point's node
    active = [0] if size > 1 else []
    if size == 1:
        rank[0] = 0
    while active:
        groups = len(active)
        slot_of = np.full(len(axis), -1, dtype=np.int64)
        slot_of[active] = np.arange(groups)
        slot = slot_of[at]
        lo = np.full((groups, 3), np.inf)
        hi = np.full((groups, 3), -np.inf)
        sel = slot >= 0
        np.minimum.at(lo, slot[sel], pos[sel])
        np.maximum.at(hi, slot[sel], pos[sel])
        comm.Allreduce(MPI.IN_PLACE, lo, op=MPI.MIN)
        comm.Allreduce(MPI.IN_PLACE, hi, op=MPI.MAX)
        empty = ~np.all(hi >= lo, axis=1)
        ax = np.argmax(np.where(empty[:, None], 0.0, hi - lo)[:, :dim], axis=1)
        frac = np.array([((r1 - r0) // 2) / (r1 - r0) for r0, r1 in (ranks[g] for g in active)])
        g_idx = np.arange(groups)
        x = pos[np.arange(pos.shape[0]), ax[np.maximum(slot, 0)]] if pos.shape[0] else np.zeros(0)
        c = _cut_fraction(comm, slot, x, w, np.where(empty, 0.0, lo[g_idx, ax]), np.where(empty, 0.0, hi[g_idx, ax]),
                          frac)  # fmt: skip
        new_active = []
        for g, node in enumerate(active):
            a = int(ax[g])
            if empty[g]:
                c[g] = _inside(box[node][0, a], box[node][1, a])
            r0, r1 = ranks[node]
            mid = r0 + (r1 - r0) // 2
            axis[node], cut[node] = a, float(c[g])
            for part, (q0, q1) in enumerate(((r0, mid), (mid, r1))):
                b = box[node].copy()
                b[1 - part, a] = c[g]
                axis.append(-1), cut.append(np.nan), left.append(-1), right.append(-1)
                rank.append(q0 if q1 - q0 == 1 else -1)
                ranks.append((q0, q1))
                box.append(b)
                child = len(axis) - 1
                if part == 0:
                    left[node] = child
                else:
                    right[node] = child
                if q1 - q0 > 1:
                    new_active.append(child)
            mine = at == node
            at[mine] = np.where(pos[mine, a] < c[g], left[node], right[node])
        active = new_active
    rank_arr = np.asarray(rank, dtype=np.int64)
    boxes = np.empty((size, 2, 3))
    for node in np.flatnonzero(rank_arr >= 0):
        boxes[rank_arr[node]] = box[node]
    return BoxTree(np.asarray(axis, dtype=np.int64), np.asarray(cut), np.asarray(left, dtype=np.int64),
                   np.asarray(right, dtype=np.int64), rank_arr, boxes)  # fmt: skip


@njit(cache=True)
def _near(pos, p, lo, hi, r, r2):
    """Whether point p of pos lies within sqrt(r2) of box r [lo[r], hi[r]]."""
    d2 = 0.0
    for a in range(3):
        d = max(lo[r, a] - pos[p, a], 0.0, pos[p, a] - hi[r, a])
        d2 += d * d
    return d2 <= r2


@njit(cache=True)
def box_ghost_targets(pos, n, lo, hi, me, reach):
    """Send lists (start (nr+1,), rows): rows[start[r]:start[r+1]] are the points pos[:n] within `reach` of box r.

    lo, hi: (nr, 3) the ranks' boxes; rank `me` (the owner) gets none.
    """
    nr = lo.shape[0]
    r2 = reach * reach
    counts = np.zeros(nr, dtype=np.int64)
    near = np.zeros(n, dtype=np.bool_)  # whether a point is near any other box
    for p in range(n):
        for r in range(nr):
            if r != me and _near(pos, p, lo, hi, r, r2):
                counts[r] += 1
                near[p] = True
    start = np.zeros(nr + 1, dtype=np.int64)
    for r in range(nr):
        start[r + 1] = start[r] + counts[r]
    rows = np.empty(start[nr], dtype=np.int64)
    fill = start[:nr].copy()
    for p in range(n):
        if near[p]:
            for r in range(nr):
                if r != me and _near(pos, p, lo, hi, r, r2):
                    rows[fill[r]] = p
                    fill[r] += 1
    return start, rows
