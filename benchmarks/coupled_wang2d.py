"""Coupled CFD-DEM benchmark: the seed-000 2D bed (4,080 particles, 18 x 100 cells, 0.9 m/s), serial.

Prints wall time per simulated second and its split DEM / coupling / gas / output, after a short warm-up
run that compiles the Numba kernels and the DOLFINx forms (compile time reported separately).
Usage: .venv/bin/python benchmarks/coupled_wang2d.py [--sim-time 0.2]
"""

import argparse
import logging
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

from febed.case import load_case
from febed.run import CoupledRun

parser = argparse.ArgumentParser()
parser.add_argument("--sim-time", type=float, default=0.2, help="simulated seconds timed (after 0.01 s warm-up)")
args = parser.parse_args()

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
shutil.rmtree(out, ignore_errors=True)
