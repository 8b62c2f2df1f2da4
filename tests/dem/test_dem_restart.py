"""Pure-DEM runs write checkpoints and continue from them (`febed.runs.dem.DEMRun`), like coupled runs:
bit for bit on one rank, every particle once on any number of ranks; Ctrl-C/SIGTERM and blow-ups leave one."""

import json
import logging
import re
import signal

from mpi4py import MPI

import numpy as np
import pytest

from febed.case import load_case
from febed.io.checkpoint import CheckpointError, latest_valid, list_checkpoints, read_checkpoint

# 300 spheres poured into a 2 x 2 x 4 cm box: they fall, collide and pile up within 0.04 s
CASE = """
[run]
mode = "dem"
end_time = {end}

[mesh]
builtin = "box"
extent = [0.02, 0.02, 0.04]
size = 0.005

[particles]
diameter = 2e-3
density = 2500.0
count = 300
region = [0.0, 0.0, 0.0, 0.02, 0.02, 0.04]

[contact]
stiffness = 1e4

[output]
particle_interval = 0.005
directory = "{out}"
"""


def case_at(folder, end, out, **extra):
    """The case file for `end` (written by rank 0 only: two ranks writing one file raced, and a rank that read
    it half-written failed alone and hung the other), loaded on every rank."""
    path = folder / f"case-{end:g}.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(CASE.format(end=end, out=out))
    MPI.COMM_WORLD.barrier()
    return load_case(path, [f"{k}={v}" for k, v in extra.items()])


def run(case, out, restart=None):
    from febed.runs.dem import run as dem_run

    return dem_run(case, out, logging.getLogger("test"), MPI.COMM_WORLD, restart=restart)


def by_gid(out, k=-1):
    """Positions and velocities of the k-th checkpoint (every particle once, in gid order)."""
    state, meta = read_checkpoint(list_checkpoints(out / "checkpoints")[k])
    order = np.argsort(state["dem/p_gid"])
    return {key: state[f"dem/p_{key}"][order] for key in ("gid", "pos", "vel")}, meta


@pytest.mark.mpi
def test_stop_and_restart_continues_the_run(mpi_tmp_path):
    """A run to 0.02 s continued to 0.04 s ends where the run straight to 0.04 s ends: bit for bit on one rank;
    on two (lists rebuilt at the restart, sums in another order) every particle once, within 1e-9 m."""
    comm = MPI.COMM_WORLD
    straight, split = mpi_tmp_path / "straight", mpi_tmp_path / "split"
    run(case_at(mpi_tmp_path, 0.04, straight), straight)
    run(case_at(mpi_tmp_path, 0.02, split), split)
    dem = run(case_at(mpi_tmp_path, 0.04, split), split, restart=split / "checkpoints")
    assert dem.time == pytest.approx(0.04, abs=dem.dt)
    comm.barrier()
    (a, ma), (b, mb) = by_gid(straight), by_gid(split)
    assert ma["mode"] == mb["mode"] == "dem" and ma["step"] == mb["step"]
    assert np.array_equal(a["gid"], np.arange(300)) and np.array_equal(b["gid"], a["gid"])
    if comm.size == 1:
        assert np.array_equal(a["pos"], b["pos"]) and np.array_equal(a["vel"], b["vel"])
    else:
        np.testing.assert_allclose(b["pos"], a["pos"], rtol=0, atol=1e-9)
    assert np.abs(a["vel"][:, 2]).max() > 0.3  # falling at ~g t: the run did something
    pvd = (split / "particles" / "particles.pvd").read_text()
    assert pvd.count("<DataSet") == 9  # t = 0, 0.005, ..., 0.04: the restart continued the series


@pytest.mark.mpi
def test_sigterm_stops_with_a_checkpoint_that_continues(mpi_tmp_path):
    from febed.runs.dem import DEMRun
    from febed.runs.lifecycle import Interrupted

    out = mpi_tmp_path / "run"
    case = case_at(mpi_tmp_path, 0.02, out)
    r = DEMRun(case, out, logging.getLogger("test"), MPI.COMM_WORLD)
    r._signal = signal.SIGTERM if MPI.COMM_WORLD.rank == 0 else 0  # as the handler sets it, on one rank
    with pytest.raises(Interrupted, match="stopped by SIGTERM at t = .* after a checkpoint"):
        r.advance_to(0.02)
    MPI.COMM_WORLD.barrier()
    assert json.loads((out / "status.json").read_text())["state"] == "interrupted"
    (_, meta) = by_gid(out)
    assert 0 < meta["time"] < 0.02
    dem = run(case, out, restart=out / "checkpoints")
    assert dem.time == pytest.approx(0.02, abs=dem.dt) and dem.count() == 300


@pytest.mark.mpi
def test_blow_up_leaves_the_last_good_state(mpi_tmp_path, monkeypatch):
    from febed.dem import DEMFailure, solver

    out = mpi_tmp_path / "run"
    case = case_at(mpi_tmp_path, 0.02, out)
    advance, calls = solver.DEM.advance, []

    def fling_then_advance(self, n_steps, dt=None, f_ext=None):  # after the output at 0.005 s, fling gid 7
        calls.append(self.time)
        if self.time > 0.004:
            rows = np.flatnonzero(self.particles.gid[: self.particles.n_owned] == 7)
            self.particles.vel[rows] = [1e9, 0.0, 0.0]
        return advance(self, n_steps, dt, f_ext)

    monkeypatch.setattr(solver.DEM, "advance", fling_then_advance)
    with pytest.raises(DEMFailure, match="particle 7 at"):
        run(case, out)
    MPI.COMM_WORLD.barrier()
    status = json.loads((out / "status.json").read_text())
    good = re.search(r"last good state \(t = ([0-9.e-]+) s\)", status["message"])
    assert status["state"] == "failed" and float(good.group(1)) == pytest.approx(0.005, abs=1e-5)
    _, meta = read_checkpoint(latest_valid(out / "checkpoints"))
    assert meta["time"] == pytest.approx(0.005, abs=1e-5)  # the particle output before the fling


def test_a_checkpoint_continues_its_own_mode_only():
    from febed.restart import check_restartable

    class Run:  # check_restartable reads only run.mode and run.end_time
        mode, end_time = "cfd-dem", 1.0

    class Case:
        run = Run

    check_restartable({"time": 0.5}, Case)  # a coupled checkpoint from before modes were recorded
    with pytest.raises(CheckpointError, match="checkpoint is of a \\[run\\] mode = 'dem' run, the case is 'cfd-dem'"):
        check_restartable({"time": 0.5, "mode": "dem"}, Case)
