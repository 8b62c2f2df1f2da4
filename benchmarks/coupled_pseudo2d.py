"""Coupled CFD-DEM benchmark: seed 001's case C2 (57,300 particles, intermediate mesh 35 x 6 x 110, 1.2 m/s).

Run serially or with `mpirun -n 2`. Prints wall time per simulated second and its split DEM / coupling /
gas (inputs, predictor, pressure, correction) / output (max over ranks) and, on several ranks, the particle
exchange's share of the DEM time, the particle load per rank at the end and its max/mean sampled every 0.01 s
of the window, after a warm-up that compiles the kernels and lets the inlet ramp start.
The packed 75 g bed of demos/pseudo2d is made on first use (several minutes) and reused.

    [mpirun -n 2] python benchmarks/coupled_pseudo2d.py [--sim-time 0.01] [--case demos/pseudo2d/C2.toml]
        [--set contact.skin=0.1 ...] [--restart RUN_DIR_OR_CHECKPOINT]

By default the timed window is the start-up (t = 0.004 to 0.014 s: the inlet ramp, a packed bed, gas steps of
dt_max with ~15 sub-steps). `--restart` times a window of a fluidized bed instead: it continues a C2 run's
checkpoint (e.g. `febed run C2.toml --set run.end_time=1` first), where the gas step is CFL-limited to
~5-6 sub-steps and the gas takes a larger share. A long window (`--sim-time 1`) gives the sustained rate of a
bubbling bed, whose particle load moves between the ranks; a 0.01 s window the rate at one instant.
"""

import argparse
import logging
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

from mpi4py import MPI

from febed.case import load_case
from febed.io.checkpoint import load_checkpoint
from febed.io.rundir import get_logger
from febed.runs.coupled import CoupledRun

ROOT = Path(__file__).resolve().parents[1]
parser = argparse.ArgumentParser()
parser.add_argument("--case", default=str(ROOT / "demos" / "pseudo2d" / "C2.toml"))
parser.add_argument("--sim-time", type=float, default=0.01, help="simulated seconds timed (after the warm-up)")
parser.add_argument("--warmup", type=float, default=0.004, help="simulated seconds before timing")
parser.add_argument("--set", action="append", default=[], help="case overrides KEY=VALUE (repeatable)")
parser.add_argument("--restart", default=None, help="continue this run folder's newest checkpoint (or this file)")
args = parser.parse_args()

comm = MPI.COMM_WORLD
cpu = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), "?")
out = Path(comm.bcast(tempfile.mkdtemp(prefix="febed-bench-") if comm.rank == 0 else None, root=0))
quiet = [f"output.directory={out}", "output.field_interval=100", "output.particle_interval=100"]
case = load_case(args.case, quiet + args.set)
log = get_logger(None, comm) if comm.rank == 0 else logging.getLogger("febed.bench")
t0 = time.perf_counter()
ckpt = load_checkpoint(Path(args.restart), comm) if args.restart else None
run = CoupledRun(case, out, log, comm, restart=ckpt)
run.advance_to(run.solver.t + args.warmup)
comm.barrier()
t1 = time.perf_counter()
s = run.solver
before = s.timers.as_dict()
gas_split: dict[str, float] = {}  # the gas time by part of its step (inputs, predictor, pressure, correction)
gas_step = s.gas.step


steps = {"n": 0, "cfl": 0.0, "fourier": 0.0, "sub": 0}  # gas steps of the window, largest CFL and Fourier, sub-steps


def timed_gas_step(*a, **kw):
    info = gas_step(*a, **kw)
    for key, seconds in info.timings.items():
        gas_split[key] = gas_split.get(key, 0.0) + seconds
    steps["n"] += 1
    steps["sub"] += info.substeps
    steps["cfl"], steps["fourier"] = max(steps["cfl"], info.cfl), max(steps["fourier"], info.fourier)
    return info


s.gas.step = timed_gas_step
ex = s.dem.exchange
ex_before = dict(ex.timers) if ex is not None else {}
sim0 = s.t
imbalance = []  # max/mean particles per rank, sampled every 0.01 s of the window
while s.t < sim0 + args.sim_time - 1e-12:
    run.advance_to(min(s.t + 0.01, sim0 + args.sim_time))
    n = comm.allgather(s.dem.particles.n_owned)
    imbalance.append(max(n) * len(n) / max(sum(n), 1))
comm.barrier()
t2 = time.perf_counter()
after = s.timers.as_dict()
split = {k.removeprefix("wall_"): comm.allreduce(after[k] - before[k], op=MPI.MAX) for k in after}
ex_split = (
    {
        k: [comm.allreduce(v - ex_before.get(k, 0.0), op=op) for op in (MPI.MIN, MPI.MAX)]
        for k, v in sorted(ex.timers.items())
    }
    if ex
    else {}
)
exchange = comm.allreduce(sum(ex.timers.values()) - sum(ex_before.values()) if ex is not None else 0.0, op=MPI.MAX)
gas_parts = {k: comm.allreduce(v, op=MPI.MAX) for k, v in sorted(gas_split.items())}
counts = comm.gather(s.dem.particles.n_owned, root=0)
if comm.rank == 0:
    sim = s.t - sim0
    per_s = (t2 - t1) / sim
    print(f"machine: {platform.node()}, {os.cpu_count()} cores, {cpu}; load average {os.getloadavg()[0]:.2f}")
    print(f"case {case.name}: {sum(counts)} particles on {comm.size} rank(s) {counts}, {s.ma.num_dofs} nodes (rank 0)")
    print(f"set-up + compile + {args.warmup} s warm-up: {t1 - t0:.1f} s; {s.n_sub} DEM sub-steps per gas step")
    print(f"wall time per simulated second: {per_s / 60:.1f} min ({sim:.4f} s simulated in {t2 - t1:.1f} s)")
    k, sub = case.gas.convection_substeps, steps["sub"] / max(steps["n"], 1)
    print(
        f"  {steps['n']} gas steps of {sim / max(steps['n'], 1):.3g} s on average (largest CFL {steps['cfl']:.3f}, "
        f"Fourier {steps['fourier']:.3f}; {sub:.2f} convective sub-steps per gas step on average, at most {k})"
    )
    for k, v in split.items():
        print(f"  {k:9s} {v / sim / 60:7.2f} min per simulated s ({100 * v / (t2 - t1):4.1f} %)")
        if k == "gas":
            for part, sec in gas_parts.items():
                print(f"    {part:11s} {sec / sim / 60:5.2f} min per simulated s ({100 * sec / (t2 - t1):4.1f} %)")
    if comm.size > 1:
        mean, worst = sum(imbalance) / len(imbalance), max(imbalance)
        print(f"  particles max/mean over {len(imbalance)} samples of the window: mean {mean:.3f}, max {worst:.3f}")
        print(f"  particle exchange (in the DEM time): {exchange / sim / 60:.2f} min per simulated s")
        for k, (lo, hi) in ex_split.items():  # the rank that waits least shows the cost of the messages alone
            print(f"    {k:9s} {lo / sim / 60:5.2f} - {hi / sim / 60:5.2f} min per simulated s (min - max over ranks)")
    shutil.rmtree(out, ignore_errors=True)
