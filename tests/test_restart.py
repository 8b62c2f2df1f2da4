"""Runs that survive: exact restart, crash-safe checkpoints, failure detection, signals, progress.

All runs use the seed-000 2D bed of demos/wang2d (its committed packed bed) for a few hundredths of a
second: long enough for the bed to move, rebuild its neighbour lists and re-sort its particles.
"""

import io
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from febed.cli import main
from febed.io.checkpoint import (
    CheckpointError,
    latest_valid,
    list_checkpoints,
    load_checkpoint,
    read_checkpoint,
    write_checkpoint,
)
from febed.io.probes import read_probes
from febed.io.progress import Progress
from febed.restart import case_changes

ROOT = Path(__file__).resolve().parents[1]
CASE = ROOT / "demos" / "wang2d" / "wang2d.toml"
FAST = ["--set", "output.probe_interval=5e-4", "--set", "output.field_interval=0.01", "--set",
        "output.particle_interval=0.01"]  # fmt: skip


def febed(out, end, *extra):
    """`febed run` of the wang2d case into `out` up to `end` (s), in this process; returns the exit status."""
    return main(["run", str(CASE), "--set", f"output.directory={out}", "--set", f"run.end_time={end}", *FAST, *extra])


def febed_process(out, end, *extra):
    """The same as `febed` in a fresh process, as users run it.

    Exact comparisons need one process per run: the ML preconditioner keeps state between setups in one
    process, so two runs in the same process may differ at round-off (never two processes).
    """
    cmd = [sys.executable, "-m", "febed.cli", "run", str(CASE), "--set", f"output.directory={out}",
           "--set", f"run.end_time={end}", *FAST, *extra]  # fmt: skip
    return subprocess.run(cmd, capture_output=True, text=True).returncode


def final_state(out):
    return read_checkpoint(list_checkpoints(Path(out) / "checkpoints")[-1])


def assert_same_run(a, b, rtol=0.0):
    """Probe series (except wall clocks) and final particle/gas states of two run folders agree to rtol."""
    pa, pb = read_probes(Path(a) / "probes.csv"), read_probes(Path(b) / "probes.csv")
    assert pa.keys() == pb.keys()
    for k in pa:
        if not k.startswith("wall_"):
            np.testing.assert_allclose(pb[k], pa[k], rtol=rtol, atol=0, err_msg=k)
    (sa, ma), (sb, mb) = final_state(a), final_state(b)
    assert ma["time"] == mb["time"] and ma["step"] == mb["step"]
    order_a, order_b = np.argsort(sa["dem/p_gid"]), np.argsort(sb["dem/p_gid"])
    assert np.array_equal(sa["dem/p_gid"][order_a], sb["dem/p_gid"][order_b])
    for k in ("pos", "vel", "omega"):
        x, y = sa[f"dem/p_{k}"][order_a], sb[f"dem/p_{k}"][order_b]
        if rtol == 0:
            assert np.array_equal(x, y), k
        else:
            np.testing.assert_allclose(y, x, rtol=rtol, atol=rtol * np.abs(x).max(), err_msg=k)


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """The uninterrupted reference run to t = 0.03 s."""
    out = tmp_path_factory.mktemp("straight") / "run"
    assert febed_process(out, 0.03) == 0
    return out


def test_stop_and_restart_is_bit_identical(straight, tmp_path):
    out = tmp_path / "run"
    assert febed_process(out, 0.015) == 0
    assert json.loads((out / "status.json").read_text())["state"] == "finished"
    assert febed_process(out, 0.03, "--restart") == 0
    assert_same_run(straight, out)
    t = read_probes(out / "probes.csv")["time"]
    assert np.all(np.diff(t) > 0)  # neither duplicated nor missing rows
    assert (out / "fields.restart1.xdmf").is_file()  # the continued segment of the field series


def test_restart_refuses_changed_physics_and_reports_changes(straight, tmp_path, capsys):
    out = tmp_path / "run"
    assert febed(out, 0.01) == 0
    capsys.readouterr()
    assert febed(out, 0.02, "--restart", "--set", "contact.friction_pp=0.5") == 2
    err = capsys.readouterr().err
    assert "contact.friction_pp: 0.3 -> 0.5" in err and "cannot change midway" in err
    assert febed(out, 0.02, "--restart", "--set", "gas.cfl=0.1") == 0
    assert "gas.cfl: 0.2 -> 0.1" in capsys.readouterr().out
    assert febed(out, 0.02, "--restart") == 2  # already at its end time: nothing to do, said clearly
    assert "not before run.end_time" in capsys.readouterr().err
    assert febed(out, 0.03, "--restart", "--set", "contact.skin=0.25") == 0  # a performance setting: accepted
    assert "contact.skin: 0.1 -> 0.25" in capsys.readouterr().out


KILLER = """
import sys, numpy as np
from febed.io.checkpoint import write_checkpoint
big = {"x": np.ones((60_000_000,))}  # ~0.5 GB: long enough to be killed while writing
print("writing", flush=True)
write_checkpoint(sys.argv[1], big, {"step": 999999, "time": 1.0}, keep=5)
"""


def test_kill_during_checkpoint_write_keeps_previous_checkpoint(straight, tmp_path):
    out = tmp_path / "run"
    assert febed(out, 0.01) == 0
    ckpt = out / "checkpoints"
    before = latest_valid(ckpt)
    proc = subprocess.Popen([sys.executable, "-c", KILLER, str(ckpt)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "writing"
    deadline = time.time() + 60
    while not any(p.name.endswith(".tmp") for p in ckpt.iterdir()) and time.time() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)  # kill -9 mid-write
    proc.wait()
    assert any(p.name.endswith(".tmp") for p in ckpt.iterdir())  # it was caught mid-write
    assert latest_valid(ckpt) == before
    assert febed(out, 0.02, "--restart") == 0
    assert json.loads((out / "status.json").read_text())["state"] == "finished"


def test_checkpoint_files_are_rotated_and_unwritable_folder_is_reported(tmp_path):
    for step in range(5):
        write_checkpoint(tmp_path, {"a": np.arange(3)}, {"step": step, "time": 0.1 * step}, keep=2)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["checkpoint_000000003.npz", "checkpoint_000000004.npz"]
    arrays, meta = read_checkpoint(list_checkpoints(tmp_path)[-1])
    assert meta["time"] == 0.4 and np.array_equal(arrays["a"], np.arange(3))
    (tmp_path / "checkpoint_000000009.npz").write_bytes(b"PK\x03\x04 truncated")  # not a complete archive
    assert latest_valid(tmp_path).name == "checkpoint_000000004.npz"
    if os.geteuid() != 0:  # root writes anywhere; the message is tested where permissions bite
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        with pytest.raises(Exception, match="cannot write checkpoint"):
            write_checkpoint(ro, {"a": np.arange(3)}, {"step": 1, "time": 0.0}, keep=2)


def test_load_checkpoint_takes_a_file_a_checkpoint_folder_or_a_run_folder(tmp_path):
    run = tmp_path / "run"
    for step in (3, 7):
        write_checkpoint(run / "checkpoints", {"a": np.arange(step)}, {"step": step, "time": 0.1 * step}, keep=2)
    newest = run / "checkpoints" / "checkpoint_000000007.npz"
    for where in (newest, run / "checkpoints", run):
        path, arrays, meta = load_checkpoint(where)
        assert path == newest and meta["step"] == 7 and arrays["a"].size == 7
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match=r"no valid checkpoint in .*empty \(no checkpoint_<step>.npz files\)"):
        load_checkpoint(tmp_path / "empty")
    newest.write_bytes(b"PK\x03\x04 truncated")
    (run / "checkpoints" / "checkpoint_000000003.npz").write_bytes(b"")
    with pytest.raises(CheckpointError, match=r"2 checkpoint file\(s\), none readable"):
        load_checkpoint(run)


@pytest.mark.parametrize(
    "settings, message",
    [
        (["run.max_overlap=1e-5"], r"overlap reached .* above run.max_overlap"),
        (["coupling.void_fraction_floor=0.99", "run.max_clipped_fraction=0.0"], r"void fraction sits at its floor"),
        (['gas.petsc_options="-febed_pressure_weighted_ksp_max_it 1"'], r"pressure solve did not converge"),
        (["gas.boundary.walls.particles=false"], r"left the mesh other than through an outlet"),
    ],
    ids=["overlap", "clipped-void-fraction", "poisson", "escape"],
)
def test_failures_stop_with_message_checkpoint_and_exit_3(tmp_path, capsys, settings, message):
    from petsc4py import PETSc

    out = tmp_path / "run"
    sets = [a for s in settings for a in ("--set", s)]
    try:
        status = febed(out, 0.05, *sets)
    finally:
        PETSc.Options().delValue("-febed_pressure_weighted_ksp_max_it")
    assert status == 3
    err = capsys.readouterr().err
    assert "the run failed" in err and " s" in err
    info = json.loads((out / "status.json").read_text())
    assert info["state"] == "failed"
    import re

    assert re.search(message, info["message"]), info["message"]
    assert latest_valid(out / "checkpoints") is not None  # the last good state


@pytest.mark.mpi
@pytest.mark.parametrize(
    "what, value, message",
    [
        ("vel", np.nan, r"particle \d+ at \[.*nan.*\] m has a non-finite position during the DEM steps from t = 0.002"),
        ("vel", 1e12, r"particle 100 at .* moved .* from t = 0.002 s, more than 1000 times the size"),
        ("vel", 1e200, r"particle \d+ at .* moved beyond 1e154 m .* more than 1000 times the size"),  # overflow
    ],
    ids=["nan", "huge-velocity", "overflow"],
)
def test_blow_up_on_one_rank_stops_every_rank_with_the_last_good_state(mpi_tmp_path, what, value, message):
    """On 2 ranks only the rank holding particle 100 sees it go wrong; every rank stops with the same message
    (agreed at the DEM's next list rebuild) and the last good state is written as a checkpoint."""
    from mpi4py import MPI

    from febed.case import load_case
    from febed.io.rundir import get_logger
    from febed.runs.coupled import CoupledRun
    from febed.solver import RunFailure

    comm = MPI.COMM_WORLD
    out = mpi_tmp_path / "run"
    case = load_case(CASE, [f"output.directory={out}", *FAST[1::2]])
    run = CoupledRun(case, out, get_logger(None, comm), comm)
    run.advance_to(0.002)
    P = run.solver.dem.particles
    row = np.flatnonzero(P.gid[: P.n_owned] == 100)
    getattr(P, what)[row, 1] = value
    with pytest.raises(RunFailure, match="the particles blew up: " + message):
        run.advance_to(0.004)
    comm.barrier()
    assert json.loads((out / "status.json").read_text())["state"] == "failed"
    _, meta = read_checkpoint(latest_valid(out / "checkpoints"))
    assert meta["time"] <= 0.002 + 1e-12  # the last state that passed the checks
    run.close()


def test_sigterm_writes_checkpoint_and_the_run_completes(straight, tmp_path):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "febed.cli", "run", str(CASE), "--set", f"output.directory={out}",
           "--set", "run.end_time=0.03", *FAST]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    for line in proc.stdout:
        if line.startswith("cfd-dem:"):  # stepping has begun
            break
    time.sleep(0.3)
    proc.send_signal(signal.SIGTERM)
    rest = proc.stdout.read()
    assert proc.wait(timeout=120) == 128 + signal.SIGTERM, rest
    info = json.loads((out / "status.json").read_text())
    if info["state"] == "finished":
        pytest.skip("the run finished before the signal arrived (machine too fast for this test)")
    assert info["state"] == "interrupted" and "SIGTERM" in info["message"]
    assert febed_process(out, 0.03, "--restart") == 0
    assert_same_run(straight, out)


def test_progress_line_is_live_on_a_terminal_and_logged(tmp_path):
    class Tty(io.StringIO):
        def isatty(self):
            return True

    log = logging.getLogger("febed.test.progress")
    log.handlers.clear()
    fh = logging.FileHandler(tmp_path / "febed.log")
    log.addHandler(fh)
    tty, pipe = Tty(), io.StringIO()
    # env={}: not under an MPI launcher, whatever launched pytest (mpirun and pytest-xdist workers set its variables)
    Progress(log, 0, tty, env={}).show("t = 0.1 / 1 s")
    quiet = Progress(log, 0, pipe, env={})
    quiet.show("t = 0.2 / 1 s")
    fh.flush()
    assert tty.getvalue() == "\rt = 0.1 / 1 s" and pipe.getvalue() == ""
    assert "t = 0.1 / 1 s" in (tmp_path / "febed.log").read_text()
    assert "t = 0.2 / 1 s" in (tmp_path / "febed.log").read_text()


def test_keys_added_since_the_checkpoint_at_their_default_are_not_changes():
    old = "[gas]\ndensity = 1.2\n[run]\nend_time = 1.0\n"
    new = "[gas]\ndensity = 1.2\nbackflow = 1.0\n[run]\nend_time = 2.0\n"
    accepted, refused = case_changes(old, new)
    assert accepted == ["run.end_time: 1.0 -> 2.0"] and refused == []
    _, refused = case_changes(old, new.replace("backflow = 1.0", "backflow = 0.0").replace("1.2", "1.3"))
    assert refused == ["gas.density: 1.2 -> 1.3"]
    accepted, _ = case_changes(old, new.replace("backflow = 1.0", "backflow = 0.5"))
    assert "gas.backflow: '(unset)' -> 0.5" in accepted
    # the same for the keys of a boundary table (slip_normals arrived after runs were checkpointed)
    old_b = '[gas.boundary.walls]\ntype = "wall"\n'
    accepted, refused = case_changes(old_b, old_b + "slip_normals = []\n")
    assert accepted == refused == []
    _, refused = case_changes(old_b, old_b + 'slip_normals = ["y"]\n')
    assert refused == ["gas.boundary.walls.slip_normals: '(unset)' -> ['y']"]
