"""Pure-DEM run (`[run] mode = "dem"`): walls from the mesh, a packed or inserted bed, stepping, output.

The walls and the bed are the case's (`febed.bed.build_dem`). Particles that leave the mesh's bounding box
(through an open outlet) are removed and counted in the log.

With MPI (`mpirun -n N febed run`), the particles are distributed over the ranks by boxes of equal DEM work
(`febed.parallel.BoxExchange`; `[run] particle_partition = "auto"` or `"work"`), or by the mesh partition
(`"mesh"`), and migrate inside `DEM.advance`. Output gathers every particle once; the log gives the particle
load imbalance (max/mean particles per rank) at each output.

Like a coupled run, a pure-DEM run (`DEMRun`) writes checkpoints (every `[output] checkpoint_interval`
simulated or `checkpoint_wall_interval` wall seconds, on SIGINT/SIGTERM/SIGUSR1, at the end, and the last good
state when the particles blow up), continues from one with `febed run CASE --restart` on any number of
ranks, shows a progress line and keeps `status.json` up to date (`febed.runs.lifecycle`).
"""

from __future__ import annotations

import time
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed.bed import build_dem, dem_from_case, particle_exchange, walls_from_mesh
from febed.dem.particles import Particles
from febed.dem.solver import DEM, DEMFailure, StopRequested
from febed.io.particles import ParticleWriter
from febed.io.progress import peak_memory
from febed.io.state import dem_arrays, load_dem
from febed.meshing import load_case_mesh
from febed.parallel.exchange import balance_line
from febed.runs.lifecycle import (
    RunMode,
    after_step,
    catch_stop_signals,
    guarded_write,
    load_restart,
    run_to_end,
)


class DEMRun(RunMode):
    """A pure-DEM run with its output: `advance_to(t)` steps the DEM, writing particles and checkpoints.

    Checkpoints (`checkpoints/checkpoint_<step>.npz`, the same files as a coupled run's: the DEM state by
    global id, `febed.io.state.dem_arrays`) are written every `[output] checkpoint_interval` simulated or
    `checkpoint_wall_interval` wall seconds, on SIGINT/SIGTERM/SIGUSR1 and at the end. The state at each particle
    output is kept in memory: a blow-up (`DEMFailure`) writes it as the last good checkpoint.
    """

    def __init__(self, case, outdir: Path, log, comm=MPI.COMM_WORLD, restart=None):
        """Build the mesh, walls and bed; `restart`: (path, arrays, meta) of a checkpoint to continue."""
        self.case, self.outdir, self.log, self.comm = case, Path(outdir), log, comm
        md = load_case_mesh(case, comm)
        partition = case.run.particle_partition
        exchange = particle_exchange(md, comm, "work" if partition == "auto" else partition)
        self.restarted_from = None
        files = []
        self.left = 0  # particles that left the domain, on this rank
        o = case.output
        if restart is None:
            self.dem = build_dem(case, md, log, exchange)
            self.next_out, self.next_ckpt = o.particle_interval, o.checkpoint_interval
        else:
            path, arrays, meta = restart
            walls = walls_from_mesh(case, md)
            self.dem = dem_from_case(case, walls, md.gdim, Particles())
            if exchange is not None:
                self.dem.attach_exchange(exchange)
            load_dem(self.dem, arrays, meta, comm.size)
            sched = meta["run"]
            self.next_out = float(sched["next_out"])
            self.next_ckpt = self.dem.time + o.checkpoint_interval
            files = sched["particle_files"]
            self.left = int(sched["left"]) if comm.rank == 0 else 0  # the total, counted once
            self.restarted_from = path
        self.lo = np.minimum.reduce(comm.allgather(md.mesh.geometry.x.min(axis=0))) - 1e-9
        self.hi = np.maximum.reduce(comm.allgather(md.mesh.geometry.x.max(axis=0))) + 1e-9
        folder = self.outdir / "particles"
        self.writer = guarded_write(comm, folder, ParticleWriter, folder, comm=comm, entries=files)
        self._start_lifecycle(self.dem.time)

    # ------------------------------------------------------------------------------------ state
    def capture(self) -> tuple[dict, dict]:
        """This rank's state (copies) and the JSON-able meta record of a checkpoint."""
        meta = {
            "time": self.dem.time,
            "step": self.dem.steps,
            "ranks": self.comm.size,
            "mode": "dem",
            "run": {
                "next_out": self.next_out,
                "particle_files": [list(e) for e in self.writer.entries],
                "left": self.comm.allreduce(self.left),
            },
        }
        return dem_arrays(self.dem), meta

    STEP = "DEM step"

    def sim_time(self) -> float:
        """The DEM's simulated time (s)."""
        return self.dem.time

    def steps_done(self) -> int:
        """DEM steps made."""
        return self.dem.steps

    def _checkpointed(self, gathered, meta: dict, state) -> None:
        self.next_ckpt = self.dem.time + self.case.output.checkpoint_interval

    def output(self, scheduled: bool = True) -> None:
        """Write the particles, move the next output time on if `scheduled`, keep the state as the last good one.

        A failed write raises `OutputFailure` on every rank (and leaves the schedule as it was).
        """
        guarded_write(self.comm, self.writer.outdir, self.writer.write, self.dem.time, self.dem.particles)
        if scheduled:
            self.next_out += self.case.output.particle_interval
        _log_balance(self.dem, self.log)
        self.good = self.capture()

    def advance_to(self, end: float) -> None:
        """Step to `end` (s), writing particles, checkpoints and progress (collective).

        Raises DEMFailure (after writing the last good state), `febed.runs.lifecycle.OutputFailure` or
        `febed.runs.lifecycle.Interrupted` (after a checkpoint).
        """
        dem = self.dem
        dt = dem.dt
        if self.good is None:
            if self.restarted_from is None:
                self.output(scheduled=False)
            elif dem.time >= self.next_out - 0.5 * dt:  # due when the run before stopped on an output error
                self.output()
            else:
                self.good = self.capture()
        self.status("running")
        while dem.time < end - 0.5 * dt:
            target = min(end, self.next_out, self.next_ckpt)
            n = max(1, int(round((target - dem.time) / dt)))
            try:
                dem.advance(min(n, CHUNK), dt)
            except DEMFailure as e:  # raised on every rank
                self.fail(f"the particles blew up: {e}")
                raise
            except StopRequested:  # a stop signal, agreed on every rank: the particles are at a whole step
                pass  # `after_step` below writes the checkpoint and stops
            x = dem.particles.pos[: dem.particles.n_owned]
            gone = np.any((x < self.lo) | (x > self.hi), axis=1)
            if gone.any():
                self.left += int(gone.sum())
                dem.remove_particles(gone)
            if dem.time >= self.next_out - 0.5 * dt:
                self.output()
            if after_step(self, dem.time, dem.time >= self.next_ckpt - 0.5 * dt):
                self.progress(end)
        self.progress(end)
        self.display.end()

    def progress_text(self, end: float, now: float) -> str:
        """Simulated time, steps, particles, particles left (collective)."""
        dem = self.dem
        left = self.comm.allreduce(self.left)
        return f"t = {dem.time:.5f} / {end:g} s  step {dem.steps}  {dem.count()} particles  {left} left"

    def close(self, last_output: bool = True) -> None:
        """Nothing to close: every particle output is a complete file of its own."""

    def catch_signals(self):
        """Handle the stop signals by stopping within a second (`DEM.stop_check`); returns the restorer."""
        return catch_stop_signals(self, "these DEM steps", self.dem)


CHUNK = 500  # DEM steps per `advance` call between output, signal and progress checks


def run(case, outdir, log, comm=MPI.COMM_WORLD, restart=None) -> DEM:
    """Run a pure-DEM case to `run.end_time` (called by `febed run`); returns the DEM.

    `restart`: a checkpoint file or run folder to continue from (its newest valid checkpoint).
    """
    ckpt = load_restart(restart, case, comm)
    r = DEMRun(case, outdir, log, comm, restart=ckpt)
    dem = r.dem
    start = f"restarted from {r.restarted_from} at t = {dem.time:.6g} s" if ckpt else "DEM"
    end = case.run.end_time
    log.info(f"{start}: {dem.count()} particles on {comm.size} process(es), dt = {dem.dt:.3e} s "
             f"(T_C/{dem.params.dt_factor:g}), {dem.params.integrator}, law {dem.params.contact_model}, "
             f"to t = {end:g} s")  # fmt: skip
    wall0 = time.time()
    run_to_end(r, end)
    left = comm.allreduce(r.left)
    log.info(
        f"DEM done: t = {dem.time:.5f} s, {dem.steps} steps in {time.time() - wall0:.1f} s; "
        f"max overlap {100 * dem.global_max(dem.max_overlap):.3f} % d; {left} particles left the domain; "
        f"{peak_memory(comm)}"
    )
    if dem.exchange is not None:
        t = dem.exchange.timers
        log.info("particle exchange: " + ", ".join(f"{k} {comm.allreduce(v, op=MPI.MAX):.2f} s" for k, v in t.items())
                 + f"; {comm.allreduce(dem.exchange.migrated)} migrations")  # fmt: skip
    return dem


def _log_balance(dem: DEM, log) -> None:
    """Log the particle load imbalance max/mean over ranks (collective; nothing on one process)."""
    if dem.exchange is None:
        return

    total, ghosts = dem.exchange.counts(dem.particles)
    line = balance_line(dem.exchange.comm, dem.particles.n_owned, dem.pairs.size)
    log.info(f"{line}; {total} particles, {ghosts} ghosts")
