"""Stop signals are honoured within seconds whatever the step size, at start-up too, and what a stopped or
failed run says is true: its status, febed.log, and the checkpoint it names.

The runs are the seed-000 2D bed of demos/wang2d; a contact stiffness of 1e20 N/m (with --force) makes a DEM
step of 5e-14 s, about 4e9 DEM sub-steps in one gas step, which used to ignore SIGTERM.
"""

import json
import logging
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest
from _febed_process import MPIRUN, clean_env

from febed.cli import main
from febed.io.checkpoint import latest_valid, list_checkpoints, read_checkpoint

ROOT = Path(__file__).resolve().parents[1]
CASE = ROOT / "demos" / "wang2d" / "wang2d.toml"
STIFF = ["--set", "contact.stiffness=1e20", "--force"]


def command(out, end, *extra):
    sets = ["--set", f"output.directory={out}", "--set", f"run.end_time={end}"]
    return [sys.executable, "-m", "febed.cli", "run", str(CASE), *sets, *extra]


def start(cmd, until, **kwargs):
    """Start `cmd`; return (process, output so far) once a line of its output starts with `until`."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kwargs)
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if line.startswith(until):
            return proc, "".join(seen)
    proc.wait()
    raise AssertionError(f"the run ended before printing {until!r}:\n{''.join(seen)[-3000:]}")


def stop(proc, sig, timeout):
    """Send `sig`; return (exit status, seconds until the process ended, the rest of its output)."""
    t0 = time.monotonic()
    proc.send_signal(sig)
    try:
        rest, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        rest, _ = proc.communicate()
        raise AssertionError(f"{signal.Signals(sig).name} ignored for {timeout} s:\n{rest[-3000:]}") from None
    return proc.returncode, time.monotonic() - t0, rest


def status(out):
    return json.loads((Path(out) / "status.json").read_text())


def test_sigterm_stops_a_gas_step_of_billions_of_dem_steps_within_seconds(tmp_path):
    out = tmp_path / "run"
    proc, _ = start(command(out, 0.01, *STIFF), "cfd-dem:")
    time.sleep(2.0)  # well inside the first gas step's DEM sub-steps
    code, waited, rest = stop(proc, signal.SIGTERM, timeout=10)
    assert code == 128 + signal.SIGTERM and waited < 10, rest
    info = status(out)
    assert info["state"] == "interrupted" and "stopped by SIGTERM in the middle of the gas step" in info["message"]
    newest = latest_valid(out / "checkpoints")  # the last complete state: the start, here
    assert newest is not None and str(newest) in info["message"] and read_checkpoint(newest)[1]["time"] == 0.0
    assert "Traceback" not in rest


@pytest.mark.skipif(shutil.which("mpirun") is None, reason="needs mpirun")
def test_sigusr1_stops_every_rank_in_the_middle_of_a_long_gas_step(tmp_path):
    """Under mpirun -n 2 both ranks agree on the stop between chunks of DEM sub-steps."""
    out = tmp_path / "run"
    proc, _ = start(MPIRUN + command(out, 0.01, *STIFF), "cfd-dem:", env=clean_env())
    time.sleep(2.0)
    code, waited, rest = stop(proc, signal.SIGUSR1, timeout=15)  # mpirun forwards it to both ranks
    assert code != 0 and waited < 15, rest
    info = status(out)
    assert info["state"] == "interrupted" and "stopped by SIGUSR1 in the middle of the gas step" in info["message"]
    assert latest_valid(out / "checkpoints") is not None


def test_sigterm_during_start_up_exits_with_a_status_and_a_message(tmp_path, capsys):
    """While the bed is being packed (a new bed file: seconds of DEM), the run's own handlers are not yet in place."""
    out = tmp_path / "run"
    bed = ["--set", f"particles.bed_file={tmp_path / 'new-bed.npz'}"]
    proc, _ = start(command(out, 0.01, *bed), "output folder:")
    code, waited, rest = stop(proc, signal.SIGTERM, timeout=10)
    assert code == 128 + signal.SIGTERM, rest
    assert "febed: stopped by SIGTERM during start-up" in rest and "Traceback" not in rest
    info = status(out)
    assert info["state"] == "interrupted" and "during start-up" in info["message"], info
    assert "stopped by SIGTERM during start-up" in (out / "febed.log").read_text()
    assert main(["status", str(out)]) == 0
    said = capsys.readouterr().out
    assert f"{out}: interrupted" in said and "during start-up" in said


def test_a_second_stop_signal_names_the_checkpoint_that_was_written(tmp_path, capsys, monkeypatch):
    from febed.runs.lifecycle import StopNow
    from febed.solver import CoupledSolver

    out = tmp_path / "run"
    fast = ["--set", "output.particle_interval=0.01", "--set", "output.field_interval=0.01"]
    assert main(command(out, 0.004, *fast)[3:]) == 0
    newest = list_checkpoints(out / "checkpoints")[-1]
    steps = []
    real = CoupledSolver.step

    def second_ctrl_c(self):  # a second Ctrl-C in the third gas step after the restart: stop at once
        steps.append(1)
        if len(steps) == 3:
            raise StopNow(signal.SIGINT)
        return real(self)

    monkeypatch.setattr(CoupledSolver, "step", second_ctrl_c)
    capsys.readouterr()
    assert main(command(out, 0.01, *fast, "--restart")[3:]) == 128 + signal.SIGINT
    err = capsys.readouterr().err
    assert "no checkpoint" not in err and f"the newest checkpoint is {newest} (t = 0.004 s)" in err, err
    info = status(out)
    assert info["state"] == "interrupted" and str(newest) in info["message"] and "--restart" in info["message"]
    assert read_checkpoint(newest)[1]["time"] == pytest.approx(0.004)


def test_a_real_double_ctrl_c_never_denies_a_checkpoint(tmp_path):
    """Two SIGINTs 10 ms apart, once checkpoints exist: whichever stop wins, the message is true."""
    out = tmp_path / "run"
    proc, _ = start(command(out, 0.5, "--set", "output.checkpoint_interval=0.002"), "checkpoint at")
    proc.send_signal(signal.SIGINT)
    time.sleep(0.01)
    code, _, rest = stop(proc, signal.SIGINT, timeout=30)
    assert code == 128 + signal.SIGINT, rest
    info = status(out)
    assert info["state"] == "interrupted" and "no checkpoint" not in rest, rest
    newest = latest_valid(out / "checkpoints")
    assert newest is not None
    if "second SIGINT" in info["message"]:
        assert f"the newest checkpoint is {newest}" in info["message"]


def test_an_unfinished_checkpoint_of_a_killed_run_is_removed_at_the_restart(tmp_path):
    out = tmp_path / "run"
    assert main(command(out, 0.004, "--set", "output.particle_interval=0.01")[3:]) == 0
    stale = out / "checkpoints" / ".checkpoint_000000040.npz.k3x9_q.tmp"  # as mkstemp names it, left by kill -9
    stale.write_bytes(b"PK\x03\x04 half an archive")
    assert main(command(out, 0.006, "--set", "output.particle_interval=0.01", "--restart")[3:]) == 0
    assert not stale.exists() and [p.name for p in (out / "checkpoints").iterdir() if p.name.startswith(".")] == []
    assert (
        f"removed {stale.name}: the unfinished checkpoint of a run killed while writing it"
        in (out / "febed.log").read_text()
    )


def test_an_error_after_start_up_reaches_the_log_and_febed_status(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(command(out, 0.01, "--set", "output.probe_heights=[5.0]")[3:]) == 2
    assert "febed: error: probe height 5.0 m lies outside the mesh" in capsys.readouterr().err
    info = status(out)
    assert info["state"] == "failed" and info["message"] == "probe height 5.0 m lies outside the mesh"
    assert "ERROR run failed: probe height 5.0 m lies outside the mesh" in (out / "febed.log").read_text()
    assert main(["status", str(out)]) == 0
    said = capsys.readouterr().out
    assert f"{out}: failed" in said and "message: probe height 5.0 m lies outside the mesh" in said


# 300 spheres poured into a 2 x 2 x 4 cm box
BOX = {
    "run": {"mode": "dem", "end_time": 0.02},
    "mesh": {"builtin": "box", "extent": [0.02, 0.02, 0.04], "size": 0.005},
    "particles": {"diameter": 2e-3, "density": 2500.0, "count": 300, "region": [0.0, 0.0, 0.0, 0.02, 0.02, 0.04]},
    "contact": {"stiffness": 1e4},
}


@pytest.mark.mpi
def test_a_long_dem_advance_stops_at_the_same_whole_step_on_every_rank(mpi_tmp_path, monkeypatch):
    """Asked every 10 steps (300 particles), a stop seen by rank 0 alone at the third question stops every rank
    after step 30; the DEM's clock counts exactly the steps made, and it goes on from there."""
    from febed.case import load_case
    from febed.dem import solver
    from febed.runs.dem import DEMRun
    from febed.runs.lifecycle import agree

    comm = MPI.COMM_WORLD
    case = load_case(data={**BOX, "output": {"directory": str(mpi_tmp_path)}})
    dem = DEMRun(case, mpi_tmp_path, logging.getLogger("febed.test"), comm).dem
    monkeypatch.setattr(solver, "STOP_CHECK_WORK", 10 * (300 // comm.size))  # a rank's share of 10 steps
    asked = []

    def stop_check():
        asked.append(dem.steps)
        return bool(agree(comm, signal.SIGTERM if comm.rank == 0 and len(asked) == 3 else 0)[0])

    dem.stop_check = stop_check
    dt = dem.dt
    t0 = dem.time
    with pytest.raises(solver.StopRequested, match="stopped after 30 DEM steps"):
        dem.advance(1000, dt)
    assert dem.steps == 30 and dem.time == pytest.approx(t0 + 30 * dt, rel=1e-12)
    assert comm.allgather(dem.steps) == [30] * comm.size and dem.count() == 300
    dem.stop_check = None
    dem.advance(20, dt)
    assert dem.steps == 50 and np.isfinite(dem.particles.pos[: dem.particles.n_owned]).all()
