"""The coupled run (`[run] mode = "cfd-dem"`): output and probe intervals, progress, the probe quantities.

`run_coupled` builds the `CoupledRun` of a case (its `febed.solver.CoupledSolver` and writers) and calls the
solver's `step()` until the end time; between steps it writes

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
checkpoint, and exits non-zero. Stop signals, failures and output errors are handled as in every run mode
(`febed.runs.lifecycle`): a signal finishes the current gas step (or stops its DEM sub-steps within a second
or so), writes a checkpoint and stops (`Interrupted`); an output error stops the run with status 3
(`OutputFailure`).

Definitions:

* **Bed height**: the height (along gravity) below which `[output] bed_fraction` of the particle volume lies.
* **Cross-section averaged pressure** at height z: mean of p over a uniform grid of sample points filling
  the mesh's cross-section at z (midpoint rule; points outside the mesh are dropped).
* **Bed pressure drop** `dp_bed`: ⟨p⟩ at the bottom of the mesh minus ⟨p⟩ at the top, less the weight of
  the gas column ρ_g g H, i.e. the part of the pressure drop that carries the particles.
"""

from __future__ import annotations

import time
from pathlib import Path

from mpi4py import MPI

import dolfinx.fem
import numpy as np

from febed import restart as rs
from febed.coupling.exchange import solid_volume
from febed.dem.solver import DEMFailure, StopRequested
from febed.io.fields import FieldWriter
from febed.io.particles import ParticleWriter
from febed.io.probes import ProbeFile
from febed.io.progress import peak_memory
from febed.meshing import load_case_mesh
from febed.parallel.exchange import balance_line
from febed.runs.lifecycle import (
    OutputFailure,
    RunMode,
    after_step,
    catch_stop_signals,
    close_after_error,
    close_files,
    guarded_write,
    load_restart,
    record_internal_error,
    run_to_end,
    stopped_mid_step,
)
from febed.runs.probes import SectionAverage, bed_height
from febed.solver import RunFailure, build_solver


class CoupledRun(RunMode):
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
        self.mid_step = False  # stopped in the middle of a gas step: the state in memory is not a whole step
        self._closed = False
        self._start_lifecycle(s.t)
        try:
            self.probes = guarded_write(
                comm, self.outdir / "probes.csv", ProbeFile, self.outdir / "probes.csv", self.columns, comm,
                restart_time=s.t if restart else None, keep_rows=self._probe_rows,
            )  # fmt: skip
            self._writers()
        except OutputFailure:
            close_after_error(self, False)
            raise

    def _writers(self) -> None:
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
            own = [n, tot.crushed, tot.merged, tot.crush_deferred + tot.merge_deferred]
            counts = self.comm.allreduce(np.array(own, dtype=np.int64))
            vals.update(zip(("groups", "crushed", "merged", "events_deferred"), counts.tolist(), strict=True))
            vals["originals"] = self.comm.allreduce(float(P.n_orig[:n].sum()))  # fractions with divisible originals
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
        dem = self.solver.dem
        self.log.info(balance_line(self.comm, dem.particles.n_owned, dem.pairs.size))

    # ---------------------------------------------------------------------------------- checkpoints
    STEP = "gas step"

    def sim_time(self) -> float:
        """The coupled solver's simulated time (s)."""
        return self.solver.t

    def steps_done(self) -> int:
        """Gas steps made."""
        return self.solver.steps

    def capture(self) -> tuple[dict, dict]:
        """(arrays, meta) of the run's state (`febed.restart.capture`)."""
        return rs.capture(self)

    def checkpoint(self, state=None) -> Path:
        """`RunMode.checkpoint`, its time counted as output."""
        t0 = time.perf_counter()
        path = super().checkpoint(state)
        self.solver.timers.output += time.perf_counter() - t0
        return path

    def _checkpointed(self, gathered, meta: dict, state) -> None:
        if self.comm.size > 1 and state is None:  # go on from the layout a restart would have (febed.restart)
            rs.reload_particles(self, self.comm.bcast(gathered, root=0), meta)
        self.next["checkpoint"] = self.solver.t + self.case.output.checkpoint_interval

    # ---------------------------------------------------------------------------------------- loop
    def progress_text(self, end: float, now: float) -> str:
        """Simulated time, gas step, particles, DEM sub-steps per gas step (collective under MPI)."""
        s = self.solver
        n = self.comm.allreduce(s.dem.particles.n_owned)
        return f"t = {s.t:.5f} / {end:g} s  step {s.steps}  {n} particles  {s.n_sub} sub-steps/step"

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
            except Exception as e:
                # Only this rank may know: the others may wait in a collective, so on several ranks there is no
                # closing output and no collective checkpoint. A blow-up can surface inside a kernel or NumPy
                # call before the checks see it (an absurd array size); the state then shows it. An error
                # with nothing wrong in the state is a bug in febed, reported as such.
                where = f"in the gas step from t = {s.t:.6g} s"
                problem = "out of memory" if isinstance(e, MemoryError) else s._local_problem()  # this rank's checks
                if problem is None:
                    raise record_internal_error(self, e, where) from e
                err = RunFailure(f"{problem}; it stopped the gas step from t = {s.t:.6g} s: {type(e).__name__}: {e}")
                self.broken = err.alone = self.comm.size > 1
                self.fail(err, collective=not self.broken)
                raise err from e
            self.output()
            if after_step(self, s.t, s.t >= self.next["checkpoint"] - 1e-12 * end):
                self.progress(end)
        self.progress(end)
        self.display.end()

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
        """Handle the stop signals by stopping after the current gas step; returns the restorer."""
        return catch_stop_signals(self, "this gas step", self.solver.dem)


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
    ckpt = load_restart(restart, case, comm)
    run = CoupledRun(case, Path(outdir), log, comm, restart=ckpt)
    s = run.solver
    start = f"restarted from {run.restarted_from} at t = {s.t:.6g} s" if ckpt else "cfd-dem"
    log.info(
        f"{start}: {comm.allreduce(s.dem.particles.n_owned)} particles, {s.num_nodes} nodes, "
        f"drag {case.coupling.drag}, DEM step {s.dem.dt:.3e} s, to t = {case.run.end_time:g} s"
    )
    if comm.size > 1:
        log.info(s.partition_line())
    run_to_end(run, case.run.end_time)
    t = s.timers
    total = t.dem + t.coupling + t.gas + t.output
    left = comm.allreduce(s.left_outlet)  # each rank counts its own (probes.csv has the same total)
    log.info(
        f"done: {s.steps} gas steps to t = {s.t:.5f} s in {total:.1f} s "
        f"(DEM {t.dem:.1f} s, coupling {t.coupling:.1f} s, gas {t.gas:.1f} s, output {t.output:.1f} s); "
        f"{left} particles left through the outlet; {peak_memory(comm)}; probes in {run.outdir / 'probes.csv'}"
    )
    return run
