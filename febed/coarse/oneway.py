r"""One-way driver: DEM particles moved by a prescribed gas (seed 003 sec 2: the particles do not act on the gas).

Each drag window of length h, the drag is evaluated once from the gas velocity at the particles,
K_p = n_orig law(1, |u - v|, d_orig) (`febed.coupling.drag`), then the DEM advances ⌈h / Δt_DEM⌉ sub-steps with
that force held fixed (contacts, walls and gravity are the DEM's).

Drag integration (`integration`):
* ``exponential`` (default): the force held over the window is K (u - v) φ(h/τ_p), φ(x) = (1 - e^{-x})/x,
  τ_p = m_p/K_p, so that the velocity change over the window is the exact (u - v)(1 - e^{-h/τ_p}) of a frozen
  gas velocity and drag coefficient: stable for any h, exact for linear drag in a uniform flow.
* ``explicit``: F = K (u - v) (forward Euler in the drag); needs h ≪ τ_p.

The default window is h = min(τ_p,min / 20, dt) (`drag_factor`).
"""

from __future__ import annotations

import io
import math
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from febed.coupling.drag import drag_forces, get_drag_law
from febed.gas.prescribed import PrescribedGas, make_prescribed_gas

INTEGRATIONS = ("exponential", "explicit")


class OneWay:
    """A DEM in a prescribed gas: `advance(t_end)` moves the particles; `callback(self)` runs after each window."""

    def __init__(self, dem, gas: PrescribedGas, drag: str = "stokes", integration: str = "exponential",
                 drag_factor: float = 20.0, sink: Callable | None = None):  # fmt: skip
        """Couple `dem` to `gas` with a registered drag law; `sink(pos, diameter) -> bool mask` removes particles."""
        if integration not in INTEGRATIONS:
            raise ValueError(f"integration: must be one of {INTEGRATIONS}, got {integration!r}")
        if not drag_factor > 0:
            raise ValueError(f"drag_factor: must be > 0, got {drag_factor}")
        self.dem = dem
        self.gas = gas
        self.law = get_drag_law(drag)
        self.integration = integration
        self.drag_factor = float(drag_factor)
        self.sink = sink
        self.t = 0.0
        self.removed = 0
        self.windows = 0

    def _drag(self, h: float) -> tuple[np.ndarray, np.ndarray]:
        """Drag force (N, (n, 3)) held over a window of h (s), and the particles' relaxation times τ_p (s)."""
        P = self.dem.particles
        n = P.n_owned
        x = P.pos[:n]
        v = P.vel[:n]
        n_orig = P.n_orig[:n]
        d_orig = P.diameter[:n] if n_orig.max(initial=1) == 1 else P.diameter[:n] / np.cbrt(n_orig.astype(float))
        u = self.gas.velocity(x, self.t)
        K, F = drag_forces(self.law, np.ones(n), u, v, d_orig, n_orig, self.gas.density, self.gas.viscosity)
        tau = P.mass[:n] / np.maximum(K, 1e-300)
        if self.integration == "exponential":
            r = h / tau
            phi = np.where(r > 1e-12, -np.expm1(-r) / np.where(r > 1e-12, r, 1.0), 1.0)
            F *= phi[:, None]
        return F, tau

    def relaxation_time(self) -> float:
        """Smallest particle relaxation time m_p/K_p (s) at the current slip."""
        n = self.dem.particles.n_owned
        return float(self._drag(0.0)[1].min()) if n else math.inf

    def step(self, h: float) -> None:
        """One drag window of h (s): drag evaluated now, then DEM sub-steps of at most the DEM's dt."""
        dem = self.dem
        if dem.particles.n_owned:
            n_sub = max(1, math.ceil(h / dem.dt * (1.0 - 1e-12)))
            f, _ = self._drag(h)
            dem.advance(n_sub, h / n_sub, f)
        else:
            dem.advance(1, h)  # nothing to move: the clock advances
        self.t += h
        self.windows += 1
        if self.sink is not None and dem.particles.n_owned:
            P = dem.particles
            gone = np.asarray(self.sink(P.pos[: P.n_owned], P.diameter[: P.n_owned]), dtype=bool)
            if gone.any():
                self.removed += int(gone.sum())
                dem.remove_particles(gone)

    def advance(self, t_end: float, h: float | None = None, callback: Callable | None = None) -> None:
        """Advance to time t_end (s) in drag windows of h (default min(τ_min / drag_factor, DEM dt))."""
        while self.t < t_end * (1.0 - 1e-12):
            if h is not None:
                hh = h
            elif self.dem.particles.n_owned:
                hh = min(self.relaxation_time() / self.drag_factor, self.dem.dt)
            else:
                hh = t_end - self.t  # no particles: nothing happens (pass h when a callback feeds particles)
            hh = min(hh, t_end - self.t)
            self.step(hh)
            if callback is not None:
                callback(self)


@dataclass
class OneWayCase:
    """The parameters of a one-way run (`case_settings` reads them from a case with `[run] mode = "one-way"`).

    Attributes:
        flow: prescribed flow name (uniform | vortex | function); flow_params: its keyword parameters.
        drag: registered drag law; density, viscosity: gas ρ_g (kg/m^3), μ_g (Pa s).
        end_time: s; window: drag window h (s, 0 = auto); drag_factor: auto h = τ_min / drag_factor.
        integration: exponential | explicit; output_interval: s between particle CSV rows.
        progress_interval: wall-clock s between progress lines.
    """

    flow: str = "uniform"
    flow_params: dict = field(default_factory=dict)
    drag: str = "stokes"
    density: float = 1.2
    viscosity: float = 1.8e-5
    end_time: float = 1.0
    window: float = 0.0
    drag_factor: float = 20.0
    integration: str = "exponential"
    output_interval: float = 0.01
    progress_interval: float = 10.0


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
    raises `febed.run.OutputFailure` naming it and the error. `stop`: an object whose `_signal` becomes
    nonzero when the run must stop (`febed.run.catch_stop_signals`): the run then stops after the current drag
    window (`febed.dem.solver.StopRequested`).
    """
    from febed.dem.solver import StopRequested
    from febed.io.progress import Progress, RateMeter
    from febed.run import guarded_write

    if dem is None:
        raise ValueError("dem: build the particles (a DEM) first, e.g. `febed.dem.driver.build_dem`")
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
                    from febed.solver import RunFailure

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


def case_settings(case) -> OneWayCase:
    """The `OneWayCase` of a case file's `[prescribed_gas]`, `[gas]`, `[coupling] drag` and `[run]`."""
    g = case.prescribed_gas
    flow_params = {
        "uniform": lambda: {"velocity": tuple(g.velocity)},
        "vortex": lambda: {
            "rpm": g.rpm,
            "inflow_ratio": g.inflow_ratio,
            "center": tuple(g.center),
            "outlet_radius": g.outlet_radius,
            "outlet_velocity": g.outlet_velocity,
        },  # fmt: skip
        "function": lambda: {"function": g.function},
    }[g.flow]()
    if g.flow == "function" and ":" not in g.function:
        raise ValueError(f"[prescribed_gas] function = {g.function!r}: give 'module:function'")
    return OneWayCase(
        flow=g.flow, flow_params=flow_params, drag=case.coupling.drag, density=case.gas.density,
        viscosity=case.gas.viscosity, end_time=case.run.end_time, window=g.window, drag_factor=g.drag_factor,
        integration=g.integration, output_interval=g.output_interval,
        progress_interval=case.output.progress_interval,
    )  # fmt: skip


def run(case, outdir, log, comm=None) -> OneWay:
    """`[run] mode = "one-way"`: the case's particles (walls and bed from its mesh) in its prescribed gas.

    Particles whose centre leaves the mesh's bounding box (an open outlet) are removed and counted.
    Writes outdir/particles.csv (t, gid, x, v every `output_interval`) and keeps `status.json` (running,
    finished, failed with the message); shows progress like the other modes. One process; no checkpoints
    (one-way runs are short: they are re-run rather than restarted). SIGINT/SIGTERM/SIGUSR1 stop it after the
    current drag window (its DEM sub-steps stop within a second or so) with status failed and
    `febed.run.Interrupted`; an output error (`febed.run.OutputFailure`) stops it with status failed.
    """
    from types import SimpleNamespace

    from mpi4py import MPI

    from febed.dem.driver import build_dem
    from febed.dem.solver import DEMFailure, StopRequested
    from febed.meshing import load_case_mesh
    from febed.run import Interrupted, OutputFailure, catch_stop_signals, write_run_status
    from febed.solver import RunFailure

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
