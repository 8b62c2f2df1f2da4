"""One-way runs (`[run] mode = "one-way"`): the case's particles moved by its prescribed gas (`febed.coarse.oneway`).

`run` builds the particles of the case (walls and bed from its mesh, `febed.bed.build_dem`) and hands them to
`run_oneway`, which advances a `febed.coarse.oneway.OneWay` to the end time and writes the particles' history
(`particles.csv`), a progress line and `status.json`. One process; no checkpoints.
"""

from __future__ import annotations

import io
import signal
import time
from pathlib import Path
from types import SimpleNamespace

from mpi4py import MPI

import numpy as np

from febed.bed import build_dem
from febed.coarse.oneway import OneWay, OneWayCase, case_settings
from febed.dem.solver import DEMFailure, StopRequested
from febed.gas.prescribed import make_prescribed_gas
from febed.io.progress import Progress, RateMeter
from febed.meshing import load_case_mesh
from febed.runs.lifecycle import Interrupted, OutputFailure, catch_stop_signals, guarded_write, write_run_status
from febed.solver import RunFailure


def _first_bad(P) -> int | None:
    """Row of the first owned particle whose position or velocity is not finite, or None."""
    n = P.n_owned
    ok = np.isfinite(P.pos[:n]).all(axis=1) & np.isfinite(P.vel[:n]).all(axis=1)
    return None if ok.all() else int(np.flatnonzero(~ok)[0])


def run_oneway(case: OneWayCase, outdir, log=None, dem=None, sink=None, stop=None) -> OneWay:
    """Run `dem` in the prescribed gas of `case` to its end time, writing outdir/particles.csv (t, gid, x, v).

    The rows of each output time are appended and flushed as they come (a run stopped midway keeps them);
    with `log`, a progress line (simulated time, drag windows, particles, wall time per simulated second,
    ETA) every `progress_interval` wall seconds. A particle whose position or velocity is no longer finite
    stops the run (`febed.solver.RunFailure`, naming the particle and the time); a failed write of the file
    raises `febed.runs.lifecycle.OutputFailure` naming it and the error. `stop`: an object whose `_signal`
    becomes nonzero when the run must stop (`febed.runs.lifecycle.catch_stop_signals`): the run then stops
    after the current drag window (`febed.dem.solver.StopRequested`).
    """
    if dem is None:
        raise ValueError("dem: build the particles (a DEM) first, e.g. `febed.bed.build_dem`")
    gas = make_prescribed_gas(case.flow, case.density, case.viscosity, **case.flow_params)
    ow = OneWay(dem, gas, case.drag, case.integration, case.drag_factor, sink)
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    next_out = [0.0]
    display = Progress(log, 0) if log is not None else None
    t0 = last = time.perf_counter()
    meter = RateMeter(ow.t, now=t0)

    path = out / "particles.csv"

    def rows(text: str) -> None:
        csv.write(text)
        csv.flush()

    csv = guarded_write(None, path, open, path, "w")
    ok = False
    try:
        guarded_write(None, path, rows, "t,gid,x,y,z,vx,vy,vz\n")

        def record(o: OneWay) -> None:
            nonlocal last
            if stop is not None and stop._signal:
                raise StopRequested(f"stopped after {o.windows} drag windows, at t = {o.t:.6g} s")
            P = o.dem.particles
            if o.t + 1e-12 >= next_out[0]:
                bad = _first_bad(P)
                if bad is not None:
                    raise RunFailure(
                        f"particle {int(P.gid[bad])} has a non-finite position or velocity at t = {o.t:.6g} s "
                        f"(drag window {o.windows}); lower [prescribed_gas] window or raise drag_factor"
                    )
                n = P.n_owned
                blk = np.column_stack([np.full(n, o.t), P.gid[:n], P.pos[:n], P.vel[:n]])
                text = io.StringIO()
                np.savetxt(text, blk, delimiter=",")
                guarded_write(None, path, rows, text.getvalue())
                next_out[0] += case.output_interval
            now = time.perf_counter()
            if display is not None and (now - last >= case.progress_interval or o.t >= case.end_time * (1 - 1e-12)):
                last = now
                display.show(
                    f"t = {o.t:.5g} / {case.end_time:g} s  {o.windows} drag windows  {P.n_owned} particles  "
                    f"{o.removed} removed  {meter.text(o.t, case.end_time, now)}"
                )

        record(ow)
        ow.advance(case.end_time, case.window if case.window > 0 else None, record)
        ok = True
    finally:
        if display is not None:
            display.end()
        if ok:
            guarded_write(None, path, csv.close)
        else:  # stopping on another error: a failed close must not hide it
            try:
                csv.close()
            except OSError:
                pass
    wall = time.perf_counter() - t0
    if log is not None:
        log.info(f"one-way run: {ow.windows} drag windows to t = {ow.t:.6g} s in {wall:.3g} s; removed {ow.removed}")
    return ow


def run(case, outdir, log, comm=None) -> OneWay:
    """`[run] mode = "one-way"`: the case's particles (walls and bed from its mesh) in its prescribed gas.

    Particles whose centre leaves the mesh's bounding box (an open outlet) are removed and counted.
    Writes outdir/particles.csv (t, gid, x, v every `output_interval`) and keeps `status.json` (running,
    finished, failed with the message); shows progress like the other modes. One process; no checkpoints
    (one-way runs are short: they are re-run rather than restarted). SIGINT/SIGTERM/SIGUSR1 stop it after the
    current drag window (its DEM sub-steps stop within a second or so) with status failed and
    `febed.runs.lifecycle.Interrupted`; an output error (`febed.runs.lifecycle.OutputFailure`) stops it with
    status failed.
    """
    comm = comm or MPI.COMM_WORLD
    if comm.size > 1:
        raise ValueError("[run] mode = 'one-way' runs on one process: start it without mpirun")
    settings = case_settings(case)
    md = load_case_mesh(case, comm, cache_dir=Path(outdir) / "mesh")
    dem = build_dem(case, md, log)
    x = md.mesh.geometry.x
    lo, hi = x.min(axis=0) - 1e-9, x.max(axis=0) + 1e-9

    def outside(pos, diameter):
        return np.any((pos < lo) | (pos > hi), axis=1)

    log.info(f"one-way: {dem.particles.n_owned} particles in a prescribed {settings.flow} gas, drag {settings.drag}")
    end = settings.end_time
    again = "a one-way run does not restart: run it again with --overwrite"

    def failed(message: str) -> None:  # not "interrupted": a one-way run has no checkpoint to continue from
        write_run_status(outdir, "failed", dem.time, end, dem.steps, message, comm, collective=False)

    stop = SimpleNamespace(_signal=0, log=log, comm=comm)
    restore_signals = catch_stop_signals(stop, "this drag window", dem)
    try:
        write_run_status(outdir, "running", 0.0, end, 0, comm=comm)
        ow = run_oneway(settings, outdir, log, dem=dem, sink=outside, stop=stop)
        write_run_status(outdir, "finished", ow.t, end, ow.windows, comm=comm)
    except (RunFailure, DEMFailure) as e:  # DEMFailure: found by the DEM itself at a pair-list rebuild
        msg = f"{e}; {again}" if isinstance(e, OutputFailure) else str(e)
        e.args = (msg,)
        failed(msg)
        log.error(f"run failed: {msg}")
        raise
    except (StopRequested, KeyboardInterrupt) as e:  # a stop signal (a second one, or Ctrl-C, at once)
        sig = getattr(e, "signum", 0) or stop._signal or signal.SIGINT
        msg = f"stopped by {signal.Signals(sig).name} at t = {dem.time:.6g} s; {again}"
        failed(msg)
        log.warning(msg)
        raise Interrupted(sig, msg) from None
    finally:
        restore_signals()
    return ow
