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
Under Open MPI's mpirun, SIGUSR1 is the one to send: mpirun forwards it to the ranks as it is, whereas on
SIGTERM or SIGINT it kills them after a short grace that a gas step on a loaded machine can outlast.

Definitions:

* **Bed height**: the height (along gravity) below which `[output] bed_fraction` of the particle volume lies.
* **Cross-section averaged pressure** at height z: mean of p over a uniform grid of sample points filling
  the mesh's cross-section at z (midpoint rule; points outside the mesh are dropped).
* **Bed pressure drop** `dp_bed`: ⟨p⟩ at the bottom of the mesh minus ⟨p⟩ at the top, less the weight of
  the gas column ρ_g g H, i.e. the part of the pressure drop that carries the particles.
"""

from __future__ import annotations

import math
import signal
import time
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed import restart as rs
from febed.coupling.exchange import solid_volume
from febed.coupling.interpolate import interpolate
from febed.coupling.locate import FOUND, locate
from febed.coupling.weights import compute_weights
from febed.dem.solver import DEMFailure
from febed.io.checkpoint import FOLDER, CheckpointError, write_checkpoint
from febed.io.probes import ProbeFile
from febed.io.progress import Progress, RateMeter
from febed.io.rundir import write_status
from febed.solver import RunFailure, build_solver

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1)  # finish the step, checkpoint, stop


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

    The stop signals are caught meanwhile; the handlers are restored and the run's files closed even on a
    failure or a stop (collective).
    """
    restore_signals = run.catch_signals()
    try:
        run.advance_to(end)
        run.checkpoint()
        run.status("finished")
    finally:
        restore_signals()
        run.close()


def record_failure(run, error, collective: bool = True) -> None:
    """Record a failed run of any mode: the last good state, the status and the log.

    Ends the progress line, writes the last good state (`run.good`) as a checkpoint if `collective` (every rank
    takes part), sets the status to failed and logs the error with where that state is.
    """
    from febed.io.checkpoint import CheckpointError

    run.display.end()
    where = ""
    if run.good is not None and collective:
        try:
            path = run.checkpoint(run.good)
            where = f"; last good state (t = {run.good[1]['time']:.6g} s) in {path}"
        except (RunFailure, CheckpointError) as e:
            where = f"; could not write the last good state: {e}"
    run.status("failed", f"{error}{where}")
    run.log.error(f"run failed: {error}{where}")


class Interrupted(Exception):
    """The run stopped on a signal after writing a checkpoint; `signum` is the signal."""

    def __init__(self, signum: int, message: str):
        super().__init__(message)
        self.signum = signum


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

        `restart`: (path, arrays, meta) of a checkpoint (`febed.io.checkpoint.load_checkpoint`) to continue.
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
        self.probes = ProbeFile(
            self.outdir / "probes.csv", self.columns, comm, restart_time=s.t if restart else None,
            keep_rows=self._probe_rows,
        )  # fmt: skip
        self._writers()
        self.display = Progress(log, comm.rank)
        self.good = None  # (arrays, meta) of the last state that passed the health checks
        self.broken = False  # a rank failed alone: collectives would hang
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
        self.fields = FieldWriter(self.outdir / name, self.md.mesh, funcs, self.comm)
        self.particles = ParticleWriter(self.outdir / "particles", comm=self.comm, entries=self._particle_files)

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
        failure writes it as the last good checkpoint.
        """
        s = self.solver
        o = self.case.output
        t0 = time.perf_counter()
        tol = 1e-9 * max(s.last_gas.dt if s.last_gas else 1.0, 1e-12)
        kinds = ("probe", "field", "particle")
        due = {k: (force and self.last[k] != s.t) or s.t >= self.next[k] - tol for k in kinds}
        if due["probe"]:
            self.probes.write(s.t, self.probe_values())
        if due["field"]:
            self.alpha.x.array[:] = s.alpha
            self.fields.write(s.t)
        if due["particle"]:
            self.particles.write(s.t, s.dem.particles)
            self._log_balance()
            self._log_groups()
        for kind in kinds:
            if due[kind]:
                self.last[kind] = s.t
                self.next[kind] = s.t + getattr(o, f"{kind}_interval")
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
        try:
            path = write_checkpoint(
                self.outdir / FOLDER, gathered, meta, self.case.output.keep_checkpoints, self.comm
            )  # fmt: skip
        except CheckpointError as e:
            raise RunFailure(str(e)) from None
        if self.comm.size > 1 and state is None:  # go on from the layout a restart would have (febed.restart)
            rs.reload_particles(self, self.comm.bcast(gathered, root=0), meta)
        self._last_checkpoint = time.perf_counter()
        self.next["checkpoint"] = s.t + self.case.output.checkpoint_interval
        self.log.info(f"checkpoint at t = {meta['time']:.6g} s (gas step {meta['step']}): {path}")
        s.timers.output += time.perf_counter() - t0
        return path

    def status(self, state: str, message: str = "") -> None:
        """Write `status.json`: state (running / finished / failed / interrupted), time, end time, message."""
        s = self.solver
        write_status(self.outdir, state, s.t, self.case.run.end_time, s.steps, message, self.comm)

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

        Raises RunFailure (after writing the last good state) or Interrupted (after a checkpoint).
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

    def close(self) -> None:
        """Write the last output and close the files (not after a one-rank failure on several ranks)."""
        if self.broken:
            return
        self.output(force=True)
        self.probes.close()
        self.fields.close()

    # ---------------------------------------------------------------------------------------- signals
    def catch_signals(self):
        """Handle STOP_SIGNALS by stopping after the current gas step; returns a function restoring the handlers."""
        return catch_stop_signals(self, "this gas step")


def catch_stop_signals(run, after: str):
    """Install STOP_SIGNALS handlers that set `run._signal` (logged to `run.log`: "stopping after `after`").

    A second signal raises KeyboardInterrupt (stop now). Returns a function restoring the previous handlers;
    outside the main thread (no handlers possible) a no-op.
    """
    import threading

    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def handler(signum, frame):
        if run._signal:  # a second Ctrl-C: stop now
            raise KeyboardInterrupt
        run._signal = signum
        run.log.warning(f"{signal.Signals(signum).name} received: stopping after {after}")

    old = {sig: signal.signal(sig, handler) for sig in STOP_SIGNALS}
    return lambda: [signal.signal(k, v) for k, v in old.items()]


def run_coupled(case, outdir, log, comm=MPI.COMM_WORLD, restart=None):
    """Run a coupled case to `run.end_time` (called by `febed run`); returns the CoupledRun.

    `restart`: a checkpoint file or run folder to continue from (its newest valid checkpoint).
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
