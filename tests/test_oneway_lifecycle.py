"""One-way runs live like the other modes (`febed.runs.oneway.OneWayRun`): checkpoints, `--restart` bit for bit,
a stop signal that leaves a checkpoint, a particle no longer finite that fails the run with its last good state."""

import json
import os
import re
import shutil
import signal

import numpy as np
import pytest

from febed.cli import main
from febed.io.checkpoint import latest_valid, list_checkpoints, read_checkpoint

# 30 particles of 0.1 mm carried by a uniform gas across a 2 cm box: they speed up and settle under gravity; the
# walls are soft, and from t = 0.01 s on they pass through the far one and leave the domain
CASE = """
[run]
mode = "one-way"
end_time = 0.04
[mesh]
builtin = "box"
extent = [0.02, 0.02, 0.02]
size = 0.005
[gas]
density = 1.2
viscosity = 1.8e-5
[particles]
diameter = 1e-4
density = 2500.0
count = 30
region = [0.014, 0.008, 0.0, 0.0195, 0.012, 0.004]
[contact]
stiffness = 1e-2
[coupling]
drag = "stokes"
[prescribed_gas]
flow = "uniform"
velocity = [1.0, 0.0, 0.1]
output_interval = 0.005
[output]
checkpoint_interval = 0.004
"""
END = 0.04


@pytest.fixture(scope="module")
def case_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("oneway") / "case.toml"
    path.write_text(CASE)
    return path


def febed(case_file, out, *args):
    """`febed run` of the case into `out`, in this process; returns the exit status."""
    return main(["run", str(case_file), "--set", f"output.directory={out}", *args])


@pytest.fixture(scope="module")
def straight(case_file, tmp_path_factory):
    """The run left alone from 0 to END."""
    out = tmp_path_factory.mktemp("straight")
    assert febed(case_file, out) == 0
    return out


def final_state(out):
    """(meta, positions, velocities) of a run's newest checkpoint, the particles in gid order."""
    arrays, meta = read_checkpoint(latest_valid(out / "checkpoints"))
    order = np.argsort(arrays["dem/p_gid"])
    return meta, arrays["dem/p_pos"][order], arrays["dem/p_vel"][order]


def status(out):
    return json.loads((out / "status.json").read_text())


def assert_same_run(out, straight):
    """`out` ended where the run left alone ended: the same rows, byte for byte, and the same particles."""
    assert (out / "particles.csv").read_bytes() == (straight / "particles.csv").read_bytes()
    (ma, pa, va), (mb, pb, vb) = final_state(straight), final_state(out)
    assert ma["mode"] == mb["mode"] == "one-way" and ma["step"] == mb["step"] and ma["time"] == mb["time"]
    assert ma["run"] == mb["run"]
    assert np.array_equal(pa, pb) and np.array_equal(va, vb)
    assert status(out)["state"] == "finished"


def test_a_run_stopped_at_its_end_time_and_restarted_is_the_run_left_alone(case_file, straight, tmp_path):
    rows = np.loadtxt(straight / "particles.csv", delimiter=",", skiprows=1)
    times = np.unique(rows[:, 0])
    np.testing.assert_allclose(times, np.arange(9) * 0.005, rtol=0, atol=1e-15)  # t = 0, 0.005, ..., 0.04
    assert np.count_nonzero(rows[:, 0] == 0) == 30 and np.ptp(rows[:, 5]) > 0.01  # the gas moved them: vx grew
    meta, pos, _ = final_state(straight)
    removed = meta["run"]["removed"]  # soft walls: fast particles pass through them and leave the domain
    assert meta["time"] == pytest.approx(END) and removed > 0 and len(pos) + removed == 30
    assert np.count_nonzero(rows[:, 0] == rows[-1, 0]) == len(pos)
    out = tmp_path / "split"
    assert febed(case_file, out, "--set", "run.end_time=0.02") == 0
    meta, _, _ = final_state(out)
    assert meta["time"] == pytest.approx(0.02) and meta["run"]["removed"] > 0  # some left before the stop
    with open(out / "particles.csv", "a") as f:
        f.write("2.5e-02,1.0e+00,1.9")  # a row a crash left half written
    assert febed(case_file, out, "--restart") == 0
    assert_same_run(out, straight)


def test_a_restart_from_an_older_checkpoint_cuts_the_rows_written_after_it(case_file, straight, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(straight, out)
    older = list_checkpoints(out / "checkpoints")[0]
    t = read_checkpoint(older)[1]["time"]
    rows = np.loadtxt(out / "particles.csv", delimiter=",", skiprows=1)
    assert t < 0.04 and rows[-1, 0] > t  # rows after it: the restart writes them again, once
    assert febed(case_file, out, "--restart", str(older)) == 0
    assert_same_run(out, straight)


def test_a_stop_signal_writes_a_checkpoint_and_the_restart_continues(case_file, straight, tmp_path, monkeypatch):
    """SIGUSR1 (as a batch system sends it) between two output times: a checkpoint of that moment, exit 138."""
    from febed.coarse.oneway import OneWay

    step, sent = OneWay.step, []

    def step_then_signal(self, h):
        step(self, h)
        if self.t > 0.022 and not sent:
            sent.append(self.t)
            os.kill(os.getpid(), signal.SIGUSR1)

    monkeypatch.setattr(OneWay, "step", step_then_signal)
    out = tmp_path / "run"
    assert febed(case_file, out) == 128 + signal.SIGUSR1
    info = status(out)
    assert info["state"] == "interrupted" and "stopped by SIGUSR1" in info["message"], info
    meta, _, _ = final_state(out)
    assert meta["time"] == sent[0]  # the window's end at which the signal was seen
    rows = np.loadtxt(out / "particles.csv", delimiter=",", skiprows=1)
    assert rows[-1, 0] == pytest.approx(0.02) and meta["run"]["removed"] > 0  # the rows before the stop
    monkeypatch.undo()
    assert febed(case_file, out, "--restart") == 0
    assert_same_run(out, straight)


def test_a_signal_in_a_long_drag_window_continues_from_the_last_output(case_file, tmp_path, monkeypatch):
    """Windows of many DEM sub-steps stop within them; the last good state (the output before) is continued."""
    from febed.dem import solver

    monkeypatch.setattr(solver, "STOP_CHECK_WORK", 30)  # ask for a signal every DEM sub-step
    advance, sent = solver.DEM.advance, []

    def advance_then_signal(self, n_steps, dt=None, f_ext=None):
        if self.time > 0.022 and not sent:
            sent.append(self.time)
            os.kill(os.getpid(), signal.SIGTERM)  # seen by the DEM's first question within this window
        return advance(self, n_steps, dt, f_ext)

    monkeypatch.setattr(solver.DEM, "advance", advance_then_signal)
    out = tmp_path / "run"
    window = ["--set", "prescribed_gas.window=0.0025"]  # a window of several DEM steps
    assert febed(case_file, out, *window) == 128 + signal.SIGTERM
    info = status(out)
    assert info["state"] == "interrupted" and "in the middle of the drag window" in info["message"], info
    assert final_state(out)[0]["time"] == pytest.approx(0.02)  # the last output before the signal
    monkeypatch.undo()
    assert febed(case_file, out, "--restart", *window) == 0
    rows = np.loadtxt(out / "particles.csv", delimiter=",", skiprows=1)
    times, counts = np.unique(rows[:, 0], return_counts=True)
    np.testing.assert_allclose(times, np.arange(9) * 0.005, rtol=0, atol=1e-15)
    # every output once: the rows written after the checkpoint were cut off at the restart
    assert counts[0] == 30 and (np.diff(counts) <= 0).all()
    assert status(out)["state"] == "finished"


def test_a_particle_no_longer_finite_fails_the_run_with_its_last_good_state(case_file, tmp_path, monkeypatch, capsys):
    from febed.coarse.oneway import OneWay

    step, when = OneWay.step, []

    def step_then_spoil(self, h):
        step(self, h)
        if self.t > 0.017 and not when:
            P = self.dem.particles
            row = P.n_owned // 2
            P.vel[row] = np.nan
            when.append((self.t, int(P.gid[row])))

    monkeypatch.setattr(OneWay, "step", step_then_spoil)
    out = tmp_path / "run"
    assert febed(case_file, out) == 3
    info = status(out)
    assert info["state"] == "failed", info
    t, gid = when[0]
    said = f"particle {gid} has a non-finite position or velocity at t = {t:.6g} s"
    assert info["message"].startswith(said) and f"febed: the run failed: {said}" in capsys.readouterr().err
    good = re.search(r"last good state \(t = ([0-9.e-]+) s\) in (\S+\.npz)", info["message"])
    assert good, info
    meta, pos, vel = final_state(out)  # the newest checkpoint: the last good state, before the particle spoilt
    assert float(good.group(1)) == pytest.approx(meta["time"], rel=1e-5) and 0.015 <= meta["time"] < t
    assert np.isfinite(pos).all() and np.isfinite(vel).all()
    rows = np.loadtxt(out / "particles.csv", delimiter=",", skiprows=1)
    assert rows[-1, 0] == pytest.approx(0.015) and np.isfinite(rows).all()  # the rows up to the failure
    assert f"run failed: {said}" in (out / "febed.log").read_text()
