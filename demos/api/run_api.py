# # febed from Python: load a case, step the coupled solver in your own loop, write output
#
# The command line (`febed run CASE.toml`) runs a case from start to end. A script can instead load (or
# build) the case, step the coupled CFD-DEM solver itself, look at the state between steps and decide what
# to write. This demo fluidizes the small two-dimensional bed of `box2d.toml` (300 particles of 1 mm in a
# 20 mm × 60 mm box) for 0.02 s, prints the particles' mean height as it goes, writes the usual output
# (probes, fields, particles) into `demos/api/out/` and checks that the gas carries most of the bed's weight.
# It takes a few seconds, serially or under `mpirun -n 2`.
#
# Usage: `.venv/bin/python demos/api/run_api.py` (or `mpirun -n 2 .venv/bin/python demos/api/run_api.py`).
#
# `febed.load_case(path, overrides, data)` reads a TOML case (`overrides` as given to `febed run --set`);
# a case can also be built in Python as a dict with the same sections,
# `febed.load_case(data={"run": {"mode": "cfd-dem", "end_time": 0.02}, "mesh": {...}, ...})`. Every value
# not given takes its default (`febed params` lists them). `febed.CoupledRun` builds the mesh, the solver
# (`run.solver`: `step()`, `check()`, `t`, `gas`, `dem`) and the writers; `run.output()` writes whatever
# the `[output]` intervals make due and `run.close()` the last output. `febed.run_coupled` would do all of
# this loop in one call.

import math
from pathlib import Path

from mpi4py import MPI

import febed

OUT = Path(__file__).resolve().parent / "out"
case = febed.load_case(OUT.parent / "box2d.toml", [f"output.directory={OUT}"])
log = febed.get_logger(febed.prepare_output(case, overwrite=True))  # creates (or clears) OUT and locks it
run = febed.CoupledRun(case, OUT, log)  # mesh, coupled solver, probe/field/particle writers
solver, comm = run.solver, MPI.COMM_WORLD
run.output(force=True)  # the initial state
while solver.t < case.run.end_time:
    solver.step()  # one gas step: particle sub-steps with the gas frozen, projection, gas step
    solver.check()  # raises febed.RunFailure if a particle left the mesh or a value is not finite
    run.output()  # probes, fields and particles when their intervals are due
    if solver.steps % 20 == 0:  # your own analysis between steps: here the particles' mean height
        P = solver.dem.particles  # each rank holds the particles of its cells: the first n_owned rows
        n, y = comm.allreduce(P.n_owned), comm.allreduce(P.pos[: P.n_owned, 1].sum())
        log.info(f"t = {solver.t:.4f} s: {n} particles, mean height {1e3 * y / n:.2f} mm")
run.close()  # the last output; the files are complete on rank 0 after this
p = case.particles  # the bed's weight per area (2D: the depth is one diameter): N rho pi d^3 g / 6 / (L_x d)
weight = p.count * p.density * math.pi * p.diameter**2 * case.run.gravity / (6 * case.mesh.extent[0])
dp = febed.read_probes(OUT / "probes.csv")["dp_bed"][-1] if comm.rank == 0 else weight
log.info(f"bed pressure drop {dp:.1f} Pa = {dp / weight:.2f} of the bed weight per area; output in {OUT}")
assert 0.5 < dp / weight < 1.2, "the gas should carry most of the bed's weight"
