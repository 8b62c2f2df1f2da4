"""`febed run ARGS...` with a fault on the last rank alone, at its 3rd deposit of particles onto the mesh.

`python _fault_on_one_rank.py KIND ARGS...`, under `mpirun -n 2` (tests/test_failures.py). KIND `bug`: the
deposit raises an IndexError; `blow-up`: a particle's velocity becomes NaN and the deposit raises a ValueError
(a blow-up surfacing inside a kernel). The other rank goes on into the step's collective calls. KIND
`start-up`: building the coupled solver raises a RuntimeError on that rank, while the other builds its own.
"""

import math
import sys

from mpi4py import MPI

from febed.cli import main
from febed.coupling import exchange
from febed.solver import CoupledSolver

kind = sys.argv[1]
real_deposit, real_init = exchange.exchange_project_kernel, CoupledSolver.__init__
solvers, calls = [], []


def init(self, *args, **kwargs):
    if kind == "start-up" and MPI.COMM_WORLD.rank == MPI.COMM_WORLD.size - 1:
        raise RuntimeError("injected on one rank while the solver is built")
    real_init(self, *args, **kwargs)
    solvers.append(self)


def deposit(*args):
    calls.append(1)
    if MPI.COMM_WORLD.rank == MPI.COMM_WORLD.size - 1 and len(calls) == 3:
        if kind == "bug":
            raise IndexError("index 9 is out of bounds for axis 0 with size 9 (injected on one rank)")
        solvers[0].dem.particles.vel[5] = math.nan
        raise ValueError("negative dimensions are not allowed (injected on one rank)")
    return real_deposit(*args)


exchange.exchange_project_kernel = deposit
CoupledSolver.__init__ = init
sys.exit(main(sys.argv[2:]))
