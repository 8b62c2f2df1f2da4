"""The recursive coordinate bisection of particle positions (`febed.parallel.boxes`), serially and on K ranks.

Checked: the boxes tile space (every point lies in exactly one, the one `owner` names, however far outside
the particles); the weight each rank's box holds is the mean to within a few particles' weight, for any rank
count; 2D cuts never cross z; the ghost lists hold exactly the points within the reach of each other box.
"""

from mpi4py import MPI

import numpy as np
import pytest

from febed.parallel.boxes import BIN_SHARE, bisect, box_ghost_targets

pytestmark = pytest.mark.mpi
COMM = MPI.COMM_WORLD


def cloud(n, seed, dim=3):
    """A bed-like cloud on this rank: dense at the bottom, sparse above, weights 1-10."""
    rng = np.random.default_rng(seed + 1000 * COMM.rank)
    pos = rng.uniform([0, 0, 0], [0.08, 0.015, 0.25], (n, 3))
    pos[: n // 2, 2] *= 0.2
    if dim == 2:
        pos[:, 2] = 0.0
    return pos, rng.integers(1, 11, n).astype(float)


def inside(boxes, pts):
    """(points, ranks) boolean: point in box [lo, hi) (the cut convention: x < cut goes to the lower box)."""
    lo, hi = boxes[None, :, 0, :], boxes[None, :, 1, :]
    p = pts[:, None, :]
    return np.all((p >= lo) & ((p < hi) | np.isposinf(hi)), axis=2)


@pytest.mark.parametrize("dim", [3, 2])
def test_boxes_tile_space_and_balance_the_weight(dim):
    pos, w = cloud(4000, 3, dim)
    tree = bisect(COMM, pos, w, dim=dim)
    again = bisect(COMM, pos, w, dim=dim)
    assert np.array_equal(tree.cut, again.cut, equal_nan=True)  # deterministic
    probe = np.random.default_rng(9).uniform([-1, -1, -1], [1, 1, 1], (5000, 3))  # mostly far outside the bed
    for pts in (pos, probe):
        hit = inside(tree.boxes, pts)
        assert np.all(hit.sum(axis=1) == 1)
        assert np.array_equal(np.argmax(hit, axis=1), tree.owner(pts))
    per_rank = np.zeros(COMM.size)
    np.add.at(per_rank, tree.owner(pos), w)
    COMM.Allreduce(MPI.IN_PLACE, per_rank, op=MPI.SUM)
    mean = per_rank.sum() / COMM.size
    print(f"weight per rank / mean: {np.round(per_rank / mean, 4).tolist()}")
    assert np.abs(per_rank - mean).max() <= 30.0  # a few particles of weight <= 10 (the cut's resolution)
    if dim == 2:
        assert np.all(np.isinf(tree.boxes[:, :, 2]))  # no cut across z


def test_a_far_outlier_does_not_spoil_the_balance():
    # one particle 1 km away stretches the first histogram's bins to 4 m: more rounds refine the cut
    pos, w = cloud(4000, 5)
    if COMM.rank == 0:
        pos[0] = [1000.0, 0.0, 1000.0]
    tree = bisect(COMM, pos, w)
    per_rank = np.zeros(COMM.size)
    np.add.at(per_rank, tree.owner(pos), w)
    COMM.Allreduce(MPI.IN_PLACE, per_rank, op=MPI.SUM)
    # each cut's bin holds at most BIN_SHARE of its group's weight (two rounds alone: bins of 15 mm, 6 % of it)
    assert np.abs(per_rank - per_rank.sum() / COMM.size).max() <= BIN_SHARE * per_rank.sum()


def test_one_rank_box_is_everything_and_empty_ranks_still_tile():
    pos, w = cloud(300 if COMM.rank == 0 else 0, 4)  # every particle on rank 0
    tree = bisect(COMM, pos, w)
    probe = np.random.default_rng(2).uniform(-1, 1, (1000, 3))
    assert np.all(inside(tree.boxes, probe).sum(axis=1) == 1)
    none = bisect(COMM, np.zeros((0, 3)))  # no particle anywhere: boxes cut at the middle, still a tiling
    assert np.all(inside(none.boxes, probe).sum(axis=1) == 1)


def test_ghost_lists_hold_the_points_within_reach_of_each_other_box():
    rng = np.random.default_rng(1)
    lo = np.array([[-np.inf, -np.inf, -np.inf], [0.5, -np.inf, -np.inf], [0.5, 0.5, -np.inf]])
    hi = np.array([[0.5, np.inf, np.inf], [np.inf, 0.5, np.inf], [np.inf, np.inf, np.inf]])
    pts = rng.uniform(0, 1, (3000, 3))
    reach = 0.07
    for me in range(3):
        start, rows = box_ghost_targets(pts, pts.shape[0], lo, hi, me, reach)
        for r in range(3):
            d = np.maximum(np.maximum(lo[r] - pts, 0.0), pts - hi[r])
            want = np.flatnonzero(np.sum(d * d, axis=1) <= reach**2) if r != me else np.zeros(0, dtype=np.int64)
            assert np.array_equal(np.sort(rows[start[r] : start[r + 1]]), want), (me, r)
