"""One-way runs (`[run] mode = "one-way"`): the case's particles moved by its prescribed gas (`febed.coarse.oneway`).

`run` builds the particles of the case (walls and bed from its mesh, `febed.bed.build_dem`) and runs them as a
`OneWayRun`: a `febed.coarse.oneway.OneWay` advanced in drag windows, writing the particles' history
(`particles.csv`). Like a pure-DEM run (`febed.runs.dem`), it writes checkpoints (every `[output]
checkpoint_interval` simulated or `checkpoint_wall_interval` wall seconds, on SIGINT/SIGTERM/SIGUSR1, at the end,
and the last good state when a particle's position or velocity is no longer finite), continues from one with
`febed run CASE --restart`, shows a progress line and keeps `status.json` up to date (`febed.runs.lifecycle`).
One process.

`run_oneway` drives a `OneWay` over a DEM built by a script (no mesh, no case file): it writes the same
`particles.csv`, without checkpoints or `status.json`.
"""

from __future__ import annotations

import io
import os
import time
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed.bed import build_dem, dem_from_case, walls_from_mesh
from febed.coarse.oneway import OneWay, OneWayCase, case_settings
from febed.dem.particles import Particles
from febed.dem.solver import DEMFailure, StopRequested
from febed.gas.prescribed import make_prescribed_gas
from febed.io.atomic import sync_close
from febed.io.checkpoint import CheckpointError
from febed.io.progress import Progress, RateMeter
from febed.io.state import dem_arrays, load_dem
from febed.meshing import load_case_mesh
from febed.runs.lifecycle import (
    RunMode,
    after_step,
    catch_stop_signals,
    guarded_write,
    load_restart,
    run_to_end,
    stopped_mid_step,
)
from febed.solver import RunFailure

HEADER = "t,gid,x,y,z,vx,vy,vz\n"
_TOL = 1e-12  # relative: a time within this of an output, checkpoint or end time has reached it


class ParticleRows:
    """`particles.csv`: a header, then at each output time one row per particle (t, gid, x, y, z, vx, vy, vz).

    The rows of an output time are written and flushed at once, and `size` is the file's length in bytes after
    the last complete output: a checkpoint records it. `ParticleRows(path, keep=size)` continues the file of
    such a checkpoint: it cuts off what lies beyond `size` (the rows of later output times, or the partial rows
    of a write that failed or of a run killed while writing) and appends after it. A file that does not start
    with the header or is shorter than `keep` is refused (CheckpointError).
    """

    def __init__(self, path, keep: int | None = None):
        """Open `path` anew (with its header) or, with `keep`, cut it to `keep` bytes and append."""
        self.path = Path(path)
        self._f = None
        if keep is None:
            self._f = open(self.path, "w")  # `open` by name: tests put a full disk under it
            self.size = 0
            self.write(HEADER)
        else:
            self._cut(int(keep))
            self._f = open(self.path, "a")
            self.size = int(keep)

    def _cut(self, keep: int) -> None:
        again = "start the run again with --overwrite"
        if not self.path.is_file():
            raise CheckpointError(f"{self.path} is missing: the checkpoint continues its rows; {again}")
        size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            head = f.read(len(HEADER))
            f.seek(max(keep - 1, 0))
            last = f.read(1)
        if head != HEADER.encode() or size < keep or last != b"\n":
            raise CheckpointError(
                f"{self.path} is not the file the checkpoint was written with (at the checkpoint it held {keep} "
                f"bytes of whole rows, now {size}): it was changed since; {again}"
            )
        os.truncate(self.path, keep)

    def write(self, text: str) -> None:
        """Append `text` (whole rows) and flush it; `size` counts it once it is written."""
        self._f.write(text)
        self._f.flush()
        self.size += len(text.encode())

    def sync(self) -> None:
        """Flush the rows written so far to the disk (before a checkpoint that records `size`)."""
        if self._f is not None:
            os.fsync(self._f.fileno())

    def close(self) -> None:
        """Flush to the disk and close; a second call does nothing, even after a failed close (OSError)."""
        f, self._f = self._f, None
        if f is not None:
            sync_close(f)


def _rows_text(ow: OneWay) -> str:
    """The CSV rows (t, gid, x, v) of the particles of `ow` now."""
    P = ow.dem.particles
    n = P.n_owned
    text = io.StringIO()
    np.savetxt(text, np.column_stack([np.full(n, ow.t), P.gid[:n], P.pos[:n], P.vel[:n]]), delimiter=",")
    return text.getvalue()


def _non_finite(ow: OneWay) -> str | None:
    """The message naming the first particle whose position or velocity is not finite (and the time), or None."""
    P = ow.dem.particles
    n = P.n_owned
    ok = np.isfinite(P.pos[:n]).all(axis=1) & np.isfinite(P.vel[:n]).all(axis=1)
    if ok.all():
        return None
    bad = int(np.flatnonzero(~ok)[0])
    return (
        f"particle {int(P.gid[bad])} has a non-finite position or velocity at t = {ow.t:.6g} s (drag window "
        f"{ow.windows}); check the prescribed gas there, or lower [prescribed_gas] window or raise drag_factor"
    )


def _reached(t: float, target: float) -> bool:
    """Whether time `t` has reached `target` (within a relative 1e-12: sums of windows round)."""
    return t >= target - _TOL * max(1.0, abs(target))


def _window_end(end: float, next_out: float) -> float:
    """Where the next drag window ends at the latest: the next output time, or `end` if it comes first.

    Windows end exactly at the output times, so a run stopped at an output time (its end time) and continued
    makes the same windows as the run left alone. An end within round-off of an output time is that time.
    """
    return next_out if next_out <= end or _reached(end, next_out) else end


def _progress_text(ow: OneWay, end: float) -> str:
    """'t = ... / end s  N drag windows  P particles  R removed'."""
    n = ow.dem.particles.n_owned
    return f"t = {ow.t:.5g} / {end:g} s  {ow.windows} drag windows  {n} particles  {ow.removed} removed"


def run_oneway(case: OneWayCase, outdir, log=None, dem=None, sink=None) -> OneWay:
    """Run `dem` in the prescribed gas of `case` to its end time, writing outdir/particles.csv (t, gid, x, v).

    For a DEM built by a script; a case file's one-way run is a `OneWayRun` (checkpoints, restart, status).
    The rows of each output time are appended and flushed as they come (a run stopped midway keeps them); with
    `log`, a progress line (simulated time, drag windows, particles, wall time per simulated second, ETA) every
    `progress_interval` wall seconds. A particle whose position or velocity is no longer finite stops the run
    (`febed.solver.RunFailure`, naming the particle and the time); a failed write of the file raises
    `febed.runs.lifecycle.OutputFailure` naming it and the error. `sink(pos, diameter) -> bool mask`: particles
    to remove after each drag window.
    """
    if dem is None:
        raise ValueError("dem: build the particles (a DEM) first, e.g. `febed.bed.build_dem`")
    gas = make_prescribed_gas(case.flow, case.density, case.viscosity, **case.flow_params)
    ow = OneWay(dem, gas, case.drag, case.integration, case.drag_factor, sink)
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "particles.csv"
    rows = guarded_write(None, path, ParticleRows, path)
    display = Progress(log, 0) if log is not None else None
    t0 = last = time.perf_counter()
    meter = RateMeter(ow.t, now=t0)
    h = case.window if case.window > 0 else None
    next_out, ok = 0.0, False
    try:
        while True:
            bad = _non_finite(ow)
            if bad:
                raise RunFailure(bad)
            if _reached(ow.t, next_out):
                guarded_write(None, path, rows.write, _rows_text(ow))
                next_out += case.output_interval
            done = ow.t >= case.end_time * (1 - _TOL)
            now = time.perf_counter()
            if display is not None and (done or now - last >= case.progress_interval):
                last = now
                display.show(f"{_progress_text(ow, case.end_time)}  {meter.text(ow.t, case.end_time, now)}")
            if done:
                break
            ow.step(ow.window(_window_end(case.end_time, next_out), h))
        ok = True
    finally:
        if display is not None:
            display.end()
        if ok:
            guarded_write(None, path, rows.close)
        else:  # stopping on another error: a failed close must not hide it
            try:
                rows.close()
            except OSError:
                pass
    if log is not None:
        wall = time.perf_counter() - t0
        log.info(f"one-way run: {ow.windows} drag windows to t = {ow.t:.6g} s in {wall:.3g} s; removed {ow.removed}")
    return ow


class OneWayRun(RunMode):
    """A one-way run with its output: `advance_to(t)` moves the particles, writing rows and checkpoints.

    Its state is the DEM's (`febed.io.state.dem_arrays`) and the driver's (`OneWay.get_state`: time, drag
    windows, particles removed), with the next output time and the length of `particles.csv` at the last
    complete output (`meta["run"]`). Drag windows end at the output times, never at a checkpoint: checkpoints
    are written at the end of the window that reaches `[output] checkpoint_interval`, or
    `checkpoint_wall_interval` wall seconds, or a stop signal, so that they never change the run. A restart on
    one process continues bit for bit. The state at each output is kept in memory: a particle no longer finite
    (`febed.solver.RunFailure`), a blow-up found by the DEM (`DEMFailure`) or a stop signal in the middle of a
    long window (many DEM sub-steps, stopped within a second) writes it as the last good checkpoint. Particles
    whose centre leaves the mesh's bounding box (an open outlet) are removed and counted.
    """

    STEP = "drag window"

    def __init__(self, case, outdir: Path, log, comm=MPI.COMM_WORLD, restart=None):
        """Build the mesh, walls and particles; `restart`: (path, arrays, meta) of a checkpoint to continue."""
        if comm.size > 1:
            raise ValueError("[run] mode = 'one-way' runs on one process: start it without mpirun")
        self.case, self.outdir, self.log, self.comm = case, Path(outdir), log, comm
        self.settings = s = case_settings(case)
        md = load_case_mesh(case, comm, cache_dir=self.outdir / "mesh")
        x = md.mesh.geometry.x
        self.lo, self.hi = x.min(axis=0) - 1e-9, x.max(axis=0) + 1e-9
        self.restarted_from = None
        if restart is None:
            self.dem = build_dem(case, md, log)
        else:
            path, arrays, meta = restart
            self.dem = dem_from_case(case, walls_from_mesh(case, md), md.gdim, Particles())
            load_dem(self.dem, arrays, meta, comm.size)
        gas = make_prescribed_gas(s.flow, s.density, s.viscosity, **s.flow_params)
        self.ow = OneWay(self.dem, gas, s.drag, s.integration, s.drag_factor, self._outside)
        keep = None
        self.next_out = 0.0
        if restart is not None:
            sched = meta["run"]
            self.ow.set_state(sched)
            self.next_out = float(sched["next_out"])
            keep = int(sched["csv_bytes"])
            self.restarted_from = path
        self.next_ckpt = self.ow.t + case.output.checkpoint_interval
        csv = self.outdir / "particles.csv"
        self.rows = guarded_write(comm, csv, ParticleRows, csv, keep)
        self._start_lifecycle(self.ow.t)

    def _outside(self, pos, diameter):
        return np.any((pos < self.lo) | (pos > self.hi), axis=1)

    # ------------------------------------------------------------------------------------ state
    def capture(self) -> tuple[dict, dict]:
        """The state (copies) and the JSON-able meta record of a checkpoint."""
        ow = self.ow
        meta = {
            "time": ow.t,
            "step": ow.windows,
            "ranks": self.comm.size,
            "mode": "one-way",
            "run": {
                **ow.get_state(),
                "next_out": self.next_out,
                "csv_bytes": self.rows.size,
                "left": ow.removed,  # the particles that left the domain (`febed.io.checkpoint.identity`)
            },
        }
        return dem_arrays(self.dem), meta

    def sim_time(self) -> float:
        """The one-way driver's simulated time (s)."""
        return self.ow.t

    def steps_done(self) -> int:
        """Drag windows made."""
        return self.ow.windows

    def checkpoint(self, state=None) -> Path:
        """Write a checkpoint (`RunMode.checkpoint`), the rows it counts flushed to the disk first."""
        guarded_write(self.comm, self.rows.path, self.rows.sync)
        return super().checkpoint(state)

    def _checkpointed(self, gathered, meta: dict, state) -> None:
        self.next_ckpt = self.ow.t + self.case.output.checkpoint_interval

    def output(self) -> None:
        """Write the particles' rows, move the next output time on, keep the state as the last good one.

        A failed write raises `OutputFailure` (and leaves the schedule as it was).
        """
        guarded_write(self.comm, self.rows.path, self.rows.write, _rows_text(self.ow))
        self.next_out += self.settings.output_interval
        self.good = self.capture()

    def check(self) -> None:
        """Raise RunFailure, after recording it, if a particle's position or velocity is no longer finite."""
        bad = _non_finite(self.ow)
        if bad:
            self.fail(bad)
            raise RunFailure(bad)

    def advance_to(self, end: float) -> None:
        """Move the particles to `end` (s) in drag windows, writing rows, checkpoints and progress.

        Raises RunFailure or DEMFailure (after writing the last good state), `febed.runs.lifecycle.OutputFailure`
        or `febed.runs.lifecycle.Interrupted` (after a checkpoint).
        """
        ow = self.ow
        if self.good is None:
            self.check()
            # the first output, or one due because the run before stopped on an output error
            if self.restarted_from is None or _reached(ow.t, self.next_out):
                self.output()
            else:
                self.good = self.capture()
        self.status("running")
        h = self.settings.window if self.settings.window > 0 else None
        while ow.t < end * (1 - _TOL):
            try:
                ow.step(ow.window(_window_end(end, self.next_out), h))
            except DEMFailure as e:
                self.fail(f"the particles blew up: {e}")
                raise
            except StopRequested:  # a signal in the middle of a long window: continue from the last good state
                raise stopped_mid_step(self, f"the drag window from t = {ow.t:.6g} s") from None
            self.check()
            if _reached(ow.t, self.next_out):
                self.output()
            if after_step(self, ow.t, _reached(ow.t, self.next_ckpt)):
                self.progress(end)
        self.progress(end)
        self.display.end()

    def progress_text(self, end: float, now: float) -> str:
        """Simulated time, drag windows, particles, particles removed."""
        return _progress_text(self.ow, end)

    def close(self, last_output: bool = True) -> None:
        """Close `particles.csv` (its rows are on the disk already)."""
        guarded_write(self.comm, self.rows.path, self.rows.close)

    def catch_signals(self):
        """Handle the stop signals: stop after this drag window, within a second in a long one; the restorer."""
        return catch_stop_signals(self, "this drag window", self.dem)


def run(case, outdir, log, comm=None, restart=None) -> OneWay:
    """`[run] mode = "one-way"`: the case's particles (walls and bed from its mesh) in its prescribed gas.

    Runs a `OneWayRun` to `run.end_time` (called by `febed run`); returns its `OneWay`. Writes
    outdir/particles.csv (t, gid, x, v every `[prescribed_gas] output_interval`), checkpoints and status.json.
    `restart`: a checkpoint file or run folder to continue from (its newest valid checkpoint). One process.
    """
    comm = comm or MPI.COMM_WORLD
    if comm.size > 1:
        raise ValueError("[run] mode = 'one-way' runs on one process: start it without mpirun")
    ckpt = load_restart(restart, case, comm)
    r = OneWayRun(case, outdir, log, comm, restart=ckpt)
    ow, s = r.ow, r.settings
    start = f"restarted from {r.restarted_from} at t = {ow.t:.6g} s" if ckpt else "one-way"
    end = case.run.end_time
    log.info(f"{start}: {r.dem.particles.n_owned} particles in a prescribed {s.flow} gas, drag {s.drag}, "
             f"to t = {end:g} s")  # fmt: skip
    t0 = time.perf_counter()
    run_to_end(r, end)
    wall = time.perf_counter() - t0
    log.info(f"one-way run: {ow.windows} drag windows to t = {ow.t:.6g} s in {wall:.3g} s; removed {ow.removed}")
    return ow
