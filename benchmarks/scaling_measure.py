"""Measured loads and times of a coupled run window, per rank: the validation data of `scaling_projection.py`.

Continues a run folder's newest checkpoint (a bubbling bed) for a warm-up and a timed window and writes, per
rank, the owned and ghost particles, listed pairs, owned and local gas nodes, gas steps, DEM sub-steps, pair
list builds, and the wall and CPU seconds of the window with the solver's split DEM / coupling / gas / output
in CPU seconds of each rank, to benchmarks/out/measured_<case>_P<ranks>[<tag>].json. Run it serially and on
2 ranks on the same checkpoint:

    [mpirun -n 2] python benchmarks/scaling_measure.py --restart RUN_DIR [--case demos/pseudo2d/C2.toml]
        [--warmup 0.004] [--sim-time 0.01] [--set KEY=VALUE ...] [--tag NAME] [--rebuilds N]
    python benchmarks/scaling_measure.py --restart RUN_DIR --staged --tag _staged
    mpirun -n 2 python benchmarks/scaling_measure.py --restart RUN_DIR --barriers --tag _barriers
    mpirun -n 2 python benchmarks/scaling_measure.py --restart RUN_DIR --concurrent --tag _concurrent
    python benchmarks/scaling_measure.py --restart RUN_DIR --owners --tag _owners
    mpirun -n 2 python benchmarks/scaling_measure.py --pingpong
    [mpirun -n 2] python benchmarks/scaling_measure.py --restart RUN_DIR --warmup 0.001 --sim-time 0.001 \
        --calls 500 --tag _calls
    [mpirun -n 2] python benchmarks/scaling_measure.py --restart RUN_DIR --profile [--tag NAME]

Options that add to the window or change it:

- `--rebuilds N`: then N pair-list rebuilds (fastest and median); serially also N rebuilds that restore the
  contact history by key and the locating of every particle (the parallel rebuild's own work, on one core),
  and N fills of the drag-weighted pressure operator through PETSc's COO assembly, which the gas step does on
  several ranks only (on one process the matrix is built on the assembled values).
- `--calls N`: then N of each call of the gas step and the coupling that exchanges between ranks or reduces
  over them (halo scatters, the extra columns' scatter, a PETSc ghost update, reductions); run serially and on
  2 ranks, the difference is what each call costs on several ranks beyond one process.
- `--staged`: on one process, the DEM steps as every rank of a parallel run does (a kernel call per stage of
  each step, a ghost update between them with nothing to send, rebuilds migrating and restoring the contact
  history by key): the DEM cost per pair of the parallel code path.
- `--owners`: on one process, the coupling goes through the nodes' owners over the whole mesh's arrays, as
  with `particle_partition = "work"` on several ranks: its coupling cost per particle.
- `--concurrent` (on several ranks): every rank runs the serial window alone, each phase started together
  with a barrier: the serial costs per unit of work while every core of the machine does the same phase, as
  the ranks of a parallel run do (the cores share caches and memory bandwidth; on the 2-core machine of
  docs/scaling.md the slow-down varied from 0 to 18 % between runs).
- `--barriers`: each phase of the step starts with a barrier whose time is recorded apart ("waits"), so that
  a phase's time is its own work, not the wait for another rank.
- `--core-speed`: before every gas step (outside the phases' timers) each rank times a fixed compiled loop
  of about 0.2 ms held in its core's registers and level-1 cache (`core_probe`): how fast its core runs at
  that moment. On a virtual machine the cores' speeds change with the host's other work, and not together;
  a parallel run goes at the pace of its slower core between two exchanges, which a model of equal cores
  does not see (`scaling_projection.py --check` reads these samples). On 2 ranks the ranks then also time
  10 round trips of 8 bytes between them (`message_probe`, half a round trip each): the message latency of
  that moment; and every 4th gas step, both together, a sum over an array of their own of 16 MB
  (`memory_probe`, the second of two passes): whether their data shares one last-level cache at that
  moment (a rank of C2 on 2 ranks works on about that much).
- `--profile`: the timed window under cProfile, one file per rank
  (`profile_<case>_P<ranks><tag>_r<rank>.pstats`); `profile_compare.py` sets a 2-rank profile against the
  serial one function by function, to find the work that does not divide by the ranks.
- `--pingpong`: instead of a window, between two ranks of this machine (shared memory), the latency, the
  bandwidth and an 8-byte allreduce, and the MPI calls of a ghost update and of a rebuild's exchanges,
  emulated with `--ghosts` rows and `--movers` leaving particles.

CPU seconds are the measure to use serially on a machine shared with other jobs: a descheduled process
loses wall time, not CPU time. On several ranks they are not: a rank waiting for a descheduled partner
polls, and its waiting counts as CPU time too.
"""

import argparse
import cProfile
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
from numba import njit

import febed.solver
from febed.case import load_case
from febed.coupling.locate import locate
from febed.coupling.owners import OwnerCoupler
from febed.gas.petsc_coo import coo_matrix
from febed.io.checkpoint import load_checkpoint
from febed.io.rundir import get_logger
from febed.parallel.exchange import ParticleExchange
from febed.parallel.partition import cell_owners
from febed.runs.coupled import CoupledRun

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from gas_step import solver_counts  # noqa: E402


class _CpuClock:
    """Stands in for the `time` module in `febed.solver`: its timers then add up CPU seconds of this process."""

    perf_counter = staticmethod(time.process_time)


def loads(s) -> dict:
    """This rank's load now: particles, ghosts, listed pairs, gas nodes (and, with the particles by work, the
    nodes of its particles' cells that it lacks: the census's `foreign_nodes`)."""
    P = s.dem.particles
    out = {
        "owned": int(P.n_owned),
        "ghosts": int(P.n_ghost),
        "pairs": int(s.dem.pairs.size),
        "nodes_owned": int(s.ma.num_owned_dofs),
        "nodes_local": int(s.ma.num_dofs),
        "cells_owned": int(s.ma.num_owned_cells),
    }
    c = s.coupler
    if isinstance(c, OwnerCoupler) and s.located:
        out["foreign_nodes"] = int(np.count_nonzero(c.nodes.local[c.touched()] < 0))
    return out


def _timed(comm, fn, reps: int) -> tuple[float, float]:
    """(minimum, median) seconds of fn() over reps calls, each started together on every rank."""
    import numpy as np

    t = np.empty(reps)
    for k in range(reps):
        comm.Barrier()
        t0 = time.perf_counter()
        fn()
        t[k] = time.perf_counter() - t0
    comm.Allreduce(MPI.IN_PLACE, t, op=MPI.MAX)  # a call ends when its slowest rank does
    return float(t.min()), float(np.median(t))


def pingpong(comm, ghosts: int, movers: int) -> None:
    """Message costs between ranks 0 and 1 and of febed's ghost update and rebuild exchanges, emulated.

    The minimum over many repetitions is the cost of the calls themselves (no rank descheduled meanwhile);
    the median shows what a shared machine adds.
    """
    import numpy as np

    if comm.size != 2:
        raise SystemExit("--pingpong: run on 2 ranks (mpirun -n 2)")
    other = 1 - comm.rank

    def roundtrip(buf):
        def go():
            if comm.rank == 0:
                comm.Send(buf, dest=1)
                comm.Recv(buf, source=1)
            else:
                comm.Recv(buf, source=0)
                comm.Send(buf, dest=0)

        return go

    small = _timed(comm, roundtrip(np.zeros(8, dtype=np.uint8)), 2000)
    big = _timed(comm, roundtrip(np.zeros(4 << 20, dtype=np.uint8)), 40)
    x = np.zeros(1)
    red = _timed(comm, lambda: comm.Allreduce(MPI.IN_PLACE, x), 2000)
    sb, rb = np.zeros((ghosts, 6)), np.zeros((ghosts, 6))
    red2 = np.zeros(2)

    def update():  # ExchangeParticles.update_ghosts: the rebuild test's reduction and one message each way
        reqs = [
            comm.Iallreduce(red2[:1], red2[1:], op=MPI.MAX),
            comm.Irecv(rb, source=other, tag=13),
            comm.Isend(sb, dest=other, tag=13),
        ]
        MPI.Request.Waitall(reqs)

    upd = _timed(comm, update, 2000)
    fb, ib = np.zeros((ghosts, 12)), np.zeros((ghosts, 3), dtype=np.int64)
    rfb, rib = np.zeros_like(fb), np.zeros_like(ib)
    rows = {f"f{k}": np.zeros((movers, 3)) for k in range(12)}

    def rebuild():  # migrate (reductions, alltoall of the leaving rows) and refresh_ghosts
        for _ in range(4):
            comm.allreduce(1.0, op=MPI.MAX)
        comm.alltoall([None if r == comm.rank else {"rows": rows} for r in range(2)])
        counts, recv = np.array([ghosts, ghosts], dtype=np.int64), np.zeros(2, dtype=np.int64)
        comm.Alltoall(counts, recv)
        reqs = [
            comm.Irecv(rfb, source=other, tag=11),
            comm.Irecv(rib, source=other, tag=12),
            comm.Isend(fb, dest=other, tag=11),
            comm.Isend(ib, dest=other, tag=12),
        ]
        MPI.Request.Waitall(reqs)

    reb = _timed(comm, rebuild, 300)
    if comm.rank == 0:
        us = [small[0] / 2 * 1e6, small[1] / 2 * 1e6]
        bw = [(4 << 20) / (b / 2) / 1e9 for b in big]
        print(f"latency {us[0]:.2f} µs (8 B, half the fastest round trip; median {us[1]:.2f})")
        print(f"bandwidth {bw[0]:.2f} GB/s (4 MB, fastest; median {bw[1]:.2f})")
        print(f"allreduce of 8 B on 2 ranks: {red[0] * 1e6:.2f} µs (median {red[1] * 1e6:.2f})")
        print(f"ghost update, {ghosts} rows each way + reduction: {upd[0] * 1e6:.1f} µs (median {upd[1] * 1e6:.1f})")
        print(
            f"rebuild exchanges, {movers} leaving, {ghosts} ghosts: {reb[0] * 1e6:.0f} µs (median {reb[1] * 1e6:.0f})"
        )


@njit(cache=True)
def _probe_loop(n: int) -> float:  # pragma: no cover
    """A dependent chain of multiply-adds on four registers: the core's speed, not the memory's."""
    a, b, c, d = 1.0, 0.5, 0.25, 0.125
    for _ in range(n):
        a = a * 0.999999 + b
        b = b * 0.999999 + c
        c = c * 0.999999 + d
        d = d * 0.999999 + 1e-9
    return a + b + c + d


def core_probe(s, comm, n: int = 100_000, trips: int = 10, mb: int = 16) -> tuple[list, list, list]:
    """Before each of the solver's gas steps time `_probe_loop(n)` and, on 2 ranks, `trips` round trips of
    8 bytes between them (after one that waits for the later rank) and, every 4th step, a sum over `mb` MB
    on both at once; returns the lists the seconds go into (the loop's, half a round trip's, the sum's)."""
    _probe_loop(10)  # compiled (or loaded from the cache) before the window
    loop, message, memory = [], [], []
    block = np.ones(mb * (1 << 20) // 8)
    inner = s.advance_particles
    buf = np.zeros(1)
    other = 1 - comm.rank

    def roundtrip() -> None:
        if comm.rank == 0:
            comm.Send(buf, dest=other)
            comm.Recv(buf, source=other)
        else:
            comm.Recv(buf, source=other)
            comm.Send(buf, dest=other)

    def call(*a, **k):
        t = time.perf_counter()
        _probe_loop(n)
        loop.append(time.perf_counter() - t)
        if comm.size == 2:
            roundtrip()  # both ranks here
            t = time.perf_counter()
            for _ in range(trips):
                roundtrip()
            message.append((time.perf_counter() - t) / (2 * trips))
            if len(message) % 4 == 0:
                roundtrip()  # start together
                block.sum()
                t = time.perf_counter()
                block.sum()
                memory.append(time.perf_counter() - t)
        return inner(*a, **k)

    s.advance_particles = call
    return loop, message, memory


def _barriers(s, comm) -> dict:
    """Start each phase of the solver's step (DEM, coupling, gas) with a barrier; returns its CPU seconds per phase.

    A phase's time then holds its own work only, not the wait for another rank to finish the phase before
    (a barrier inside a phase's timer is recorded apart, to be subtracted; the one before the particle
    sub-steps is outside every timer).
    """
    waits = {"dem": 0.0, "coupling": 0.0, "gas": 0.0, "untimed": 0.0}

    def wrap(obj, name: str, phase: str) -> None:
        inner = getattr(obj, name)

        def call(*a, **k):
            t = time.process_time()
            comm.Barrier()
            waits[phase] += time.process_time() - t
            return inner(*a, **k)

        setattr(obj, name, call)

    wrap(s, "advance_particles", "untimed")  # before its own timers start
    wrap(s.dem, "advance", "dem")
    wrap(s, "project", "coupling")
    wrap(s.gas, "step", "gas")
    return waits


def _ksp_seconds() -> float:
    """Wall seconds this process has spent in PETSc's KSPSolve and KSPSetUp so far (PETSc.Log.begin first)."""
    return sum(PETSc.Log.Event(name).getPerfInfo()["time"] for name in ("KSPSolve", "KSPSetUp"))


def timed_calls(comm, fn, reps: int) -> list[float]:
    """(fastest, median) seconds of this rank's own part of reps calls of fn, each started together.

    CPU seconds on one process (nothing to wait for), wall seconds on several.
    """
    clock = time.process_time if comm.size == 1 else time.perf_counter
    t = np.empty(reps)
    for k in range(reps):
        comm.Barrier()
        t0 = clock()
        fn()
        t[k] = clock() - t0
    return [float(t.min()), float(np.median(t))]


def exchange_calls(s, comm) -> dict:
    """The gas step's and the coupling's calls that exchange between ranks (or reduce over them), one of each.

    On one process they do little or nothing; on several each costs the software's overhead as well as the
    messages (`scaling_projection.py` counts how many a gas step makes).
    """
    import dolfinx.la

    g = s.gas
    vec = s.ma._vector(g.gdim)  # the coupling's nodal vector (`MeshArrays.accumulate`)
    return {
        "scatter_forward": vec.scatter_forward,  # a DOLFINx halo update of a nodal field
        "scatter_reverse": lambda: vec.scatter_reverse(dolfinx.la.ScatterMode.add),  # nodal sums to owners
        "vec_scatter": lambda: g.ops.extension.extend("q", g._q.vector, g._q.x.array),  # extra columns
        "ghost_update": lambda: g.pressure.x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD),
        "allreduce": lambda: comm.allreduce(1.0, op=MPI.MAX),  # a float (mpi4py's pickled reduction)
        "Allreduce": lambda: comm.Allreduce(MPI.IN_PLACE, np.zeros(2), op=MPI.MAX),  # a buffer
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", default=str(ROOT / "demos" / "pseudo2d" / "C2.toml"))
    parser.add_argument("--restart", help="run folder (its newest checkpoint) or checkpoint file; default runs/C2")
    parser.add_argument("--pingpong", action="store_true", help="measure the message latency and bandwidth instead")
    parser.add_argument("--ghosts", type=int, default=2200, help="--pingpong: ghost rows per rank")
    parser.add_argument("--movers", type=int, default=50, help="--pingpong: particles migrating per rebuild")
    parser.add_argument("--warmup", type=float, default=0.004, help="simulated seconds before timing")
    parser.add_argument("--sim-time", type=float, default=0.01, help="simulated seconds timed")
    parser.add_argument("--set", action="append", default=[], help="case overrides KEY=VALUE (repeatable)")
    parser.add_argument("--rebuilds", type=int, default=0, help="then time this many pair-list rebuilds")
    parser.add_argument("--tag", default="", help="appended to the output file name")
    parser.add_argument(
        "--barriers", action="store_true",
        help="a barrier before each phase of the step, its time recorded apart (each phase's own work)",
    )  # fmt: skip
    parser.add_argument(
        "--staged", action="store_true",
        help="on one process, step the DEM the way every rank of a parallel run does (staged kernels, "
        "rebuilds through the particle exchange)",
    )  # fmt: skip
    parser.add_argument(
        "--concurrent", action="store_true",
        help="on several ranks, every rank runs the serial window alone, each phase started together: the "
        "single-core costs with every core doing the same phase",
    )  # fmt: skip
    parser.add_argument(
        "--owners", action="store_true",
        help="on one process, couple through the particles' owners (the coupling of particle_partition = work)",
    )  # fmt: skip
    parser.add_argument("--calls", type=int, default=0, help="then time this many of each exchange call")
    parser.add_argument("--profile", action="store_true", help="record the timed window with cProfile, per rank")
    parser.add_argument(
        "--core-speed", action="store_true", help="time a fixed loop before every gas step: each core's pace"
    )
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "out"))
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    if args.pingpong:
        pingpong(comm, args.ghosts, args.movers)
        return
    if not args.restart:
        if not (ROOT / "runs" / "C2" / "checkpoints").is_dir():
            if comm.rank == 0:
                print(
                    "skipped: give --restart RUN_DIR, a C2 run folder with a checkpoint (e.g. of "
                    "`febed run demos/pseudo2d/C2.toml --set run.end_time=5`, which writes runs/C2)"
                )
            return
        args.restart = str(ROOT / "runs" / "C2")
    PETSc.Log.begin()  # PETSc's event times: the linear solves' share of the gas phase
    concurrent = args.concurrent and comm.size > 1
    run_comm = MPI.COMM_SELF if concurrent else comm  # concurrent: every rank runs the whole case alone
    if concurrent:
        tmp = Path(tempfile.mkdtemp(prefix="febed-measure-"))
    else:
        tmp = Path(comm.bcast(tempfile.mkdtemp(prefix="febed-measure-") if comm.rank == 0 else None, root=0))
    quiet = [f"output.directory={tmp}", "output.field_interval=100", "output.particle_interval=100"]
    case = load_case(args.case, quiet + args.set)
    febed.solver.time = _CpuClock  # the solver's split DEM / coupling / gas / output in CPU seconds
    log = get_logger(None, run_comm)
    run = CoupledRun(case, tmp, log, run_comm, restart=load_checkpoint(Path(args.restart), run_comm))
    s = run.solver
    if args.staged and run_comm.size == 1:  # an exchange on one process: no messages, the parallel code path
        s.dem.attach_exchange(ParticleExchange(s.ma, cell_owners(s.md.mesh)))
    if args.owners and run_comm.size == 1:  # the coupling of `particle_partition = "work"`, on one process
        s.coupler = OwnerCoupler.build(s.ma, s.md.mesh, s.gas.Q, s.md.mesh, s.depth, **s.law)
        s._located = -1  # locate the particles again, on the new coupler
    waits = _barriers(s, comm) if args.barriers or concurrent else None
    probes, messages, memory = core_probe(s, run_comm) if args.core_speed else (None, None, None)
    run.advance_to(s.t + args.warmup)
    comm.barrier()
    before = s.timers.as_dict()
    ksp0 = _ksp_seconds()
    solver0 = solver_counts()
    waits0 = dict(waits) if waits else None
    probes0 = len(probes) if probes is not None else 0
    memory0 = len(memory) if memory is not None else 0
    steps0, builds0, dem0 = s.steps, s.dem.pairs.builds, s.dem.steps
    start = loads(s)
    w0, c0 = time.perf_counter(), time.process_time()
    sim0 = s.t
    samples = []
    profile = cProfile.Profile() if args.profile else None
    if profile:
        profile.enable()
    while s.t < sim0 + args.sim_time - 1e-12:
        run.advance_to(min(s.t + 0.002, sim0 + args.sim_time))
        samples.append(loads(s))
    w1, c1 = time.perf_counter(), time.process_time()
    if profile:
        profile.disable()
        Path(args.out).mkdir(parents=True, exist_ok=True)
        profile.dump_stats(
            Path(args.out) / f"profile_{Path(args.case).stem}_P{comm.size}{args.tag}_r{comm.rank}.pstats"
        )
    comm.barrier()
    after = s.timers.as_dict()
    ksp1 = _ksp_seconds()
    solver1 = solver_counts()
    mine = {
        "rank": comm.rank,
        "t0": sim0,
        "t1": s.t,
        "wall": w1 - w0,
        "cpu": c1 - c0,
        "split": {k.removeprefix("wall_"): after[k] - before[k] for k in after},  # CPU seconds
        "waits": {k: waits[k] - waits0[k] for k in waits} if waits else None,  # CPU seconds at the barriers
        "ksp": ksp1 - ksp0,  # wall seconds in PETSc's KSPSolve and KSPSetUp (part of the gas phase)
        # the pressure solver's flops, messages sent, bytes sent and reductions in the window (PETSc's counts)
        "solver": dict(zip(("flops", "messages", "bytes", "reductions"), (solver1 - solver0).tolist(), strict=True)),
        "overrides": args.set,
        "staged": bool(args.staged or comm.size > 1),
        "gas_steps": s.steps - steps0,
        "dem_steps": int(s.dem.steps - dem0),
        "builds": int(s.dem.pairs.builds - builds0),
        "start": start,
        "samples": samples,
        "concurrent": concurrent,  # every rank ran the serial window alone
        # --core-speed: seconds of the fixed loop before each gas step of the window (this rank's core's pace)
        "core_probe": probes[probes0:] if probes is not None else None,
        "message_probe": messages[probes0:] if messages else None,  # and half a round trip to the other rank
        "memory_probe": memory[memory0:] if memory else None,  # and a pass over 16 MB, both ranks at once
    }
    if concurrent:
        comm.barrier()
        shutil.rmtree(tmp, ignore_errors=True)
    if args.rebuilds:
        mine["rebuild"] = timed_calls(comm, s.dem.rebuild, args.rebuilds)
        mine["rebuild_loads"] = loads(s)
        if comm.size == 1:  # the parallel rebuild's own work, on one core: history by key, locating every particle
            dem = s.dem

            def keyed():
                dem.save_history()
                dem.rebuild()

            def locate_all():
                P = dem.particles
                locate(s.ma, P.pos[: P.n_owned], np.ascontiguousarray(P.cell[: P.n_owned], dtype=np.int32))

            mine["rebuild_keyed"] = timed_calls(comm, keyed, args.rebuilds)
            mine["locate"] = timed_calls(comm, locate_all, args.rebuilds)
            W = s.gas.pressure.weighted  # the drag-weighted operator, if the case uses it
            if W is not None:  # its fill through PETSc's COO assembly, which only runs on several ranks
                rows = np.repeat(np.arange(W.indptr.size - 1), np.diff(W.indptr))
                coo = coo_matrix(MPI.COMM_SELF, W.indptr.size - 1, rows, W.cols)
                if coo is not None:
                    mine["coo_fill"] = timed_calls(comm, lambda: coo.fill(W.vals), args.rebuilds)
                    mine["coo_entries"] = int(W.cols.size)
                    coo.M.destroy()
            # the coupling's work over the mesh nodes, per gas step: the projection's filter passes and division
            # (no particle deposited) and, with the nodal reaction, the filter's transpose of ∇p
            P = dem.particles
            n = P.n_owned
            d_orig, n_orig = s._originals()
            none = np.zeros(n, dtype=bool)
            zeros = np.zeros(n)

            def coupling_nodes():
                s.coupler.project_to_gas(d_orig, n_orig, zeros, P.vel[:n], owned=none)
                if s._nodal_reaction():
                    s.coupler.filter_transpose(s.gas.grad_p)

            mine["coupling_nodes"] = timed_calls(comm, coupling_nodes, args.rebuilds)
            # last (the DEM stays on the parallel code path): a rebuild through an exchange on one process, which
            # migrates and locates nobody and has no ghosts, but keys and restores the history, and re-sorts the
            # rows every sort_every builds as on several ranks (the keyed rebuild above re-sorts them every time)
            if dem.exchange is None:
                dem.attach_exchange(ParticleExchange(s.ma, cell_owners(s.md.mesh)))
            mine["rebuild_staged"] = timed_calls(comm, dem.rebuild, args.rebuilds)
    if args.calls:
        mine["calls"] = {k: timed_calls(comm, fn, args.calls) for k, fn in exchange_calls(s, comm).items()}
    every = comm.gather(mine, root=0)
    if comm.rank == 0:
        name = Path(args.case).stem
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        path = out / f"measured_{name}_P{comm.size}{args.tag}.json"
        path.write_text(json.dumps({"case": name, "ranks": comm.size, "per_rank": every}, indent=1))
        for m in every:
            print(
                f"rank {m['rank']}: wall {m['wall']:.1f} s, cpu {m['cpu']:.1f} s, {m['gas_steps']} gas steps, "
                f"{m['dem_steps']} DEM steps, {m['builds']} builds; loads at the end {m['samples'][-1]}"
            )
        print(f"written {path}")
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
