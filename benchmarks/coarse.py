"""Coarse-graining cost on seed 000's 2D bed: plain DEM (l = 1), TM (l = 2) and PCPM (from l = 2) in one run.

Run: `python benchmarks/coarse.py [--time 0.1] [--micro]`. Asserts nothing; prints the machine, each run's wall
time of the coupled time loop and its split, then

    PCPM l=2 wall / DEM wall: X
    TM l=2 wall / DEM wall: Y
    event energy / bed kinetic energy: Z

The three runs are the 4,080-original bed of `demos/wang2d/coarse/` (`tm1.toml`: plain DEM, `tm2.toml`,
`pcpm2.toml`: 1,020 parcels or groups of 8 originals), each from its packed bed at t = 0 over the same
simulated time (`--time`, default 0.1 s: the inlet ramp of 0.02 s and the bed's first rise), no output. The
wall time is that of the gas steps only: building the solver and the first gas step (Numba and form
compilation) are left out. Kernels first called later (at the first neighbour-list rebuild, the first crush)
would compile inside the timed window from a cold Numba cache, so the three runs are made `--rounds` times
(default 2) and the ratios printed last are those of the last round. Z is the energy the PCPM events injected
over the run (`GroupDynamics.total`: the measured change of kinetic + elastic + gravitational energy, negative
when the events dissipate) divided by the bed's kinetic energy (translation + rotation of every group)
averaged over the gas steps.
Other jobs on the machine change X and Y; run it on an idle machine to compare with seed 000's ~0.10.

`--micro` adds the older component benchmarks: TM parcels in a box (DEM cost per simulated second at
l = 1, 2, 3), PCPM `apply`/d_cl per call on random groups, and the one-way driver.
"""

import argparse
import logging
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from febed.coarse.oneway import OneWay
from febed.coarse.pcpm import NO_CRUSH, GroupDynamics
from febed.coarse.tm import tm_dem_params, tm_parcels
from febed.dem import DEM, DEMParams, Walls
from febed.dem.insertion import random_positions
from febed.gas.prescribed import make_prescribed_gas

CASES = Path(__file__).resolve().parents[1] / "demos" / "wang2d" / "coarse"


def machine():
    cpu = "?"
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return f"{os.cpu_count()} cpus, {cpu}, Python {platform.python_version()}, load average {load:.2f}"


def coupled_run(name, sim_time, workdir):
    """Wall time (s) of `sim_time` s of the case `name` after its first gas step; the solver for the figures."""
    from febed.case import load_case
    from febed.meshing import load_case_mesh
    from febed.solver import Timers, build_solver

    case = load_case(CASES / f"{name}.toml", [f"output.directory={workdir / name}"])
    md = load_case_mesh(case, cache_dir=workdir / "mesh")
    s = build_solver(case, md, logging.getLogger(f"bench.{name}"))
    s.step()  # compilation
    s.check()
    s.timers = Timers()
    t_end = s.t + sim_time
    wall = 0.0
    ke = []
    while s.t < t_end * (1 - 1e-12):
        t0 = time.perf_counter()
        s.step()
        s.check()
        wall += time.perf_counter() - t0
        ke.append(s.dem.kinetic_energy())
    t = s.timers
    split = f"DEM {t.dem:.2f}, coupling {t.coupling:.2f}, gas {t.gas:.2f}"
    print(f"{name}: {s.dem.particles.n_owned} particles, {s.steps - 1} gas steps to t = {s.t:.4f} s: {wall:.2f} s "
          f"({split}), {wall / sim_time:.1f} s per simulated s")  # fmt: skip
    return wall, s, float(np.mean(ke))


def coupled_bench(sim_time, rounds):
    for r in range(1, rounds + 1):
        print(f"round {r} of {rounds}" + (" (compiles the kernels a cold Numba cache lacks)" if r == 1 else ""))
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            dem, _, _ = coupled_run("tm1", sim_time, work)
            tm, _, _ = coupled_run("tm2", sim_time, work)
            pcpm, s, ke = coupled_run("pcpm2", sim_time, work)
    gd = s.groups
    tot = gd.total
    print(f"pcpm2: criteria every {gd.event_interval * 1e3:.2f} ms (0.1 U_mf/g), {tot.crushed} crushes, "
          f"{tot.merged} merges, {tot.groups} groups; event energy {tot.energy_injected:.3g} J, mean bed kinetic "
          f"energy {ke:.3g} J")  # fmt: skip
    print(f"PCPM l=2 wall / DEM wall: {pcpm / dem:.3f}")
    print(f"TM l=2 wall / DEM wall: {tm / dem:.3f}")
    print(f"event energy / bed kinetic energy: {tot.energy_injected / ke:.3g}")


def tm_bench(n_orig_total, steps):
    d0, rho = 1.5e-3, 1150.0  # seed 000 Table 2
    base = DEMParams(stiffness=800.0, restitution_pp=0.9, restitution_pw=0.9, friction_pp=0.3)
    ref = None
    print(f"TM: {n_orig_total} originals in a box, {steps} DEM steps each (gravity, settling)")
    print(f"{'l':>4} {'parcels':>8} {'dt (us)':>9} {'us/step':>9} {'s per simulated s':>18} {'rel. to l=1':>11}")
    for ratio in (1.0, 2.0, 3.0):
        d, n = tm_parcels(d0, ratio)
        count = max(1, round(n_orig_total / n))
        side = (count * 2.5) ** (1 / 3) * d * 1.3
        lo, hi = np.zeros(3), np.array([side, side, 2 * side])
        dem = DEM(tm_dem_params(base, ratio), walls=Walls.box(lo, hi))
        dem.add_particles(random_positions(count, lo, hi, d * 1.05, seed=1), d, rho, n_orig=n)
        dem.advance(20)  # compile + first build
        t0 = time.perf_counter()
        dem.advance(steps)
        w = (time.perf_counter() - t0) / steps
        per_sim = w / dem.dt
        ref = ref or per_sim
        print(f"{ratio:4.0f} {count:8d} {dem.dt * 1e6:9.2f} {w * 1e6:9.1f} {per_sim:18.3g} {per_sim / ref:11.3f}")


def pcpm_bench(count, calls):
    d0, rho = 1.5e-3, 1150.0
    lo, hi = np.zeros(3), np.full(3, (count * 8 * 4.0) ** (1 / 3) * d0)
    dem = DEM(DEMParams(gravity=0.0, stiffness=800.0), walls=Walls.box(lo, hi))
    rng = np.random.default_rng(0)
    n0 = rng.integers(1, 9, count)
    dem.add_particles(random_positions(count, lo, hi, 2.05 * d0, seed=2), d0 * np.cbrt(n0), rho,
                      vel=rng.normal(0, 0.1, (count, 3)), n_orig=n0)  # fmt: skip
    gd = GroupDynamics(d0, rho, 1.28, 1.7e-5, 0.45, merge_tolerance=0.5, measure_energy=False)
    P = dem.particles
    gd.apply(dem, np.full(P.n_owned, NO_CRUSH))  # compile
    ev = 0
    t0 = time.perf_counter()
    for _ in range(calls):
        n = P.n_owned
        dcl = np.where(rng.random(n) < 0.02, 0.6 * P.diameter[:n], NO_CRUSH)
        s = gd.apply(dem, dcl)
        ev += s.crushed + s.merged
    w = (time.perf_counter() - t0) / calls
    n = P.n_owned
    eps = np.full(n, 0.7)
    u = np.tile([0, 0, 1.0], (n, 1))
    f = 10.0 * P.mass[:n, None] * u
    gd.equivalent_diameter(dem, eps, u, f)
    t0 = time.perf_counter()
    for _ in range(calls):
        gd.equivalent_diameter(dem, eps, u, f)
    w2 = (time.perf_counter() - t0) / calls
    print(f"PCPM: {count} groups: apply {w * 1e3:.2f} ms/call ({ev / calls:.1f} events/call), "
          f"d_cl with contact power {w2 * 1e3:.2f} ms/call")  # fmt: skip


def oneway_bench(count, windows):
    dem = DEM(DEMParams(stiffness=1e-3, gravity=0.0, rotation=False))
    lo, hi = np.array([-4e-4, -4e-4, 0]), np.array([4e-4, 4e-4, 4e-3])
    dem.add_particles(random_positions(count, lo, hi, 12e-6, seed=3), 10e-6, 1000.0)
    ow = OneWay(dem, make_prescribed_gas("vortex", rpm=300.0, inflow_ratio=0.1), "stokes")
    ow.step(1e-5)
    t0 = time.perf_counter()
    for _ in range(windows):
        ow.step(6e-5)
    w = (time.perf_counter() - t0) / windows
    print(f"one-way: {count} particles of 10 um in the seed-003 vortex: {w * 1e3:.2f} ms per drag window "
          f"({dem.steps} DEM steps so far)")  # fmt: skip


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--time", type=float, default=0.1, help="simulated time of each coupled run (s)")
    ap.add_argument("--micro", action="store_true", help="also the component benchmarks")
    ap.add_argument("--quick", action="store_true", help="smaller component benchmarks")
    ap.add_argument("--rounds", type=int, default=2, help="rounds of the three runs; the ratios are the last's")
    a = ap.parse_args()
    print(machine())
    if a.micro:
        tm_bench(2000 if a.quick else 8000, 100 if a.quick else 400)
        pcpm_bench(1000 if a.quick else 4000, 5 if a.quick else 20)
        oneway_bench(200 if a.quick else 1000, 20 if a.quick else 100)
    coupled_bench(a.time, max(a.rounds, 1))
