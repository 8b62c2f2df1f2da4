"""Strong scaling of the DEM benchmark (the seed-001 bed of benchmarks/dem_settle.py, 57,300 spheres) 1 -> 2 ranks.

Runs itself under `mpirun -n 1` (the serial compiled loop, no exchange) and `mpirun -n 2` (particles distributed
by a hexahedral mesh of the box cut in two slabs across x, so each rank holds half of the bed), times the same
steps with velocity Verlet and RK2, and prints microseconds per particle-step, the parallel efficiency
T1 / (2 T2) and, on 2 ranks, the split DEM / exchange (migration, ghost refresh, per-stage ghost updates,
reductions; max over ranks). The bed is the one dem_settle.py packs and caches.

    python benchmarks/dem_scaling.py [--steps 300] [--n 57300]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
BOX = (0.08, 0.015, 0.25)
CELLS = (16, 3, 50)  # 5 mm hexahedra


def worker(steps: int, n: int) -> None:
    """One run on the ranks of COMM_WORLD; rank 0 prints a JSON line of timings."""
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(HERE))
    from mpi4py import MPI

    import dolfinx.mesh as dm
    from dem_settle import packed_bed, params

    from febed.dem import DEM, Particles
    from febed.parallel import ParticleExchange, slab_partitioner

    comm = MPI.COMM_WORLD
    bed, box = packed_bed(n) if comm.rank == 0 else (None, None)
    data = comm.bcast(bed.to_dict() if comm.rank == 0 else None, root=0)
    from febed.dem import Walls

    box = Walls.box([0, 0, 0], list(BOX))
    mesh = None
    if comm.size > 1:
        mesh = dm.create_box(comm, [[0, 0, 0], list(BOX)], list(CELLS), dm.CellType.hexahedron,
                             dm.GhostMode.shared_facet, slab_partitioner(period=CELLS[0]))  # fmt: skip
    out = {"ranks": comm.size, "n": int(data["pos"].shape[0]), "steps": steps}
    for name in ("verlet", "rk2"):
        dem = DEM(params(name), particles=Particles.from_dict(data), walls=box)
        ex = None
        if mesh is not None:
            ex = ParticleExchange.from_mesh(mesh)
            dem.attach_exchange(ex, distribute=True)
        dt = dem.dt
        dem.advance(50, dt)  # compile, build, settle into the loop
        if ex is not None:
            ex.timers = dict.fromkeys(ex.timers, 0.0)
            m0 = ex.migrated
        comm.barrier()
        t = time.perf_counter()
        b0 = dem.pairs.builds
        dem.advance(steps, dt)
        comm.barrier()
        wall = time.perf_counter() - t
        r = {"wall": wall, "builds": dem.pairs.builds - b0, "us": wall / (steps * out["n"]) * 1e6}
        if ex is not None:
            r["compute"] = comm.allgather(wall - sum(ex.timers.values()))  # per rank: DEM work without the exchange
            timers = {k: comm.allreduce(v, op=MPI.MAX) for k, v in ex.timers.items()}
            r["exchange"] = timers
            r["exchange_total"] = comm.allreduce(sum(ex.timers.values()), op=MPI.MAX)
            r["migrated"] = comm.allreduce(ex.migrated - m0)
            r["ghosts"] = comm.allgather(dem.particles.n_ghost)
            r["owned"] = comm.allgather(dem.particles.n_owned)
        out[name] = r
        assert dem.count() == out["n"]
        del dem
    if comm.rank == 0:
        print("RESULT " + json.dumps(out), flush=True)


def machine() -> str:
    """nproc, CPU model and load."""
    cpu = "?"
    for line in open("/proc/cpuinfo"):
        if line.startswith("model name"):
            cpu = line.split(":", 1)[1].strip()
            break
    return f"nproc {os.cpu_count()}, {cpu}, load average {os.getloadavg()}"


def run(ranks: int, steps: int, n: int) -> dict:
    """Run the worker under mpirun -n ranks and return its timings."""
    return mpirun_result(ranks, __file__, ["--worker", "--steps", str(steps), "--n", str(n)])


def mpirun_result(ranks: int, script: str, args: list[str]) -> dict:
    """The JSON a benchmark's worker prints on a `RESULT ` line, run as `mpirun -n ranks python script args`."""
    # waiting ranks yield the CPU instead of spinning: on a shared machine a spinning rank starves the other one
    env = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1", OMPI_MCA_mpi_yield_when_idle="1")
    cmd = ["mpirun", "--allow-run-as-root", "--oversubscribe", "-n", str(ranks), sys.executable, script, *args]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    for line in res.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--n", type=int, default=57300)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args.steps, args.n)
        return
    print(machine())
    t = time.time()
    one = run(1, args.steps, args.n)
    two = run(2, args.steps, args.n)
    print(f"{one['n']} spheres, {args.steps} timed steps per integrator ({time.time() - t:.0f} s in all)")
    for name in ("verlet", "rk2"):
        a, b = one[name], two[name]
        eff = a["wall"] / (2 * b["wall"])
        ex = b["exchange"]
        print(f"{name:6s} 1 rank {a['us']:.3f} us/particle-step ({a['builds']} rebuilds); 2 ranks {b['us']:.3f} "
              f"us/particle-step; speed-up {a['wall'] / b['wall']:.2f}, efficiency {100 * eff:.0f} %")  # fmt: skip
        dem_t = b["wall"] - b["exchange_total"]
        comp = max(b["compute"])
        per = ", ".join(f"{c:.2f}" for c in b["compute"])
        print(f"       2 ranks: DEM compute per rank {per} s (efficiency without the exchange "
              f"{100 * a['wall'] / (2 * comp):.0f} %)")  # fmt: skip
        print(f"       2 ranks: DEM {dem_t:.2f} s, exchange {b['exchange_total']:.2f} s of {b['wall']:.2f} s "
              f"(migrate {ex['migrate']:.2f}, ghost refresh {ex['ghosts']:.2f}, ghost updates {ex['update']:.2f}, "
              f"reductions {ex['reduce']:.2f}; max over ranks, waits included); particles {b['owned']}, "
              f"ghosts {b['ghosts']}, {b['migrated']} migrations")  # fmt: skip


if __name__ == "__main__":
    main()
