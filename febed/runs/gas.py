"""Gas-only runs (`run.mode = "gas"`): the VANS solver with a prescribed void fraction, to run.end_time.

The void fraction is the uniform `gas.void_fraction`, or (Python API) a callable eps(x, t) of the node
coordinates x (n, 3) and the time t returning (n,) values in (0, 1]. Fields u, p, ε are written as XDMF
(`fields.xdmf` and its folder `fields/` in the output folder, `febed.io.fields`; `fields.restart<k>.xdmf`
after the k-th restart) every `output.field_interval`.

Like coupled and pure-DEM runs, a gas-only run (`GasRun`) shows a progress line (simulated time, step, Δt,
CFL, Poisson iterations, wall time per simulated second, ETA) every `output.progress_interval` wall seconds,
live on a terminal and always in `febed.log`; keeps `status.json` up to date; writes checkpoints (the gas
state at the owned nodes with their coordinates, `febed.io.state.gas_arrays`) every
`output.checkpoint_interval` simulated or `checkpoint_wall_interval` wall seconds, on SIGINT/SIGTERM/SIGUSR1
and at the end, and continues from one with `febed run CASE --restart` on any number of ranks. After every
step the velocity and pressure are checked: a non-finite value, or a pressure solve that does not converge,
stops the run with a message naming the node and the time, writes the last state that passed (kept every
`GOOD_EVERY` steps and at each field output and progress line) as a checkpoint and exits with status 3
(`febed.runs.lifecycle`).
"""

from __future__ import annotations

import logging
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed.gas.pressure import PressureSolveError
from febed.gas.vans import VANSSolver
from febed.io.fields import FieldWriter
from febed.io.progress import peak_memory
from febed.io.state import gas_arrays, restore_gas
from febed.meshing import load_case_mesh
from febed.runs.lifecycle import (
    RunMode,
    after_step,
    catch_stop_signals,
    close_files,
    guarded_write,
    load_restart,
    run_to_end,
)
from febed.solver import RunFailure

GOOD_EVERY = 10  # gas steps between the copies of the state kept as the last good one (and at every output)


class GasRun(RunMode):
    """A gas-only run with its output: `advance_to(t)` steps the gas, writing fields, checkpoints, progress."""

    def __init__(self, case, outdir: Path, log, comm=MPI.COMM_WORLD, eps=None, mesh_data=None, restart=None):
        """Build the mesh (unless `mesh_data` is given) and the solver; `restart`: (path, arrays, meta) to continue.

        `eps`: None for the uniform `gas.void_fraction`, or a callable eps(x, t) -> (n,) array.
        """
        if eps is not None and not callable(eps):
            raise ValueError("eps must be a callable eps(x, t) -> (n,) array, or None for gas.void_fraction")
        self.case, self.outdir, self.log, self.comm = case, Path(outdir), log, comm
        self.md = mesh_data if mesh_data is not None else load_case_mesh(case, comm, cache_dir=self.outdir / "mesh")
        self.eps = eps
        self.solver = s = VANSSolver.from_case(case, self.md)
        self.steps = 0
        self.segment = 0  # restarts so far
        self.next_out = case.output.field_interval
        self.restarted_from = None
        if restart is not None:
            path, arrays, meta = restart
            restore_gas(s, arrays, float(meta["time"]), comm)
            self.steps = int(meta["step"])
            self.segment = int(meta["run"]["segment"]) + 1
            self.next_out = float(meta["run"]["next_out"])
            self.restarted_from = path
        elif eps is not None:
            s.set_void_fraction(eps(s.x, 0.0))
        self.next_ckpt = s.t + case.output.checkpoint_interval
        name = "fields.xdmf" if self.segment == 0 else f"fields.restart{self.segment}.xdmf"
        self.writer = guarded_write(comm, self.outdir / name, FieldWriter, self.outdir / name, self.md.mesh,
                                    s.functions(), comm)  # fmt: skip
        self._start_lifecycle(s.t)
        self.last_info = None
        self._wall0 = self._last_progress
        self._steps0 = self.steps

    # ------------------------------------------------------------------------------------ state
    def capture(self) -> tuple[dict, dict]:
        """This rank's gas state (copies) and the JSON-able meta record of a checkpoint."""
        s = self.solver
        meta = {
            "time": s.t,
            "step": self.steps,
            "ranks": self.comm.size,
            "mode": "gas",
            "run": {"next_out": self.next_out, "segment": self.segment},
        }
        return gas_arrays(s), meta

    STEP = "gas step"

    def sim_time(self) -> float:
        """The gas's simulated time (s)."""
        return self.solver.t

    def steps_done(self) -> int:
        """Gas steps made."""
        return self.steps

    def _checkpointed(self, gathered, meta: dict, state) -> None:
        self.next_ckpt = self.solver.t + self.case.output.checkpoint_interval

    def problem(self) -> str | None:
        """What is wrong with the gas fields after a step (the same on every rank; collective), or None."""
        s = self.solver
        msg = None
        for name, a in (("velocity u", s.u), ("pressure p", s.p)):
            ok = np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)
            if not ok.all():
                k = int(np.flatnonzero(~ok)[0])
                msg = (
                    f"gas {name} is not finite at the node at {np.round(s.x[k], 6).tolist()} m at t = {s.t:.6g} s "
                    f"(gas step {self.steps}); lower gas.cfl or gas.dt_max"
                )
                break
        found = [m for m in self.comm.allgather(msg) if m] if self.comm.size > 1 else [msg] if msg else []
        return found[0] if found else None

    # ------------------------------------------------------------------------------------- loop
    def advance_to(self, end: float) -> None:
        """Step to `end` (s), writing fields, checkpoints and progress (collective).

        Raises RunFailure (after writing the last good state) or `febed.runs.lifecycle.Interrupted` (after a
        checkpoint).
        """
        s = self.solver
        o = self.case.output
        if self.restarted_from is None and self.steps == 0:
            guarded_write(self.comm, self.writer.path, self.writer.write, s.t)
        elif s.t >= self.next_out * (1 - 1e-12):  # due when the run before stopped on an output error
            guarded_write(self.comm, self.writer.path, self.writer.write, s.t)
            self.next_out += o.field_interval
        if self.good is None:
            self.good = self.capture()
        self.status("running")
        while s.t < end * (1 - 1e-12):
            dt = s.compute_dt()
            stop = min(end, self.next_out)
            if s.t + dt > stop - 1e-9 * dt:  # land exactly on the next output / end time
                dt = stop - s.t
            eps = self.eps(s.x, s.t + dt) if self.eps is not None else None
            try:
                self.last_info = s.step(dt, eps=eps)
            except PressureSolveError as e:  # raised on every rank
                err = RunFailure(f"{e} in the gas step from t = {s.t:.6g} s (gas step {self.steps + 1})")
                self.fail(err)
                raise err from None
            self.steps += 1
            problem = self.problem()
            if problem:
                err = RunFailure(problem)
                self.fail(err)
                raise err
            wrote = s.t >= self.next_out * (1 - 1e-12)
            if wrote:
                guarded_write(self.comm, self.writer.path, self.writer.write, s.t)
                self.next_out += o.field_interval
            show = after_step(self, s.t, s.t >= self.next_ckpt - 1e-12 * end)
            if wrote or show or self.steps % GOOD_EVERY == 0:
                self.good = self.capture()
            if show:
                self.progress(end)
        self.progress(end)
        self.display.end()

    def progress_text(self, end: float, now: float) -> str:
        """Simulated time, step, Δt, CFL, Poisson iterations, mass imbalance, wall time per step."""
        s = self.solver
        steps = self.steps - self._steps0
        info = self.last_info
        gas = (
            f"dt {info.dt:.3g} s  CFL {info.cfl:.3f}  Poisson its {info.poisson_iterations}  "
            f"mass imbalance {info.mass_imbalance:.3g} kg/s  "
            if info is not None
            else ""
        )
        per_step = f"{1e3 * (now - self._wall0) / steps:.1f} ms/step  " if steps else ""
        return f"t = {s.t:.5g} / {end:g} s  step {self.steps}  {gas}{per_step}".rstrip()

    def catch_signals(self):
        """Handle the stop signals by stopping after the current gas step; returns the restorer."""
        return catch_stop_signals(self, "this gas step")

    def close(self, last_output: bool = True) -> None:
        """Close the field file (OutputFailure if that fails; a second call does nothing)."""
        close_files(self.comm, self.writer)


def run(case, outdir, log: logging.Logger | None = None, eps=None, mesh_data=None, restart=None) -> VANSSolver:
    """Run a gas-only case to `run.end_time`; write fields to `outdir`; return the solver at the end.

    `restart`: a checkpoint file or (run) folder to continue from (its newest valid checkpoint).
    """
    log = log or logging.getLogger("febed")
    comm = MPI.COMM_WORLD
    ckpt = load_restart(restart, case, comm)
    r = GasRun(case, outdir, log, comm, eps=eps, mesh_data=mesh_data, restart=ckpt)
    s = r.solver
    start = f"restarted from {r.restarted_from} at t = {s.t:.6g} s" if ckpt else "gas"
    log.info(
        f"{start}: {comm.allreduce(s.n_owned)} nodes, LES {case.gas.les}, "
        f"boundaries {', '.join(f'{n}={b.type}' for n, b in s.bc.specs.items())}, to t = {case.run.end_time:g} s"
    )
    run_to_end(r, case.run.end_time)
    log.info(f"gas: {r.steps} steps to t = {s.t:.5g} s; {peak_memory(comm)}; fields in {r.writer.path}")
    return s
