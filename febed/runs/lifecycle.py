"""The life of a run of any mode (coupled, pure DEM, gas only, one-way): stopping, failing, its output errors.

Every run mode steps its own solver; what happens between and around the steps is the same and lives here:

* `run_to_end` advances a run to its end time with the stop signals caught (`catch_stop_signals`), then writes
  the final checkpoint and status; `after_step` ends each step: the ranks agree on a stop signal and on the
  wall-clock triggers (`agree`: rank 0's clock), a checkpoint is written when due, and after a signal the
  run stops with `Interrupted`.
* SIGINT/SIGTERM/SIGUSR1 (Ctrl-C, a batch system's time limit) finish the current step, write a checkpoint
  and stop; ranks agree on the step at which they stop. A step whose DEM sub-steps would take long is not
  waited for: the sub-steps ask for the signal every fraction of a second (`febed.dem.solver.DEM.stop_check`,
  agreed over the ranks) and the run stops with the last good state as its checkpoint (`stopped_mid_step`).
  A second signal stops at once (`StopNow`), naming the newest checkpoint there is. Under Open MPI's mpirun,
  SIGUSR1 is the one to send: mpirun forwards it to the ranks as it is, whereas on SIGTERM or SIGINT it kills
  them after a short grace that a step on a loaded machine can outlast.
* A failure of the simulation (`febed.solver.RunFailure`; the DEM's `DEMFailure`) is what the health checks
  found (a non-finite value, a particle lost, an overlap or a void fraction beyond its limit, a pressure solve
  that diverged). It is recorded by `record_failure`: the last state that passed the checks (`run.good`) is
  written as a checkpoint, status.json says "failed" with the message, and `febed run` exits non-zero.
* Any other exception raised while a run steps is a bug in febed, not a failure of the simulation:
  `run_to_end` records it by `record_internal_error` (the traceback in the log, the last good state as a
  checkpoint on one process, status.json "failed" with a message saying it is an internal error) and raises
  `InternalError`. On several ranks the rank that met it writes the status and log itself, and `febed run`
  ends the whole job (`alone`), since the other ranks may wait for it in a collective call.
* An output error (a full disk, permissions, an I/O error) while writing probes, fields, particles, a
  checkpoint or status.json stops the run on every rank (`guarded_write`, `OutputFailure`): the current
  state is written as a checkpoint if the disk takes it (the older ones are removed only after a newer one is
  complete), status.json says "failed" with the file and the error and where the newest checkpoint is, and
  `febed run` exits with status 3 (`record_output_failure`).
* `record_exit` records an error or signal that ended `febed run` before its run recorded anything.

A run object given to these functions has `comm`, `case`, `outdir`, `log`, `display` (`febed.io.progress.Progress`),
`good`, `_signal`, `_last_checkpoint`, `_last_progress`, `checkpoint_written`, `output_failed` and the methods
`advance_to(end)`, `checkpoint(state=None)`, `status(state, message, collective, alone)`, `catch_signals()` and
`close(last_output)` (collective).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed import restart as rs
from febed.dem.solver import DEMFailure
from febed.io.checkpoint import (
    FOLDER,
    CheckpointError,
    list_checkpoints,
    load_checkpoint,
    read_meta,
    write_checkpoint,
)
from febed.io.progress import Progress, RateMeter
from febed.io.rundir import LOG_FILE, STATUS_FILE, log_file_on_this_rank, write_status
from febed.io.state import gather as gather_state
from febed.solver import RunFailure

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1)  # finish the step, checkpoint, stop


class Interrupted(Exception):
    """The run stopped on a signal after writing a checkpoint; `signum` is the signal.

    `alone`: this rank stopped without the others (see `InternalError`).
    """

    def __init__(self, signum: int, message: str, alone: bool = False):
        super().__init__(message)
        self.signum = signum
        self.alone = alone


class StopNow(KeyboardInterrupt):
    """A stop signal that cannot wait for the end of a step: during start-up, or a second one; `signum` is it."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class InternalError(RuntimeError):
    """A run stopped on an unexpected exception: a bug in febed, not a failure of the simulation.

    The message names the exception and where the last good state is; the traceback is in the run's log.
    `alone`: raised on one rank of several, whose others may be waiting in a collective call; `febed run` then
    ends the whole job (`febed.cli`), since a process cannot even exit normally while the others wait.
    """

    def __init__(self, message: str, alone: bool = False):
        super().__init__(message)
        self.alone = alone


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


class RunMode:
    """What every run mode (coupled, DEM, gas, one-way) does the same way: checkpoints, progress, failures, status.

    A mode sets `case`, `outdir`, `log`, `comm`, `display` (`febed.io.progress.Progress`) and `_meter`
    (`febed.io.progress.RateMeter`), and gives `capture()` -> (arrays, meta) of its state (the `febed.restart`
    format), `sim_time()` (s) and `steps_done()` at its own clock, `STEP` (what a step is called in the log),
    `progress_text(end, now)` (its part of the progress line) and `_checkpointed(gathered, meta, state)` for what
    it does after a checkpoint is written.
    """

    STEP = "step"

    def _start_lifecycle(self, t: float) -> None:
        """The lifecycle's own state for a run starting or continuing at simulated time t (s)."""
        self.display = Progress(self.log, self.comm.rank)
        self.good = None  # (arrays, meta) of the last state that passed the checks
        self.output_failed = False  # an output error stopped the run: nothing more is written
        self.checkpoint_written = None  # (time, path) of the newest checkpoint this run wrote
        self._signal = 0
        self._last_progress = self._last_checkpoint = time.perf_counter()
        self._meter = RateMeter(t)

    def sim_time(self) -> float:
        """The simulated time (s) of the mode's clock."""
        raise NotImplementedError

    def steps_done(self) -> int:
        """The steps of the mode's clock done so far."""
        raise NotImplementedError

    def capture(self) -> tuple[dict, dict]:
        """(arrays, meta) of the current state, as `febed.restart` stores them."""
        raise NotImplementedError

    def _checkpointed(self, gathered, meta: dict, state) -> None:
        """After a checkpoint of `meta` is written (collective): e.g. the time of the next one."""

    def checkpoint(self, state=None) -> Path:
        """Write a checkpoint of the current state, or of `state` = (arrays, meta) from `capture` (collective)."""
        arrays, meta = state if state is not None else self.capture()
        meta = {**meta, "case": self.case.to_toml()}
        gathered = gather_state(arrays, meta, self.comm)
        path = checkpoint_or_fail(
            write_checkpoint, self.outdir / FOLDER, gathered, meta, self.case.output.keep_checkpoints, self.comm
        )
        self.checkpoint_written = (meta["time"], path)
        self._checkpointed(gathered, meta, state)
        self._last_checkpoint = time.perf_counter()
        self.log.info(f"checkpoint at t = {meta['time']:.6g} s ({self.STEP} {meta['step']}): {path}")
        return path

    def progress_text(self, end: float, now: float) -> str:
        """The progress line up to the wall-time rate: simulated time / `end` (s) and the mode's counts."""
        raise NotImplementedError

    def progress(self, end: float) -> None:
        """Show the progress line: `progress_text`, wall time per simulated second and ETA.

        Collective under MPI when the mode's counts are (call it on every rank; `after_step` says when).
        """
        now = time.perf_counter()
        self._last_progress = now
        self.display.show(f"{self.progress_text(end, now)}  {self._meter.text(self.sim_time(), end, now)}")

    def fail(self, error, collective: bool = True) -> None:
        """Record a failure: the last good state as a checkpoint (if `collective`) and the status (`record_failure`)."""
        record_failure(self, error, collective)

    def status(self, state: str, message: str = "", collective: bool = True, alone: bool = False) -> None:
        """Write `status.json` (running / finished / failed / interrupted) at the mode's clock (`write_run_status`).

        `alone`: this rank stopped without the others and writes the file itself (not collective).
        """
        write_run_status(
            self.outdir, state, self.sim_time(), self.case.run.end_time, self.steps_done(), message,
            MPI.COMM_SELF if alone else self.comm, collective and not alone,
        )  # fmt: skip


def load_restart(restart, case, comm):
    """(path, arrays, meta) of the checkpoint `restart`, or None without one (collective).

    `restart`: a checkpoint file, or a run folder (its newest valid checkpoint). A checkpoint that cannot continue
    `case` is refused (`febed.restart.check_restartable`).
    """
    if restart is None:
        return None
    ckpt = load_checkpoint(Path(restart), comm)
    rs.check_restartable(ckpt[2], case)
    return ckpt


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
    for path in reversed(list_checkpoints(Path(outdir) / FOLDER)):
        try:
            t = read_meta(path)["time"]
        except (CheckpointError, KeyError):
            continue
        return f"the newest checkpoint is {path} (t = {t:.6g} s)"
    return "there is no checkpoint"


# ------------------------------------------------------------------------------------ the end of a run
def after_step(run, t: float, checkpoint_due: bool) -> bool:
    """The end of a step of any run (coupled, pure DEM, gas only, one-way): returns whether a progress line is due.

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
    """Advance `run` (coupled, pure DEM, gas only or one-way) to `end`, then write the final checkpoint and status.

    The stop signals are caught meanwhile (`catch_signals`). However the run ends, its files are closed and
    the handlers restored; an error closing them after another error is logged and does not hide the first.
    An output error (`OutputFailure`) is recorded by `record_output_failure`; a second stop signal
    (`StopNow`) stops at once and becomes `Interrupted` (collective). Any exception other than a failure of
    the simulation (`RunFailure`, `DEMFailure`) or a stop (`Interrupted`) is a bug: it is recorded by
    `record_internal_error` and raised as `InternalError`.
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
    except Exception as e:
        last_output = False
        if isinstance(e, (RunFailure, DEMFailure, Interrupted, InternalError)):
            raise
        signal_stop = interrupt_behind(e)
        if signal_stop is not None:  # a second signal raised inside an extension's callback, which wrapped it
            raise stopped_at_once(run, signal_stop) from None
        raise record_internal_error(run, e) from e
    finally:
        try:
            if not closed:
                close_after_error(run, last_output and not getattr(run, "mid_step", False))
        finally:
            restore_signals()


def interrupt_behind(error: BaseException) -> KeyboardInterrupt | None:
    """The stop signal (`KeyboardInterrupt`, e.g. `StopNow`) that caused `error`, if one is among its causes.

    A signal handler that raises while an extension runs Python code (Numba loading a cached kernel, say)
    has its exception wrapped: the extension reports a SystemError whose cause is the interrupt. Only
    explicit causes count: an error met while handling an interrupt (its context) is an error.
    """
    seen = set()
    e = error
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return e
        seen.add(id(e))
        e = e.__cause__
    return None


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
    alone = not collective and run.comm.size > 1  # found by this rank only: it writes the status and log itself
    if alone:
        log_file_on_this_rank(run.log, run.outdir, run.comm)
    run.status("failed", f"{error}{where}", collective=False, alone=alone)
    run.log.error(f"run failed: {error}{where}")


def record_internal_error(run, error: Exception, where: str = "") -> InternalError:
    """Record a run stopped by an unexpected exception (a bug in febed); returns the `InternalError` to raise.

    Logs the error with its traceback, writes the last good state as a checkpoint when the run is on one
    process (on several, the other ranks may be waiting in a collective call: nothing collective is done and
    `run.broken` is set) and sets the status to failed with a message saying it is an internal error, not a
    failure of the simulation. `where`: when it happened ("in the gas step from t = ... s").
    """
    run.display.end()
    if run.comm.size > 1:
        run.broken = True
        log_file_on_this_rank(run.log, run.outdir, run.comm)  # rank 0 may be waiting for this one
    saved = ""
    if run.good is not None and not getattr(run, "broken", False):
        try:
            saved = f"; {write_good_state(run)}"
        except Exception as e:  # the same bug, maybe: the error to report is the first one
            saved = f"; could not write the last good state: {type(e).__name__}: {e}"
    what = f"{type(error).__name__}: {error}" if str(error) else type(error).__name__
    message = (
        f"internal error{' ' + where if where else ''}: {what} (a bug in febed, not a failure of the simulation: "
        f"please report it with the traceback from {Path(run.outdir) / LOG_FILE}){saved}"
    )
    run.status("failed", message, collective=False, alone=run.comm.size > 1)
    run.log.error(f"run failed: {message}", exc_info=error)
    return InternalError(message, alone=run.comm.size > 1)


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
    return Interrupted(sig, message, alone=run.comm.size > 1)


def record_exit(outdir, log, error: BaseException, end: float, t: float = 0.0, step: int = 0,
                restart: bool = False, alone: bool = False) -> None:  # fmt: skip
    """Record in status.json and the log an error that ended `febed run` before its run recorded anything.

    Errors met during start-up (building the mesh, the bed, the solver; opening the output files) or a stop
    signal then (a KeyboardInterrupt: Ctrl-C, or another stop signal carrying `signum`) would otherwise leave
    no status.json (`febed status`: "unknown") and nothing in febed.log. Nothing is done if the run already
    recorded how it ended (rank 0 writes; with `alone`, an error possibly met by this rank only, this rank).
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
        if alone:
            log_file_on_this_rank(log, outdir)
        log.error(f"run failed: {message}")
    write_run_status(outdir, state, t, end, step, message, MPI.COMM_SELF if alone else MPI.COMM_WORLD, False)


def catch_stop_signals(run, after: str, dem=None):
    """Install STOP_SIGNALS handlers that set `run._signal` (logged to `run.log`: "stopping after `after`").

    A second signal raises `StopNow` (stop at once). With a `dem`, its long sub-step loops ask for the signal
    every fraction of a second (`DEM.stop_check`, agreed over the ranks) and stop early (`StopRequested`).
    Returns a function restoring the previous handlers (and removing the DEM's check); outside the main
    thread (no handlers possible) a no-op.
    """
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
