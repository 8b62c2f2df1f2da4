"""The DEM of a bubbling bed on 2 ranks with the particles shared by the mesh partition and by work-balanced boxes.

Loads the particles of a coupled run's checkpoint (default: C2's run folder; the bed as the gas left it,
unevenly spread over a fixed mesh partition) and steps the DEM alone (gravity, walls, no gas: over a few hundred
steps of ~1e-5 s the bed keeps its layout) serially, then on 2 ranks with `[run] particle_partition` = "mesh"
(each particle on the rank owning its mesh cell) and = "work" (`BoxExchange`: boxes of equal work, cut again at
the rebuilds). Prints per decomposition the particles and listed pairs per rank with their max/mean, the time
per step and the parallel efficiency T1 / (2 T2), and the exchange's share.

    python benchmarks/dem_partition.py --restart RUN_DIR_OR_CHECKPOINT [--case demos/pseudo2d/C2.toml] [--steps 300]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from dem_scaling import mpirun_result  # noqa: E402


def worker(case_path: str, restart: str, partition: str, steps: int) -> None:
    """One run on the ranks of COMM_WORLD; rank 0 prints a JSON line."""
    import logging

    from mpi4py import MPI

    from febed.bed import dem_from_case, particle_exchange, walls_from_mesh
    from febed.case import load_case
    from febed.dem.particles import Particles
    from febed.io.checkpoint import load_checkpoint
    from febed.io.state import load_dem
    from febed.meshing import load_case_mesh

    logging.disable(logging.INFO)
    comm = MPI.COMM_WORLD
    case = load_case(case_path)
    md = load_case_mesh(case, comm)
    _, arrays, meta = load_checkpoint(Path(restart), comm)
    dem = dem_from_case(case, walls_from_mesh(case, md), md.gdim, Particles())
    ex = particle_exchange(md, comm, partition)
    if ex is not None:
        dem.attach_exchange(ex)
    load_dem(dem, arrays, meta, comm.size)
    dt = dem.dt
    dem.advance(30, dt)  # compile, build the lists, settle into the loop
    if ex is not None:
        ex.timers = dict.fromkeys(ex.timers, 0.0)
    comm.barrier()
    t = time.perf_counter()
    dem.advance(steps, dt)
    comm.barrier()
    wall = time.perf_counter() - t
    out = {
        "ranks": comm.size,
        "partition": partition,
        "wall": wall,
        "n": comm.allreduce(dem.particles.n_owned),
        "owned": comm.allgather(dem.particles.n_owned),
        "pairs": comm.allgather(int(dem.pairs.size)),
        "exchange": comm.allreduce(sum(ex.timers.values()), op=MPI.MAX) if ex is not None else 0.0,
        "migrated": comm.allreduce(ex.migrated) if ex is not None else 0,
    }
    if comm.rank == 0:
        print("RESULT " + json.dumps(out), flush=True)


def run(ranks: int, args, partition: str) -> dict:
    """The worker under mpirun -n ranks."""
    return mpirun_result(ranks, __file__, ["--worker", "--case", args.case, "--restart", args.restart,
                                           "--partition", partition, "--steps", str(args.steps)])  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default=str(ROOT / "demos" / "pseudo2d" / "C2.toml"))
    ap.add_argument("--restart", default="runs/C2", help="run folder (its newest checkpoint) or checkpoint file")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--partition", default="mesh", help=argparse.SUPPRESS)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args.case, args.restart, args.partition, args.steps)
        return
    print(f"nproc {os.cpu_count()}, load average {os.getloadavg()[0]:.2f}; {args.restart}, {args.steps} DEM steps")
    one = run(1, args, "mesh")
    print(f"1 rank: {one['n']} particles, {one['wall'] / args.steps * 1e3:.1f} ms per step")
    for partition in ("mesh", "work"):
        r = run(2, args, partition)
        owned, pairs = r["owned"], r["pairs"]
        print(
            f"2 ranks, particle_partition = {partition!r}: particles {owned} (max/mean "
            f"{max(owned) * len(owned) / sum(owned):.3f}), listed pairs {pairs} (max/mean "
            f"{max(pairs) * len(pairs) / sum(pairs):.3f}); {r['wall'] / args.steps * 1e3:.1f} ms per step, "
            f"efficiency {100 * one['wall'] / (2 * r['wall']):.0f} %; exchange {r['exchange']:.2f} of "
            f"{r['wall']:.2f} s, {r['migrated']} migrations"
        )


if __name__ == "__main__":
    main()
