"""The ghost bin table for any rank count: bit sets of several int64 words against plain Python integers."""

import numpy as np
import pytest

from febed.parallel.halo import WORD, _mark, ghost_targets, neighbour_ranks


def python_targets(bins, masks, me, nr):
    """Reference send lists: masks[b] is a Python int with bit r set when rank r needs bin b's particles."""
    send = {r: [p for p, b in enumerate(bins) if r != me and masks[b] >> r & 1] for r in range(nr)}
    stray = sum(1 for b in bins if not masks[b] >> me & 1)
    return send, stray


@pytest.mark.parametrize("nr", [2, 63, 64, 65, 130, 1000])
def test_ghost_targets_match_python_integers_for_any_rank_count(nr):
    rng = np.random.default_rng(nr)
    dims = np.array([4, 3, 5])
    nb = int(np.prod(dims))
    words = (nr + WORD - 1) // WORD
    # a few ranks per bin, rank 0, 63, 64 and the last included somewhere: every word and the sign bit
    ranks_of = [set(rng.choice(nr, size=min(nr, 4), replace=False)) for _ in range(nb)]
    for b, r in enumerate([0, min(63, nr - 1), min(64, nr - 1), nr - 1]):
        ranks_of[b].add(r)
    mask = np.zeros((nb, words), dtype=np.int64)
    for b, rs in enumerate(ranks_of):
        for r in rs:
            mask[b, r // WORD] |= np.int64(1) << np.int64(r % WORD)
    big = [sum(1 << int(r) for r in rs) for rs in ranks_of]
    lo, size = np.zeros(3), 1.0
    pos = rng.uniform(0, 1, (400, 3)) * dims  # inside the grid
    bins = [int((k[0] * dims[1] + k[1]) * dims[2] + k[2]) for k in pos.astype(int)]
    for me in sorted({0, nr // 2, nr - 1}):
        start, rows, stray = ghost_targets(pos, pos.shape[0], lo, size, dims, mask, me, nr)
        send, stray_ref = python_targets(bins, big, me, nr)
        assert stray == stray_ref
        for r in range(nr):
            assert rows[start[r] : start[r + 1]].tolist() == send[r], f"rank {r} of {nr}, sender {me}"
        touched = mask[[b for b in range(nb) if big[b] >> me & 1]]
        expect = sorted({int(r) for b in range(nb) if big[b] >> me & 1 for r in ranks_of[b]} - {me})
        assert neighbour_ranks(touched, me, nr) == expect


def test_mark_sets_the_rank_bit_in_its_word_only():
    dims = np.array([3, 3, 3])
    mask = np.zeros((27, 3), dtype=np.int64)
    bbox = np.array([[[0.2, 0.2, 0.2], [0.8, 0.8, 0.8]]])  # one cell in bin (0, 0, 0); with h = 0.5 up to bin 1
    r = 2 * WORD + 63  # the sign bit of the third word
    _mark(bbox, 1, 0.5, np.zeros(3), 1.0, dims, r // WORD, np.int64(1) << np.int64(r % WORD), mask)
    hit = {(i * 3 + j) * 3 + k for i in (0, 1) for j in (0, 1) for k in (0, 1)}
    assert np.all(mask[:, :2] == 0)
    assert {b for b in range(27) if mask[b, 2] != 0} == hit
    assert all(mask[b, 2] == np.iinfo(np.int64).min for b in hit)  # bit 63 alone
