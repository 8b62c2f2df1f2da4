"""DEM benchmark: the seed-001 bed (57,300 spheres of 1 mm, 2,500 kg/m3, k_n = 1,000 N/m, e = 0.97,
mu = 0.1, k_t = 2/7 k_n, tangential history + rotation, dt = T_C/6, 80 x 15 x 250 mm box), settled, then
timed over >= 10,000 steps on one thread with velocity Verlet and with RK2.

Prints microseconds per particle-step, pair-list rebuilds, peak memory per particle and Numba compile
time. The packed bed is cached under benchmarks/out/ (git-ignored).

    python benchmarks/dem_settle.py [--steps 10000] [--n 57300] [--fresh-compile]
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

OUT = Path(__file__).resolve().parent / "out"


def machine() -> str:
    cpu = "?"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{platform.node()}: {os.cpu_count()} cpus ({cpu}), python {platform.python_version()}"


def params(integrator: str, settle: bool = False):
    """Seed-001 bed parameters; for packing: softer (k_n = 200 N/m: 2.2x longer steps), damped (e = 0.3) and
    without rotation, so the bed comes to rest fast."""
    from febed.dem import DEMParams

    return DEMParams(
        contact_model="linear-history",
        stiffness=200.0 if settle else 1000.0,
        tangential_ratio=2.0 / 7.0,
        restitution_pp=0.3 if settle else 0.97,
        restitution_pw=0.3 if settle else 0.97,
        friction_pp=0.1,
        friction_pw=0.1,
        integrator=integrator,
        dt_factor=6.0,
        skin=0.1,
        rotation=not settle,
    )


def packed_bed(n: int):
    """The settled seed-001 bed of n spheres, packed once and cached (soft pour, then relaxed at k_n = 1000 N/m)."""
    from dataclasses import replace

    from febed.dem import DEM, Walls
    from febed.dem.insertion import insert, load_bed, save_bed, settle

    path = OUT / f"seed001_bed_{n}.npz"
    soft = OUT / f"seed001_soft_{n}.npz"
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / ".gitignore").write_text("*\n")  # cached beds are not versioned
    box = Walls.box([0, 0, 0], [0.08, 0.015, 0.25])
    if path.exists():
        return load_bed(path)[0], box
    print(f"packing {n} spheres (once; cached in {path}) ...", flush=True)
    t = time.time()
    if soft.exists():
        dem = DEM(params("verlet", settle=True), walls=box, particles=load_bed(soft)[0])
    else:
        dem = DEM(params("verlet", settle=True), walls=box)
        height = min(0.25, n * 5.236e-10 / 0.3 / (0.08 * 0.015))  # poured from a random fill of solid fraction 0.3
        insert(dem, n, [0, 0, 0], [0.08, 0.015, height], 1e-3, 2500.0, how="random", seed=1)
        settle(dem, energy=1e-13, max_time=0.35, chunk=500)
        save_bed(soft, dem.particles)
        print(f"  poured in {time.time() - t:.0f} s wall, {dem.time:.3f} s simulated, {dem.steps} steps", flush=True)
    # relax at the benchmark's stiffness, still damped and without rotation
    stiff = DEM(replace(params("verlet", settle=True), stiffness=1000.0), walls=box, particles=dem.particles)
    stiff.particles.vel[:] = 0.0
    settle(stiff, energy=1e-14, max_time=0.06, chunk=500, min_time=0.0)
    print(f"  relaxed in {stiff.time:.3f} s simulated, mean KE {stiff.mean_kinetic_energy():.1e} J", flush=True)
    stiff.particles.vel[:] = 0.0
    stiff.particles.omega[:] = 0.0
    save_bed(path, stiff.particles)
    return stiff.particles, box


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=10000)
    ap.add_argument("--n", type=int, default=57300)
    ap.add_argument("--fresh-compile", action="store_true", help="compile into an empty Numba cache")
    args = ap.parse_args()
    if args.fresh_compile:
        os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="febed-numba-")
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    t = time.time()
    import numpy as np

    from febed.dem import DEM, Particles

    print(machine())
    print(f"load average at start: {os.getloadavg()}")
    print(f"import: {time.time() - t:.2f} s")
    bed, box = packed_bed(args.n)
    data = bed.to_dict()
    for name in ("verlet", "rk2"):
        dem = DEM(params(name), particles=Particles.from_dict(data), walls=box)
        t = time.time()
        dem.advance(1)
        first = time.time() - t
        dem.advance(200)
        b0 = dem.pairs.builds
        t = time.time()
        c = time.process_time()
        dem.advance(args.steps)
        wall = time.time() - t
        cpu = time.process_time() - c
        n = dem.particles.n_owned
        us = wall / (args.steps * n) * 1e6
        us_cpu = cpu / (args.steps * n) * 1e6
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
        arrays = sum(a.nbytes for a in dem.particles._data.values()) + dem.pairs.nbr.nbytes + dem.pairs.hist.nbytes
        print(
            f"{name:6s}: {n} particles, dt = {dem.dt:.3e} s (T_C/6), {args.steps} steps in {wall:.2f} s -> "
            f"{us:.3f} us/particle-step wall ({us_cpu:.3f} CPU); first call (compile or cache load) {first:.1f} s; "
            f"{dem.pairs.builds - b0} rebuilds; {dem.pairs.size / n:.2f} pairs/particle; "
            f"max overlap {dem.max_overlap * 100:.3f} % d; mean KE {dem.mean_kinetic_energy():.2e} J"
        )
        print(
            f"        peak RSS {rss / 2**20:.0f} MiB = {rss / n:.0f} B/particle; DEM arrays {arrays / n:.0f} B/particle"
        )
        if name == "verlet":  # the headline figure: CPU time, robust to other jobs sharing the core
            print(f"DEM: {us_cpu:.3f} us per particle-step (velocity Verlet, history, rotation; CPU time, 1 thread)")
    np.set_printoptions()


if __name__ == "__main__":
    main()
