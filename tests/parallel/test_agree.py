"""Wall-clock decisions of a run are rank 0's on every rank (run under mpirun -n 2).

A progress line taken when one rank's own clock said so made that rank count particles (a collective)
while the other had gone on into the gas step's: a 2-rank PCPM run hung at t = 0.26 s and 0.84 s.
"""

from mpi4py import MPI

import pytest

from febed.runs.lifecycle import agree

pytestmark = pytest.mark.mpi
COMM = MPI.COMM_WORLD


def test_every_rank_gets_rank_0s_decisions_and_the_largest_signal():
    r = COMM.rank
    sig = 15 if r == COMM.size - 1 else 0  # a signal seen by the last rank only
    due = (r % 2 == 0, r % 2 == 1)  # each rank's own clock says something else
    got = agree(COMM, sig, *due)
    assert got == (15, True, False)  # rank 0's flags, the signal of any rank
    assert COMM.allgather(got) == [got] * COMM.size
    assert agree(COMM, 0) == (0,)
