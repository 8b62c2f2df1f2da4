"""Driving a coupled run: output and probe intervals, progress, the probe quantities.

`run_coupled` builds the `CoupledSolver` of a case and calls its `step()` until the end time; between
steps it writes

* probes (`probes.csv`, every `[output] probe_interval`): time, gas step, DEM sub-steps per gas step,
  particle count, particles removed at the outlet, particle kinetic energy, bed height, cross-section
  averaged pressures, the bed pressure drop, gas CFL, Poisson iterations, gas mass balance, clipped nodes
  and the wall-time split DEM / coupling / gas / output (cumulative seconds);
* fields (`fields.xdmf`: u, p, ε, α_p) every `field_interval` and particles (`particles/*.vtp` + `.pvd`)
  every `particle_interval`, for ParaView;
* a progress line every `progress_interval` wall seconds (live on a terminal, always in `febed.log`);
* checkpoints (`checkpoints/checkpoint_<step>.npz`, see `febed.io.checkpoint` and `febed.restart`) every
  `checkpoint_interval` simulated or `checkpoint_wall_interval` wall seconds, on SIGINT/SIGTERM/SIGUSR1 and at
  the end; `status.json` says whether the run is running, finished, failed or interrupted.

After every gas step the solver's health checks run (`CoupledSolver.check`). A failure stops the run with
its message, writes the last state that passed the checks (kept in memory at each probe time) as a
checkpoint, and exits non-zero. SIGINT/SIGTERM/SIGUSR1 (Ctrl-C, a batch system's time limit) finish the
current gas step, write a checkpoint and stop (`Interrupted`); ranks agree on the step at which they stop.
A gas step whose DEM sub-steps would take long (a tiny DEM step) is not waited for: the sub-steps ask for
the signal every fraction of a second (`febed.dem.solver.DEM.stop_check`, agreed over the ranks) and the
run stops with the last good state as its checkpoint (`stopped_mid_step`). A second signal stops at once
(`StopNow`), naming the newest checkpoint there is. Under Open MPI's mpirun, SIGUSR1 is the one to send:
mpirun forwards it to the ranks as it is, whereas on SIGTERM or SIGINT it kills them after a short grace
that a gas step on a loaded machine can outlast.

An output error (a full disk, permissions, an I/O error) while writing probes, fields, particles, a
checkpoint or status.json stops the run on every rank (`guarded_write`, `OutputFailure`): the current
state is written as a checkpoint if the disk takes it (the older ones are removed only after a newer one is
complete), status.json says "failed" with the file and the error and where the newest checkpoint is, and
`febed run` exits with status 3. The same helpers serve the pure-DEM, gas-only and one-way drivers.

Definitions:

* **Bed height**: the height (along gravity) below which `[output] bed_fraction` of the particle volume lies.
* **Cross-section averaged pressure** at height z: mean of p over a uniform grid of sample points filling
  the mesh's cross-section at z (midpoint rule; points outside the mesh are dropped).
* **Bed pressure drop** `dp_bed`: ⟨p⟩ at the bottom of the mesh minus ⟨p⟩ at the top, less the weight of
  the gas column ρ_g g H, i.e. the part of the pressure drop that carries the particles.
"""

from __future__ import annotations

import math
import os
import signal
import sys
import time
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed import restart as rs
from febed.coupling.exchange import solid_volume
from febed.coupling.interpolate import interpolate
from febed.coupling.locate import FOUND, locate
from febed.coupling.weights import compute_weights
from febed.dem.solver import DEMFailure, StopRequested
from febed.io.checkpoint import FOLDER, CheckpointError, write_checkpoint
from febed.io.probes import ProbeFile
from febed.io.progress import Progress, RateMeter
from febed.io.rundir import STATUS_FILE, write_status
from febed.solver import RunFailure, build_solver

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1)  # finish the step, checkpoint, stop


class Interrupted(Exception):
    """The run stopped on a signal after writing a checkpoint; `signum` is the signal."""

    def __init__(self, signum: int, message: str):
        super().__init__(message)
        self.signum = signum


class StopNow(KeyboardInterrupt):
    """A stop signal that cannot wait for the end of a step: during start-up, or a second one; `signum` is it."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class OutputFailure(RunFailure):
    """The run's output could not be written (a full disk, permissions, an I/O error).

    The message names the file and the operating system's error. `checkpoint`: it was a checkpoint that failed.
    """

    def __init__(self, message: str, checkpoint: bool = False):
        super().__init__(message)
        self.checkpoint = checkpoint


def agree(comm, sig: int, *due: bool) -> tuple:
    """(largest signal number over the ranks, then rank 0's value of each `due` flag) on every rank (collective).

    Decisions taken from a rank's own wall clock must be rank 0's: the ranks' clocks disagree, and a rank
    acting on its own would make collective calls its partners never make (a hang).
    """
    if comm.size == 1:
        return (sig, *due)
    flags = np.array([sig, *(due if comm.rank == 0 else [False] * len(due))], dtype=np.int64)
    comm.Allreduce(MPI.IN_PLACE, flags, op=MPI.MAX)
    return (int(flags[0]), *(bool(f) for f in flags[1:]))


# ------------------------------------------------------------------------------------------ output errors
def os_error_text(error: OSError, path) -> str:
    """'cannot write FILE: [Errno 28] No space left on device' (the error's own file name if it has one)."""
    name = error.filename or path
    what = f"[Errno {error.errno}] {error.strerror}" if error.errno and error.strerror else str(error)
    return f"cannot write {name}: {what}"


def guarded_write(comm, path, write, /, *args, **kwargs):
    """`write(*args, **kwargs)` on every rank, its output errors raised as OutputFailure on every rank (collective).

    An OSError (ENOSPC, EACCES, EIO, ...), or the RuntimeError of DOLFINx's XDMF/HDF5 writer, on any rank
    becomes one OutputFailure naming the file (the error's own, else `path`) and the error; the ranks agree
    through one allgather (none on one process). Returns what `write` returns.
    """
    err = result = None
    try:
        result = write(*args, **kwargs)
    except OSError as e:
        err = os_error_text(e, path)
    except RuntimeError as e:
        if type(e) is not RuntimeError:  # febed's own errors (RunFailure, CheckpointError, ...) are subclasses
            raise
        err = f"cannot write {path}: {e}"
    if comm is not None and comm.size > 1:
        err = next((m for m in comm.allgather(err) if m), None)
    if err:
        raise OutputFailure(err)
    return result


def close_files(comm, *files) -> None:
    """Close each of `files` (each has `path` and `close()`; None skipped) and then raise the first OutputFailure."""
    first = None
    for f in files:
        if f is None:
            continue
        try:
            guarded_write(comm, f.path, f.close)
        except OutputFailure as e:
            first = first or e
    if first is not None:
        raise first


def checkpoint_or_fail(write, *args):
    """`write_checkpoint(*args)` (or another `write` raising CheckpointError on every rank) as OutputFailure."""
    try:
        return write(*args)
    except CheckpointError as e:
        raise OutputFailure(str(e), checkpoint=True) from None


# -------------------------------------------------------------------------------------------------- status
_ENDED: dict[str, str] = {}  # run folder -> the last state this process wrote to its status.json


def write_run_status(outdir, state: str, t: float, end: float, step: int, message: str = "", comm=MPI.COMM_WORLD,
                     collective: bool = True) -> None:  # fmt: skip
    """Write the run's `status.json` (`febed.io.rundir.write_status`, rank 0).

    `collective`: every rank calls, and a failed write raises OutputFailure on every rank. Otherwise (the
    recording of a failure, possibly on one rank only) a failed write is said on stderr and the run goes on
    to stop with its own error.
    """
    _ENDED[os.path.abspath(outdir)] = state
    path = Path(outdir) / STATUS_FILE
    if collective:
        guarded_write(comm, path, write_status, outdir, state, t, end, step, message, comm)
        return
    try:
        write_status(outdir, state, t, end, step, message, comm)
    except OSError as e:
        print(f"febed: {os_error_text(e, path)}: it could not record the run as {state}", file=sys.stderr, flush=True)


def last_state(outdir) -> str | None:
    """The state this process last wrote to the `status.json` of `outdir` (None: none since `forget_state`)."""
    return _ENDED.get(os.path.abspath(outdir))


def forget_state(outdir) -> None:
    """Forget what this process wrote to the `status.json` of `outdir` (a new run in the same process)."""
    _ENDED.pop(os.path.abspath(outdir), None)


def newest_checkpoint(outdir) -> str:
    """'the newest checkpoint is .../checkpoint_<step>.npz (t = ... s)', or 'there is no checkpoint' (this rank)."""
    from febed.io.checkpoint import list_checkpoints, read_meta

    for path in reversed(list_checkpoints(Path(outdir) / FOLDER)):
        try:
            t = read_meta(path)["time"]
        except (CheckpointError, KeyError):
            continue
        return f"the newest checkpoint is {path} (t = {t:.6g} s)"
    return "there is no checkpoint"


# ------------------------------------------------------------------------------------ the end of a run
def after_step(run, t: float, checkpoint_due: bool) -> bool:
    """The end of a step of any run (coupled, pure DEM, gas only): returns whether a progress line is due.

    Agrees with the other ranks on a stop signal and on the wall-clock triggers (`agree`: rank 0's clock), writes
    a checkpoint when one is due (a signal, `[output] checkpoint_wall_interval`, or `checkpoint_due`: the
    simulated-time interval), and after a signal ends the progress line, sets the status to interrupted and
    raises `Interrupted`. When a progress line is due, status.json is rewritten with the current time. `run`
    has comm, case, display, `_signal`, `_last_checkpoint`, `_last_progress`, `checkpoint()` and `status()`
    (collective).
    """
    o = run.case.output
    now = time.perf_counter()
    sig, wall_due, show = agree(
        run.comm, run._signal, now - run._last_checkpoint >= o.checkpoint_wall_interval,
        now - run._last_progress >= o.progress_interval,
    )  # fmt: skip
    if sig or wall_due or checkpoint_due:
        run.checkpoint()
    if show and not sig:
        run.status("running")  # status.json follows the progress line: its time and step are recent
    if sig:
        name = signal.Signals(sig).name
        run.display.end()
        run.status("interrupted", f"stopped by {name}")
        raise Interrupted(sig, f"stopped by {name} at t = {t:.6g} s after a checkpoint; continue with --restart")
    return show


def run_to_end(run, end: float) -> None:
    """Advance `run` (coupled, pure DEM or gas only) to `end`, then write the final checkpoint and status.

    The stop signals are caught meanwhile (`catch_signals`). However the run ends, its files are closed and
    the handlers restored; an error closing them after another error is logged and does not hide the first.
    An output error (`OutputFailure`) is recorded by `record_output_failure`; a second stop signal
    (`StopNow`) stops at once and becomes `Interrupted` (collective).
    """
    restore_signals = run.catch_signals()
    closed, last_output = False, True
    try:
        run.advance_to(end)
        run.checkpoint()
        run.status("finished")
        run.close()
        closed = True
    except OutputFailure as e:
        last_output = False
        record_output_failure(run, e)
        raise
    except KeyboardInterrupt as e:
        last_output = False
        raise stopped_at_once(run, e) from None
    finally:
        try:
            if not closed:
                close_after_error(run, last_output and not getattr(run, "mid_step", False))
        finally:
            restore_signals()


def close_after_error(run, last_output: bool) -> None:
    """Close a run that stopped on an error or signal, with its last output if `last_output`; errors are logged."""
    if getattr(run, "broken", False):  # a rank failed alone: collective calls would hang
        return
    try:
        run.close(last_output)
    except (RunFailure, OSError, RuntimeError) as e:
        run.log.warning(f"could not write the last output while stopping: {e}")


def write_good_state(run) -> str:
    """Write the last good state (`run.good`) as a checkpoint unless this run wrote a newer one (collective).

    Returns where that state is, as a clause of a message.
    """
    t_good = run.good[1]["time"]
    written = getattr(run, "checkpoint_written", None)  # (time, path) of this run's newest checkpoint
    if written is not None and written[0] >= t_good:
        return f"last good state (t = {written[0]:.6g} s) in {written[1]}"
    try:
        path = run.checkpoint(run.good)
        return f"last good state (t = {t_good:.6g} s) in {path}"
    except (RunFailure, CheckpointError) as e:
        return f"could not write the last good state: {e}"


def record_failure(run, error, collective: bool = True) -> None:
    """Record a failed run of any mode: the last good state, the status and the log.

    Ends the progress line, writes the last good state (`run.good`) as a checkpoint if `collective` (every rank
    takes part), sets the status to failed and logs the error with where that state is.
    """
    run.display.end()
    where = f"; {write_good_state(run)}" if run.good is not None and collective else ""
    run.status("failed", f"{error}{where}", collective=False)
    run.log.error(f"run failed: {error}{where}")


def record_output_failure(run, error: OutputFailure) -> None:
    """Record a run stopped by an output error: a checkpoint of the state if one can be written, status, log.

    Unless it was a checkpoint that failed, the current state (whole steps, passed the checks) is written as a
    checkpoint; either way the message says where the newest checkpoint is. The previous checkpoints are never
    removed before a newer one is complete (`febed.io.checkpoint.write_checkpoint`). Collective.
    """
    run.display.end()
    run.output_failed = True
    fix = "free disk space" if "No space left" in str(error) else "fix that"
    saved = None
    if not error.checkpoint:
        try:
            path = run.checkpoint()
            saved = f"the state at t = {run.checkpoint_written[0]:.6g} s is saved in {path}"
        except RunFailure:  # the same cause, most likely: the newest checkpoint is the one to continue from
            pass
    if saved:
        where = f"; {saved}: {fix}, then continue with --restart"
    else:
        newest = newest_checkpoint(run.outdir)
        again = "continue from it with --restart" if newest.startswith("the newest") else "run it again (--overwrite)"
        either = "" if error.checkpoint else "a checkpoint of this moment could not be written either; "
        where = f"; {either}{newest}: {fix}, then {again}"
    message = f"{error}{where}"
    run.status("failed", message, collective=False)
    if run.comm.rank == 0:  # every rank knows it: said once
        run.log.error(f"run failed: {message}")
    error.args = (message,)


def stopped_mid_step(run, what: str) -> Interrupted:
    """A stop signal came in the middle of a step (`what`): write the last good state, status; the Interrupted.

    The state in memory is half-way through a step, so the last complete state that passed the checks
    (`run.good`) is what a restart continues from. Collective (the ranks agreed on the stop).
    """
    run.mid_step = True
    run.display.end()
    sig = run._signal or signal.SIGTERM
    name = signal.Signals(sig).name
    where = write_good_state(run)
    message = f"stopped by {name} in the middle of {what}; {where}; continue with --restart"
    run.status("interrupted", message, collective=False)
    if run.comm.rank == 0:
        run.log.warning(message)
    return Interrupted(sig, message)


def stopped_at_once(run, error: KeyboardInterrupt) -> Interrupted:
    """A second stop signal (or Ctrl-C) stopped the run at once: status, log and the Interrupted (this rank only).

    No checkpoint is written for the moment it came; the message names the newest checkpoint there is.
    """
    if run.comm.size > 1:
        run.broken = True  # the other ranks may not have stopped: no collective calls
    run.display.end()
    sig = getattr(error, "signum", signal.SIGINT)
    name = signal.Signals(sig).name
    newest = newest_checkpoint(run.outdir)
    then = "; continue from it with --restart" if newest.startswith("the newest") else ": start the run again"
    message = f"stopped at once by a second {name}, without a checkpoint of this moment; {newest}{then}"
    run.status("interrupted", message, collective=False)
    run.log.warning(message)
    return Interrupted(sig, message)


def record_exit(outdir, log, error: BaseException, end: float, t: float = 0.0, step: int = 0,
                restart: bool = False) -> None:  # fmt: skip
    """Record in status.json and the log an error that ended `febed run` before its run recorded anything.

    Errors met during start-up (building the mesh, the bed, the solver; opening the output files) or a stop
    signal then (a KeyboardInterrupt: Ctrl-C, or another stop signal carrying `signum`) would otherwise leave
    no status.json (`febed status`: "unknown") and nothing in febed.log. Nothing is done if the run already
    recorded how it ended (rank 0 writes).
    """
    if last_state(outdir) not in (None, "running"):
        return
    started = last_state(outdir) == "running"
    if isinstance(error, KeyboardInterrupt):
        name = signal.Signals(getattr(error, "signum", signal.SIGINT)).name
        when = "before the run's end" if started else "during start-up, before the first step"
        then = "its checkpoints are unchanged: continue with --restart" if restart else "run it again (--overwrite)"
        state, message = "interrupted", f"stopped by {name} {when}; {then}"
        log.warning(message)
    else:
        state = "failed"
        known = isinstance(error, (RunFailure, ValueError, OSError, RuntimeError, MemoryError))
        message = str(error) if known and str(error) else f"{type(error).__name__}: {error}"
        log.error(f"run failed: {message}")
    write_run_status(outdir, state, t, end, step, message, collective=False)


class SectionAverage:
    """Cross-section average of a nodal field at a fixed height, from sample points located once."""

    def __init__(self, ma, axis: int, height: float, lo: np.ndarray, hi: np.ndarray, per_dim: int = 40):
        """Sample points on a uniform grid over the box [lo, hi] of the cross-section at `height`."""
        gdim = ma.gdim
        others = [a for a in range(gdim) if a != axis]
        axes = [lo[a] + (np.arange(per_dim) + 0.5) * (hi[a] - lo[a]) / per_dim for a in others]
        grid = np.meshgrid(*axes, indexing="ij")
        pts = np.zeros((grid[0].size, 3))
        for a, g in zip(others, grid, strict=True):
            pts[:, a] = g.ravel()
        pts[:, axis] = height
        cell = np.full(pts.shape[0], -1, dtype=np.int32)
        cell, ref, status, _, _ = locate(ma, pts, cell)
        keep = (status == FOUND) & (cell < ma.num_owned_cells)
        self.ma = ma
        self.cell = np.ascontiguousarray(cell[keep])
        self.w = compute_weights(ma, np.ascontiguousarray(ref[keep]), self.cell)
        self.count = ma.comm.allreduce(int(keep.sum())) if ma.comm is not None else int(keep.sum())
        if self.count == 0:
            raise ValueError(f"probe height {height} m lies outside the mesh")

    def __call__(self, nodal: np.ndarray) -> float:
        """The average of nodal field `nodal` (nd,) over the section (collective)."""
        local = float(interpolate(self.ma, self.cell, self.w, nodal).sum())
        total = self.ma.comm.allreduce(local) if self.ma.comm is not None else local
        return total / self.count


def bed_height(heights: np.ndarray, volumes: np.ndarray, fraction: float, comm=MPI.COMM_WORLD) -> float:
    """Height below which `fraction` of the particle volume lies (m); NaN without particles (collective)."""
    h = np.concatenate(comm.allgather(np.asarray(heights, dtype=float)))
    v = np.concatenate(comm.allgather(np.asarray(volumes, dtype=float)))
    if h.size == 0:
        return math.nan
    order = np.argsort(h, kind="stable")
    cum = np.cumsum(v[order])
    k = int(np.searchsorted(cum, fraction * cum[-1]))
    return float(h[order][min(k, h.size - 1)])


class CoupledRun:
    """A coupled run with its output: `advance_to(t)` steps the solver, writing probes, output, checkpoints."""

    def __init__(self, case, outdir: Path, log, comm=MPI.COMM_WORLD, md=None, restart=None):
        """Build the mesh (unless given), the coupled solver, the probes and the writers.

        Args:
            case: a validated `Case` (`febed.load_case`) of mode "cfd-dem".
            outdir: its output folder, prepared and locked by `febed.prepare_output`.
            log: the logger to report to (`febed.get_logger(outdir)`).
            comm: the MPI communicator (every rank builds the run together).
            md: an already loaded mesh (`febed.load_case_mesh`); None loads the case's.
            restart: (path, arrays, meta) of a checkpoint (`febed.io.checkpoint.load_checkpoint`) to continue.
        """
        from febed.meshing import load_case_mesh

        self.case = case
        self.outdir = Path(outdir)
        self.log = log
        self.comm = comm
        self.md = md if md is not None else load_case_mesh(case, comm, cache_dir=self.outdir / "mesh")
        self.solver = s = build_solver(case, self.md, log)
        self.axis = 1 if self.md.gdim == 2 else 2
        x = self.md.mesh.geometry.x
        lo = np.minimum.reduce(comm.allgather(x.min(axis=0)))
        hi = np.maximum.reduce(comm.allgather(x.max(axis=0)))
        self.height = hi[self.axis] - lo[self.axis]
        eps_h = 1e-9 * self.height
        self.sections = {
            "bottom": SectionAverage(s.ma, self.axis, lo[self.axis] + eps_h, lo, hi),
            "top": SectionAverage(s.ma, self.axis, hi[self.axis] - eps_h, lo, hi),
        }
        for z in case.output.probe_heights:
            self.sections[f"{z:g}"] = SectionAverage(s.ma, self.axis, z, lo, hi)
        heights = [f"p_{name}" for name in self.sections]
        self.columns = [
            "step", "dt", "n_sub", "particles", "left_outlet", "kinetic_energy", "bed_height", "dp_bed", *heights,
            "cfl", "poisson_iterations", "gas_inflow", "gas_mass_imbalance", "clipped_nodes",
            "wall_dem", "wall_coupling", "wall_gas", "wall_output",
        ]  # fmt: skip
        if s.groups is not None:  # PCPM: cumulative event counts (difference them for per-interval rates)
            self.columns += ["groups", "originals", "crushed", "merged", "events_deferred", "event_energy"]
        o = case.output
        self.next = {"probe": 0.0, "field": 0.0, "particle": 0.0, "checkpoint": o.checkpoint_interval}
        self.last = {"probe": None, "field": None, "particle": None}  # time of the last one written
        self.segment = 0  # restarts so far: fields of segment k go to fields.restart<k>.xdmf
        self._particle_files = []
        self._probe_rows = None
        self.restarted_from = None
        if restart is not None:
            path, arrays, meta = restart
            rs.restore(self, arrays, meta)
            self.restarted_from = path
        self.probes = self.fields = None
        self.broken = False  # a rank failed alone: collectives would hang
        self.output_failed = False  # an output error stopped the run: nothing more is written
        self.mid_step = False  # stopped in the middle of a gas step: the state in memory is not a whole step
        self._closed = False
        self.checkpoint_written = None  # (time, path) of the newest checkpoint this run wrote
        try:
            self.probes = guarded_write(
                comm, self.outdir / "probes.csv", ProbeFile, self.outdir / "probes.csv", self.columns, comm,
                restart_time=s.t if restart else None, keep_rows=self._probe_rows,
            )  # fmt: skip
            self._writers()
        except OutputFailure:
            close_after_error(self, False)
            raise
        self.display = Progress(log, comm.rank)
        self.good = None  # (arrays, meta) of the last state that passed the health checks
        self._signal = 0
        self._last_progress = self._last_checkpoint = time.perf_counter()
        self._meter = RateMeter(s.t)

    def _writers(self) -> None:
        import dolfinx.fem

        from febed.io.fields import FieldWriter
        from febed.io.particles import ParticleWriter

        s = self.solver
        self.alpha = dolfinx.fem.Function(s.gas.Q)
        funcs = dict(s.gas.functions())
        funcs["alpha_p"] = self.alpha
        name = "fields.xdmf" if self.segment == 0 else f"fields.restart{self.segment}.xdmf"
        self.fields = guarded_write(self.comm, self.outdir / name, FieldWriter, self.outdir / name, self.md.mesh,
                                    funcs, self.comm)  # fmt: skip
        folder = self.outdir / "particles"
        self.particles = guarded_write(self.comm, folder, ParticleWriter, folder, comm=self.comm,
                                       entries=self._particle_files)  # fmt: skip

    # ------------------------------------------------------------------------------------- schedule
    def schedule(self) -> dict:
        """The output schedule, for checkpoints: next/last output times, files and rows written so far."""
        return {
            "next": dict(self.next),
            "last": dict(self.last),
            "particle_files": [list(e) for e in self.particles.entries],
            "probe_rows": self.comm.bcast(self.probes.rows, root=0),
            "segment": self.segment,
        }

    def set_schedule(self, sched: dict) -> None:
        """Continue the output schedule of a checkpoint (before the writers are opened)."""
        self.next.update(sched["next"])
        self.next["checkpoint"] = self.solver.t + self.case.output.checkpoint_interval
        self.last.update(sched["last"])
        self._particle_files = sched["particle_files"]
        self._probe_rows = int(sched["probe_rows"])
        self.segment = int(sched["segment"]) + 1

    # ------------------------------------------------------------------------------------------ probes
    def probe_values(self) -> dict[str, float]:
        """Every probe quantity now (collective)."""
        s = self.solver
        P = s.dem.particles
        n = P.n_owned
        vol = solid_volume(P.diameter[:n], 1.0)  # a parcel's volume is that of its sphere
        p = s.gas.p
        sec = {name: f(p) for name, f in self.sections.items()}
        rho_g, g = self.case.gas.density, self.case.run.gravity
        info = s.last_gas
        vals = {
            "step": s.steps,
            "dt": info.dt if info else 0.0,
            "n_sub": s.n_sub,
            "particles": self.comm.allreduce(n),
            "left_outlet": self.comm.allreduce(s.left_outlet),
            "kinetic_energy": self.comm.allreduce(float(P.kinetic_energy())),
            "bed_height": bed_height(P.pos[:n, self.axis], vol, self.case.output.bed_fraction, self.comm),
            "dp_bed": sec["bottom"] - sec["top"] - rho_g * g * self.height,
            "cfl": info.cfl if info else 0.0,
            "poisson_iterations": info.poisson_iterations if info else 0,
            "gas_inflow": rho_g * info.inflow if info else 0.0,
            "gas_mass_imbalance": info.mass_imbalance if info else 0.0,
            "clipped_nodes": s.clipped,
            **s.timers.as_dict(),
        }
        vals.update({f"p_{k}": v for k, v in sec.items()})
        if s.groups is not None:
            tot = s.groups.total
            own = [n, int(P.n_orig[:n].sum()), tot.crushed, tot.merged, tot.crush_deferred + tot.merge_deferred]
            counts = self.comm.allreduce(np.array(own, dtype=np.int64))
            vals.update(
                zip(("groups", "originals", "crushed", "merged", "events_deferred"), counts.tolist(), strict=True)
            )
            vals["event_energy"] = tot.energy_injected  # measured on the whole bed (every rank holds the total)
        return vals

    # ------------------------------------------------------------------------------------------ output
    def output(self, force: bool = False) -> None:
        """Write whatever is due (probes, fields, particles); `force` writes all of them now.

        At each probe time the state (which has just passed the health checks) is kept in memory: a later
        failure writes it as the last good checkpoint. A write that fails raises `OutputFailure` on every rank;
        the kinds written before it count as written.
        """
        s = self.solver
        o = self.case.output
        t0 = time.perf_counter()
        tol = 1e-9 * max(s.last_gas.dt if s.last_gas else 1.0, 1e-12)
        kinds = ("probe", "field", "particle")
        due = {k: (force and self.last[k] != s.t) or s.t >= self.next[k] - tol for k in kinds}
        comm = self.comm

        def written(kind: str) -> None:
            self.last[kind] = s.t
            self.next[kind] = s.t + getattr(o, f"{kind}_interval")

        if due["probe"]:
            guarded_write(comm, self.probes.path, self.probes.write, s.t, self.probe_values())
            written("probe")
        if due["field"]:
            self.alpha.x.array[:] = s.alpha
            guarded_write(comm, self.fields.path, self.fields.write, s.t)
            written("field")
        if due["particle"]:
            guarded_write(comm, self.particles.outdir, self.particles.write, s.t, s.dem.particles)
            written("particle")
            self._log_balance()
            self._log_groups()
        if due["probe"] and not force:
            self.good = rs.capture(self)
        s.timers.output += time.perf_counter() - t0

    def _log_groups(self) -> None:
        """PCPM: groups and crush/merge events since the last particle output (seed 000 Figs 8-9)."""
        if self.solver.groups is None:
            return
        e = self.solver.groups.interval_stats()
        c = self.comm.allreduce(np.array([e.groups, e.crushed, e.children, e.merged], dtype=np.int64))
        energy = e.energy_injected  # already the whole bed's
        self.log.info(
            f"groups: {c[0]} ({c[1]} crushed into {c[2]}, {c[3]} merges since the last output; "
            f"energy injected {energy:.3g} J)"
        )

    def _log_balance(self) -> None:
        if self.comm.size == 1:
            return
        from febed.parallel.exchange import balance_line

        dem = self.solver.dem
        self.log.info(balance_line(self.comm, dem.particles.n_owned, dem.pairs.size))

    # ---------------------------------------------------------------------------------- checkpoints
    def checkpoint(self, state=None) -> Path:
        """Write a checkpoint of the current state (or of `state` = (arrays, meta) from `restart.capture`)."""
        s = self.solver
        t0 = time.perf_counter()
        arrays, meta = state if state is not None else rs.capture(self)
        meta = {**meta, "case": self.case.to_toml()}
        gathered = rs.gather(arrays, meta, self.comm)
        path = checkpoint_or_fail(
            write_checkpoint, self.outdir / FOLDER, gathered, meta, self.case.output.keep_checkpoints,
            self.comm,
        )  # fmt: skip
        self.checkpoint_written = (meta["time"], path)
        if self.comm.size > 1 and state is None:  # go on from the layout a restart would have (febed.restart)
            rs.reload_particles(self, self.comm.bcast(gathered, root=0), meta)
        self._last_checkpoint = time.perf_counter()
        self.next["checkpoint"] = s.t + self.case.output.checkpoint_interval
        self.log.info(f"checkpoint at t = {meta['time']:.6g} s (gas step {meta['step']}): {path}")
        s.timers.output += time.perf_counter() - t0
        return path

    def status(self, state: str, message: str = "", collective: bool = True) -> None:
        """Write `status.json`: state (running / finished / failed / interrupted), time, end time, message.

        See `write_run_status` for `collective`.
        """
        s = self.solver
        write_run_status(self.outdir, state, s.t, self.case.run.end_time, s.steps, message, self.comm, collective)

    # ---------------------------------------------------------------------------------------- loop
    def progress(self, end: float) -> None:
        """Show the progress line (collective under MPI: call it on every rank, `after_step` says when)."""
        now = time.perf_counter()
        self._last_progress = now
        s = self.solver
        n = self.comm.allreduce(s.dem.particles.n_owned)
        self.display.show(
            f"t = {s.t:.5f} / {end:g} s  step {s.steps}  {n} particles  {s.n_sub} sub-steps/step  "
            f"{self._meter.text(s.t, end, now)}"
        )

    def advance_to(self, end: float) -> None:
        """Step until `end` (s), writing output, checkpoints and progress on the way.

        Raises RunFailure (after writing the last good state), OutputFailure, or Interrupted (after a
        checkpoint; a signal that comes during a long gas step stops its DEM sub-steps within a second or so and
        the last good state is written, `stopped_mid_step`).
        """
        s = self.solver
        self.output(force=s.steps == 0)
        if self.good is None:
            self.good = rs.capture(self)
        self.status("running")
        while s.t < end * (1 - 1e-12):
            try:
                s.step()
                s.check()
            except StopRequested:  # on every rank
                raise stopped_mid_step(self, f"the gas step from t = {s.t:.6g} s") from None
            except RunFailure as e:
                self.fail(e)
                raise
            except DEMFailure as e:  # agreed over the ranks, like RunFailure
                err = RunFailure(f"the particles blew up: {e}")
                self.fail(err)
                raise err from None
            except (ValueError, IndexError, ZeroDivisionError, FloatingPointError, MemoryError) as e:
                # a blow-up surfacing inside a kernel or NumPy call (e.g. a negative array size): a failure,
                # not an input error; on several ranks only this rank knows, so no collective checkpoint
                err = RunFailure(f"numerical failure in the gas step from t = {s.t:.6g} s: {type(e).__name__}: {e}")
                self.broken = self.comm.size > 1  # the other ranks wait in a collective: no closing output
                self.fail(err, collective=not self.broken)
                raise err from e
            self.output()
            if after_step(self, s.t, s.t >= self.next["checkpoint"] - 1e-12 * end):
                self.progress(end)
        self.progress(end)
        self.display.end()

    def fail(self, error: RunFailure, collective: bool = True) -> None:
        """Record a failure: write the last good state as a checkpoint (if `collective`) and the status."""
        record_failure(self, error, collective)

    def close(self, last_output: bool = True) -> None:
        """Write the last output (if `last_output`) and close the files; a second call does nothing.

        Nothing is done after a one-rank failure on several ranks (collective calls would hang), and no more
        output is written after an output error. Raises OutputFailure if a write or close fails.
        """
        if self.broken or self._closed:
            return
        self._closed = True
        try:
            if last_output and not self.output_failed:
                self.output(force=True)
        finally:
            close_files(self.comm, self.probes, self.fields)

    # ---------------------------------------------------------------------------------------- signals
    def catch_signals(self):
        """Handle STOP_SIGNALS by stopping after the current gas step; returns a function restoring the handlers."""
        return catch_stop_signals(self, "this gas step", self.solver.dem)


def catch_stop_signals(run, after: str, dem=None):
    """Install STOP_SIGNALS handlers that set `run._signal` (logged to `run.log`: "stopping after `after`").

    A second signal raises `StopNow` (stop at once). With a `dem`, its long sub-step loops ask for the signal
    every fraction of a second (`DEM.stop_check`, agreed over the ranks) and stop early (`StopRequested`).
    Returns a function restoring the previous handlers (and removing the DEM's check); outside the main
    thread (no handlers possible) a no-op.
    """
    import threading

    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def handler(signum, frame):
        if run._signal:  # a second Ctrl-C: stop now
            raise StopNow(signum)
        run._signal = signum
        run.log.warning(f"{signal.Signals(signum).name} received: stopping after {after}")

    def stop_check() -> bool:
        run._signal = agree(run.comm, run._signal)[0]
        return bool(run._signal)

    old = {sig: signal.signal(sig, handler) for sig in STOP_SIGNALS}
    if dem is not None:
        dem.stop_check = stop_check

    def restore() -> None:
        for k, v in old.items():
            signal.signal(k, v)
        if dem is not None:
            dem.stop_check = None

    return restore


def run_coupled(case, outdir, log, comm=MPI.COMM_WORLD, restart=None):
    """Run a coupled case to `run.end_time`, as `febed run` does.

    Args:
        case: a validated `Case` of mode "cfd-dem".
        outdir: its output folder, prepared and locked by `febed.prepare_output`.
        log: the logger to report to.
        comm: the MPI communicator.
        restart: a checkpoint file or run folder to continue from (its newest valid checkpoint).

    Returns:
        The finished `CoupledRun` (its files closed).

    Raises:
        RunFailure: the run could not go on (after writing its last good state and a failed status).
    """
    from febed.io.checkpoint import load_checkpoint

    ckpt = None
    if restart is not None:
        ckpt = load_checkpoint(Path(restart), comm)
        rs.check_restartable(ckpt[2], case)
    run = CoupledRun(case, Path(outdir), log, comm, restart=ckpt)
    s = run.solver
    start = f"restarted from {run.restarted_from} at t = {s.t:.6g} s" if ckpt else "cfd-dem"
    log.info(
        f"{start}: {comm.allreduce(s.dem.particles.n_owned)} particles, {s.ma.num_dofs} nodes, "
        f"drag {case.coupling.drag}, DEM step {s.dem.dt:.3e} s, to t = {case.run.end_time:g} s"
    )
    run_to_end(run, case.run.end_time)
    t = s.timers
    total = t.dem + t.coupling + t.gas + t.output
    left = comm.allreduce(s.left_outlet)  # each rank counts its own (probes.csv has the same total)
    log.info(
        f"done: {s.steps} gas steps to t = {s.t:.5f} s in {total:.1f} s "
        f"(DEM {t.dem:.1f} s, coupling {t.coupling:.1f} s, gas {t.gas:.1f} s, output {t.output:.1f} s); "
        f"{left} particles left through the outlet; probes in {run.outdir / 'probes.csv'}"
    )
    return run
