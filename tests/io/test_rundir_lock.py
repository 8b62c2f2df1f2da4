"""One run owns its folder: the lock `.febed.lock` refuses a second run, `--overwrite` and `--restart` while held.

The holder of a lock in these tests is another process (a lock is re-entrant within its own process). Its
lock is dropped by the kernel when it dies, so the lock file it leaves is stale and is taken over.
"""

import json
import shutil
import signal
import socket
import subprocess
import sys
import time

from mpi4py import MPI

import pytest
from _febed_process import MPIRUN, clean_env

from febed.case import load_case
from febed.cli import main
from febed.io.rundir import (
    LOCK_FILE,
    RESOLVED_CASE,
    OutputError,
    held_lock,
    lock_output,
    prepare_output,
    release_output,
)

CASE = """
[run]
mode = "dem"
end_time = 0.001
[mesh]
builtin = "wang2d"
[particles]
count = 3
"""

HOLDER = """
import sys, time
from febed.io.rundir import lock_output
lock_output(sys.argv[1])
print("locked", flush=True)
time.sleep(120)
"""


@pytest.fixture
def case_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    p = tmp_path / "bed.toml"
    p.write_text(CASE)
    return p


def start_holder(folder):
    """Another process holding the lock of `folder` (it has written its record once it says "locked")."""
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(folder)], stdout=subprocess.PIPE, text=True, env=clean_env()
    )
    assert proc.stdout.readline().strip() == "locked"
    return proc


def stop(proc):
    proc.kill()
    proc.wait()


def test_a_held_lock_refuses_a_second_run_overwrite_and_restart(case_file, capsys):
    case = load_case(case_file)
    out = prepare_output(case)
    release_output(out)
    (out / "result.txt").write_text("precious")
    holder = start_holder(out)
    try:
        in_use = f"output folder {out} is in use by another febed run (process {holder.pid} on this machine"
        with pytest.raises(OutputError, match=r"is in use by another febed run \(process " + str(holder.pid)):
            prepare_output(case, overwrite=True)
        for extra in ([], ["--overwrite"], ["--restart"]):
            assert main(["run", str(case_file), *extra]) == 2, extra
            err = capsys.readouterr().err
            assert in_use in err and f"kill -USR1 {holder.pid}" in err and "Traceback" not in err, (extra, err)
            assert len(err.strip().splitlines()) == 1
            assert (out / "result.txt").read_text() == "precious" and (out / RESOLVED_CASE).is_file()
            assert held_lock(out) is None
        assert json.loads((out / LOCK_FILE).read_text())["pid"] == holder.pid  # the holder's record is kept
    finally:
        stop(holder)
    # killed: the kernel dropped its lock; the file it left is stale and is taken over, with a note
    assert (out / LOCK_FILE).is_file()
    prepare_output(case, overwrite=True)
    lock = held_lock(out)
    assert lock is not None and f"stale lock of output folder {out} left by process {holder.pid}" in lock.note
    assert not (out / "result.txt").exists()
    release_output(out)
    assert not (out / LOCK_FILE).exists() and held_lock(out) is None


def test_a_stale_lock_file_is_taken_over_with_a_logged_note(case_file):
    case = load_case(case_file)
    out = case.output_dir()
    out.mkdir(parents=True)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # a process id that is gone
    started = "2000-01-01 00:00:00"
    (out / LOCK_FILE).write_text(json.dumps({"host": socket.gethostname(), "pid": dead.pid, "started": started}))
    assert main(["run", str(case_file), "--overwrite"]) == 0
    log = (out / "febed.log").read_text()
    assert f"took over the stale lock of output folder {out} left by process {dead.pid} on this machine" in log
    assert not (out / LOCK_FILE).exists()  # released at the end of the run
    assert json.loads((out / "status.json").read_text())["state"] == "finished"


@pytest.mark.parametrize(
    "error, status",
    [(KeyboardInterrupt(), 130), ("interrupted", 128 + signal.SIGTERM), (ValueError("refused value"), 2)],
)
def test_the_lock_is_released_however_the_run_ends(case_file, monkeypatch, error, status):
    from febed.runs import dem as driver
    from febed.runs.lifecycle import Interrupted

    if error == "interrupted":
        error = Interrupted(signal.SIGTERM, "interrupted by SIGTERM")

    def stopped(case, outdir, log, restart=None):
        assert (outdir / LOCK_FILE).is_file() and held_lock(outdir) is not None
        raise error

    monkeypatch.setattr(driver, "run", stopped)
    assert main(["run", str(case_file)]) == status
    out = load_case(case_file).output_dir()
    assert (out / RESOLVED_CASE).is_file() and not (out / LOCK_FILE).exists() and held_lock(out) is None
    monkeypatch.undo()
    assert main(["run", str(case_file), "--overwrite"]) == 0  # the next run is not refused
    assert not (out / LOCK_FILE).exists()


def test_a_script_using_the_python_api_holds_the_lock_until_it_exits(case_file):
    script = "import sys; from febed.case import load_case; from febed.io.rundir import prepare_output\n"
    script += "out = prepare_output(load_case(sys.argv[1]))\nprint(sorted(p.name for p in out.iterdir()))"
    r = subprocess.run([sys.executable, "-c", script, str(case_file)], capture_output=True, text=True, env=clean_env())
    assert r.returncode == 0 and LOCK_FILE in r.stdout, r.stderr
    out = load_case(case_file).output_dir()
    assert (out / RESOLVED_CASE).is_file() and not (out / LOCK_FILE).exists()


def test_a_folder_febed_did_not_write_gets_no_lock_file(case_file, tmp_path):
    user = tmp_path / "mine"
    user.mkdir()
    (user / "thesis.tex").write_text("x")
    case = load_case(case_file, [f"output.directory={user}"])
    for overwrite in (False, True):
        with pytest.raises(OutputError):
            prepare_output(case, overwrite=overwrite)
        assert sorted(p.name for p in user.iterdir()) == ["thesis.tex"]


# ---------------------------------------------------------------------------------------------- the race
WORKER = """
import contextlib, io, json, sys
from febed.cli import main
case, root = sys.argv[1], sys.argv[2]
print("ready", flush=True)
for line in sys.stdin:
    trial = int(line)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(["run", case, "--set", f"output.directory={root}/trial{trial}"])
    print(json.dumps({"rc": rc, "err": err.getvalue()}), flush=True)
"""


def check_trial(folder, results):
    """Exactly one of two runs started together on `folder` ran; the other was refused with a message."""
    ran = [r for r in results if r["rc"] == 0]
    refused = [r for r in results if r["rc"] == 2]
    assert len(ran) == 1 and len(refused) == 1, results
    msg = refused[0]["err"]
    assert f"output folder {folder} " in msg and "Traceback" not in msg, msg
    status = json.loads((folder / "status.json").read_text())
    assert status["state"] == "finished" and not (folder / LOCK_FILE).exists()
    if "is in use by another febed run" in msg:
        assert f"(process {status['pid']} on this machine" in msg, msg  # names the run that holds it
        return "in use"
    assert "already exists and is not empty" in msg, msg  # the winner had already finished
    return "not empty"


def test_two_runs_started_together_on_one_folder_exactly_one_runs(case_file, tmp_path):
    """20 times, two `febed run` (in two processes that have imported febed) told to start at the same moment."""
    root = tmp_path / "race"
    workers = [
        subprocess.Popen(
            [sys.executable, "-c", WORKER, str(case_file), str(root)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env=clean_env(),
        )
        for _ in range(2)
    ]
    try:
        for w in workers:
            assert w.stdout.readline().strip() == "ready"
        outcomes = []
        for trial in range(20):
            for w in workers:
                w.stdin.write(f"{trial}\n")
            for w in workers:
                w.stdin.flush()
            results = [json.loads(w.stdout.readline()) for w in workers]
            outcomes.append(check_trial(root / f"trial{trial}", results))
        assert "in use" in outcomes  # the lock decided (not only the finished winner's files)
    finally:
        for w in workers:
            w.stdin.close()
            w.wait(timeout=60)


@pytest.mark.slow
def test_two_febed_processes_started_together_exactly_one_runs(case_file, tmp_path):
    """20 times, two fresh `febed run` processes started at the same moment on one folder."""
    outcomes = []
    for trial in range(20):
        folder = tmp_path / f"trial{trial}"
        cmd = [sys.executable, "-m", "febed.cli", "run", str(case_file), "--set", f"output.directory={folder}"]
        procs = [
            subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=clean_env())
            for _ in range(2)
        ]
        results = [{"rc": p.wait(timeout=300), "err": p.stderr.read()} for p in procs]
        outcomes.append(check_trial(folder, results))
    assert "in use" in outcomes


# ------------------------------------------------------------------------------------------------- MPI
@pytest.mark.mpi
def test_rank_0_holds_the_lock_and_every_rank_is_refused_together(mpi_tmp_path):
    comm = MPI.COMM_WORLD
    folder = mpi_tmp_path / "run"
    lock = lock_output(folder)
    assert (lock is not None) == (comm.rank == 0) and (held_lock(folder) is not None) == (comm.rank == 0)
    assert lock_output(folder) is lock  # re-entrant
    release_output(folder)
    comm.barrier()
    holder = start_holder(folder) if comm.rank == 0 else None
    pid = comm.bcast(holder.pid if holder else None, root=0)
    try:
        with pytest.raises(OutputError, match=f"in use by another febed run \\(process {pid} on this machine"):
            lock_output(folder)
    finally:
        if holder:
            stop(holder)
    comm.barrier()
    lock = lock_output(folder)
    if comm.rank == 0:
        assert f"left by process {pid}" in lock.note
    release_output(folder)
    comm.barrier()
    assert not (folder / LOCK_FILE).exists()


@pytest.mark.skipif(shutil.which("mpirun") is None, reason="needs mpirun")
def test_a_refused_run_under_mpirun_exits_on_every_rank_with_one_message(case_file):
    if MPI.COMM_WORLD.size > 1:
        pytest.skip("starts its own mpirun")
    out = load_case(case_file).output_dir()
    holder = start_holder(out)
    try:
        t0 = time.monotonic()
        r = subprocess.run(
            [*MPIRUN, sys.executable, "-m", "febed.cli", "run", str(case_file), "--overwrite"],
            capture_output=True,
            text=True,
            timeout=300,
            env=clean_env(),
        )
        assert r.returncode == 2, r.stdout + r.stderr
        assert r.stderr.count(f"is in use by another febed run (process {holder.pid}") == 1, r.stderr
        assert "Traceback" not in r.stderr and time.monotonic() - t0 < 120
    finally:
        stop(holder)
