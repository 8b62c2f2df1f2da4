"""Coupled CFD-DEM benchmark: the seed-000 2D bed (4,080 particles, 18 x 100 cells, 0.9 m/s), serial.

Prints wall time per simulated second and its split DEM / coupling / gas / output, after a short warm-up
run that compiles the Numba kernels and the DOLFINx forms (compile time reported separately). With
--stages, the coupling's parts are timed per gas step too (wrappers around the solver's methods; the health
check `CoupledSolver.check` runs outside the four timers and is listed apart).
Usage: .venv/bin/python benchmarks/coupled_wang2d.py [--sim-time 0.2] [--stages]
"""

import argparse
import functools
import logging
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

from febed.case import load_case
from febed.coupling.exchange import Coupler
from febed.runs.coupled import CoupledRun
from febed.solver import CoupledSolver

STAGES = {  # what each timed method does, per gas step
    (CoupledSolver, "_fluid"): "particle forces: interpolate + drag + F_P -> FLUID record, min m/K",
    (Coupler, "forces_into"): "  of which the fused kernel",
    (CoupledSolver, "project"): "projection to the gas, relocation included",
    (CoupledSolver, "locate_particles"): "  of which locate (walk + weights) + outlet bookkeeping",
    (Coupler, "project_to_gas"): "  of which project + filter + divide by dV",
    (CoupledSolver, "check"): "health check (not in the coupling timer)",
}

parser = argparse.ArgumentParser()
parser.add_argument("--sim-time", type=float, default=0.2, help="simulated seconds timed (after 0.01 s warm-up)")
parser.add_argument("--stages", action="store_true", help="also time the coupling's parts per gas step")
args = parser.parse_args()
spent = dict.fromkeys(STAGES, 0.0)


def timed(key):
    """Wrap method key = (class, name) so that its wall time adds to spent[key]."""
    f = getattr(*key)

    @functools.wraps(f)
    def wrapper(*a, **k):
        t = time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            spent[key] += time.perf_counter() - t

    setattr(*key, wrapper)


cpu = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), "?")
print(f"machine: {platform.node()}, {os.cpu_count()} cores, {cpu}")
out = Path(tempfile.mkdtemp(prefix="febed-bench-"))
case = load_case(Path(__file__).parents[1] / "demos" / "wang2d" / "wang2d.toml", [f"output.directory={out}"])
log = logging.getLogger("febed.bench")
t0 = time.perf_counter()
run = CoupledRun(case, out, log)
run.advance_to(0.01)
t1 = time.perf_counter()
s = run.solver
before = s.timers.as_dict()
sim0 = s.t
steps0 = s.steps
if args.stages:
    for key in STAGES:
        timed(key)
run.advance_to(sim0 + args.sim_time)
t2 = time.perf_counter()
after = s.timers.as_dict()
split = {k.removeprefix("wall_"): after[k] - before[k] for k in after}
per_s = (t2 - t1) / (s.t - sim0)
print(f"set-up + compile + 0.01 s warm-up: {t1 - t0:.1f} s")
print(f"{s.dem.particles.n_owned} particles, {s.steps} gas steps, {s.n_sub} DEM sub-steps per gas step")
print(f"wall time per simulated second: {per_s / 60:.2f} min ({per_s:.0f} s)")
for k, v in split.items():
    print(f"  {k:9s} {v / (s.t - sim0):7.1f} s per simulated s  ({100 * v / (t2 - t1):4.1f} %)")
print(f"coupling / DEM: {100 * split['coupling'] / split['dem']:.0f} %")
if args.stages:
    n = s.steps - steps0
    print(f"per gas step (ms): DEM {1e3 * split['dem'] / n:.2f}, coupling {1e3 * split['coupling'] / n:.3f}")
    for key, what in STAGES.items():
        print(f"  {1e3 * spent[key] / n:6.3f}  {what}")
shutil.rmtree(out, ignore_errors=True)
