"""`febed run` (the arguments given) with a bug on the last rank alone: its 3rd deposit of particles raises.

Run under `mpirun -n 2` by tests/test_failures.py: the other rank goes on into the step's collective calls.
"""

import sys

from mpi4py import MPI

from febed.cli import main
from febed.coupling import exchange

real = exchange.exchange_project_kernel
calls = []


def fault(*args):
    calls.append(1)
    if MPI.COMM_WORLD.rank == MPI.COMM_WORLD.size - 1 and len(calls) == 3:
        raise IndexError("index 9 is out of bounds for axis 0 with size 9 (injected on one rank)")
    return real(*args)


exchange.exchange_project_kernel = fault
sys.exit(main(sys.argv[1:]))
