"""The `febed` command line: messages instead of tracebacks, output folders never clobbered."""

import json
import socket
import subprocess
import sys

import numpy as np
import pytest

from febed.case import load_case
from febed.cli import main
from febed.io.rundir import RESOLVED_CASE, OutputError, prepare_output, running_process, write_status
from febed.schema import BOUNDARY, SCHEMA

CASE = """
[run]
mode = "dem"
end_time = 0.01
[mesh]
builtin = "wang2d"
[particles]
count = 10
"""


@pytest.fixture
def case_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    p = tmp_path / "bed.toml"
    p.write_text(CASE)
    return p


def test_params_lists_every_parameter(capsys):
    assert main(["params"]) == 0
    out = capsys.readouterr().out
    for sec, params in SCHEMA.items():
        for key in params:
            assert f"{sec}.{key} = " in out
    for key in BOUNDARY:
        assert f"gas.boundary.<tag>.{key} = " in out
    assert main(["params", "nosuch"]) == 2


def test_check_ok_and_bad(case_file, capsys):
    assert main(["check", str(case_file)]) == 0
    assert "OK" in capsys.readouterr().out
    assert main(["check", str(case_file), "--set", "particles.densty=1"]) == 2
    err = capsys.readouterr().err
    assert "did you mean 'density'" in err and "Traceback" not in err


def test_check_reports_missing_mesh_tag(case_file, capsys):
    assert main(["check", str(case_file), "--set", "gas.boundary.distributor.type=wall"]) == 2
    err = capsys.readouterr().err
    assert "'distributor'" in err and "the mesh has: inlet, outlet, walls" in err


def test_output_folder_is_never_clobbered(case_file, tmp_path):
    case = load_case(case_file)
    out = prepare_output(case)
    assert (out / RESOLVED_CASE).is_file()
    assert load_case(out / RESOLVED_CASE).to_dict() == case.to_dict()  # the resolved case runs as is
    (out / "result.txt").write_text("precious")
    with pytest.raises(OutputError, match="--overwrite"):
        prepare_output(case)
    assert (out / "result.txt").read_text() == "precious"
    prepare_output(case, overwrite=True)
    assert not (out / "result.txt").exists()
    # a folder febed did not write is refused even with --overwrite
    user = tmp_path / "mine"
    user.mkdir()
    (user / "thesis.tex").write_text("x")
    other = load_case(case_file, [f"output.directory={user}"])
    with pytest.raises(OutputError, match="not written by febed"):
        prepare_output(other, overwrite=True)
    assert (user / "thesis.tex").exists()


@pytest.fixture
def other_febed_process():
    """A live process whose command line names febed (as a running `febed run` would)."""
    from _febed_process import sleeping_febed_process

    proc = sleeping_febed_process()
    yield proc
    proc.kill()
    proc.wait()


def test_a_run_still_going_is_neither_restarted_nor_cleared(case_file, other_febed_process, capsys):
    case = load_case(case_file)
    out = prepare_output(case)
    write_status(out, "running", 0.1, 1.0, 10)
    info = json.loads((out / "status.json").read_text())
    assert info["host"] == socket.gethostname() and info["pid"] > 0
    assert running_process(out) is None  # written by this very process
    info["pid"] = other_febed_process.pid
    (out / "status.json").write_text(json.dumps(info))
    assert running_process(out) == other_febed_process.pid
    assert main(["run", str(case_file), "--restart"]) == 2
    assert f"still going (process {other_febed_process.pid} on this machine)" in capsys.readouterr().err
    with pytest.raises(OutputError, match=f"still going \\(process {other_febed_process.pid}"):
        prepare_output(case, overwrite=True)
    assert (out / RESOLVED_CASE).is_file()
    for change in ({"host": "elsewhere"}, {"state": "interrupted"}, {"pid": 1}):  # another host, stopped, not febed
        (out / "status.json").write_text(json.dumps({**info, **change}))
        assert running_process(out) is None, change
    (out / "status.json").write_text(json.dumps(info))
    other_febed_process.kill()
    other_febed_process.wait()
    assert running_process(out) is None  # killed without a chance to update its status


def test_status_reports_state_liveness_progress_and_checkpoint(case_file, other_febed_process, capsys):
    from febed.io.checkpoint import write_checkpoint

    case = load_case(case_file)
    out = prepare_output(case)
    write_status(out, "running", 0.25, 1.0, 40)
    info = {**json.loads((out / "status.json").read_text()), "pid": other_febed_process.pid}
    (out / "status.json").write_text(json.dumps(info))
    (out / "febed.log").write_text(
        "2026-12-02 06:00:00,001 INFO febed: case x\n"
        "2026-12-02 06:00:10,002 INFO t = 0.25000 / 1 s  step 40  10 particles  2.00 min wall per simulated s  "
        "ETA 0h01m30s\n"
        "2026-12-02 06:00:11,003 INFO checkpoint at t = 0.25 s (gas step 40): x\n"
    )  # fmt: skip
    write_checkpoint(out / "checkpoints", {"a": np.zeros(2)}, {"step": 40, "time": 0.25}, keep=2)
    assert main(["status", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"{out}: running (process {other_febed_process.pid} on this machine)" in text
    assert "status.json: t = 0.25 / 1 s, step 40" in text
    assert "last progress line (2026-12-02 06:00:10): t = 0.25000 / 1 s  step 40" in text and "ETA 0h01m30s" in text
    assert "newest checkpoint: checkpoints/checkpoint_000000040.npz (t = 0.25 s)" in text
    (out / "status.json").write_text(json.dumps({**info, "pid": 1}))  # alive, but no febed command line
    main(["status", str(out)])
    assert "process 1 is alive but its command line does not name febed" in capsys.readouterr().out
    (out / "status.json").write_text(json.dumps(info))
    other_febed_process.kill()
    other_febed_process.wait()
    assert main(["status", str(out), str(out.parent)]) == 2  # the second is no run folder
    text = capsys.readouterr().out
    assert "its process is gone (killed?): continue it with --restart" in text
    assert f"{out.parent}: not a febed run folder" in text
    write_status(out, "failed", 0.3, 1.0, 45, "gas pressure p is not finite")
    main(["status", str(out)])
    assert "failed\n" in (text := capsys.readouterr().out) and "message: gas pressure p is not finite" in text


def test_unwritable_output_is_reported(case_file, tmp_path):
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    case = load_case(case_file, [f"output.directory={blocker}/sub"])
    with pytest.raises(OutputError, match="output folder"):
        prepare_output(case)


def test_mesh_command(tmp_path):
    out = tmp_path / "w.msh"
    assert main(["mesh", "wang2d", "-o", str(out)]) == 0
    assert out.stat().st_size > 0
    assert main(["mesh", "wang2d", "--cell", "hexahedron", "-o", str(out)]) == 2


def test_console_script_runs():
    res = subprocess.run([sys.executable, "-m", "febed.cli", "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "febed" in res.stdout


def test_ctrl_c_during_set_up_is_a_message_and_status_130(case_file, monkeypatch, capsys):
    """A Ctrl-C before the run's signal handlers are up (meshing, packing) or a second one: no traceback."""
    from febed import cli

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "cmd_check", interrupted)
    assert cli.main(["check", str(case_file)]) == 130
    assert capsys.readouterr().err == "febed: stopped by Ctrl-C\n"
