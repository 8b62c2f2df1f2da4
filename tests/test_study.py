"""`febed study`: members from parameter lists, resumption without redoing finished members, comparison."""

import json
import math
import shlex

import numpy as np
import pytest

from febed.post.cli import main as post_main
from febed.study import collect, job_lines, load_study, member_state, member_states, run_study

BASE = """
[run]
mode = "dem"
end_time = 0.01
[mesh]
builtin = "wang2d"
[particles]
count = 10
diameter = 1.5e-3
density = 1150.0
[contact]
friction_pp = 0.3
[output]
particle_interval = 0.005
"""

STUDY = """
[study]
base = "base.toml"
directory = "out"
combine = "{combine}"
set = ["run.end_time = 0.01"]
{extra}

[parameters]
"contact.friction_pp" = [0.1, 0.3]
"mesh.cell" = ["quadrilateral", "triangle"]
"""


@pytest.fixture
def study_file(tmp_path):
    (tmp_path / "base.toml").write_text(BASE)

    def make(combine="product", extra=""):
        p = tmp_path / "s.toml"
        p.write_text(STUDY.format(combine=combine, extra=extra))
        return p

    return make


def test_members_product_zip_and_validation(study_file, tmp_path):
    s = load_study(study_file())
    assert [m.name for m in s.members] == [
        "friction_pp-0.1_cell-quadrilateral",
        "friction_pp-0.1_cell-triangle",
        "friction_pp-0.3_cell-quadrilateral",
        "friction_pp-0.3_cell-triangle",
    ]
    assert s.members[1].overrides == ["contact.friction_pp=0.1", "mesh.cell=triangle"]
    assert s.members[1].directory == tmp_path / "out" / "friction_pp-0.1_cell-triangle"
    z = load_study(study_file("zip"))
    assert [m.values for m in z.members] == [
        {"contact.friction_pp": 0.1, "mesh.cell": "quadrilateral"},
        {"contact.friction_pp": 0.3, "mesh.cell": "triangle"},
    ]
    cmd = z.members[0].command(z, restart=True)
    assert cmd[-1] == "--restart" and "output.directory=" + str(z.members[0].directory) in cmd
    assert cmd[cmd.index("contact.friction_pp=0.1") - 1] == "--set"
    bad = tmp_path / "bad.toml"
    bad.write_text('[study]\nbase = "base.toml"\n[parameters]\n"contact.frictio_pp" = [0.1]\n')
    with pytest.raises(ValueError, match="friction_pp"):  # the case validation names the nearest key
        load_study(bad)
    bad.write_text('[study]\nbase = "base.toml"\ncombine = "zip"\n[parameters]\n"a.b" = [1]\n"c.d" = [1, 2]\n')
    with pytest.raises(ValueError, match="equal length"):
        load_study(bad)
    bad.write_text('[study]\nbase = "nothere.toml"\n')
    with pytest.raises(ValueError, match="not found"):
        load_study(bad)


class FakeRunner:
    """Plays `febed run`: writes the folder, probes up to the end time and status.json; can be interrupted."""

    def __init__(self, interrupt_at=None):
        self.calls = []
        self.interrupt_at = interrupt_at

    def __call__(self, cmd, member):
        self.calls.append((member.name, "--restart" in cmd))
        d = member.directory
        d.mkdir(parents=True, exist_ok=True)
        (d / "case.resolved.toml").write_text(BASE)
        start = 0.5 if "--restart" in cmd else 0.0
        fric = member.values["contact.friction_pp"]
        stop = 0.5 if member.name == self.interrupt_at else 1.0
        mode = "a" if "--restart" in cmd else "w"
        with open(d / "probes.csv", mode) as f:
            if mode == "w":
                f.write("time,particles,dp_bed,bed_height\n")
            for t in np.arange(start, stop + 1e-9, 0.1):
                if mode == "a" and t <= 0.5 + 1e-9:
                    continue
                f.write(f"{t!r},10,{100 * fric + 10 * t!r},{0.02 + fric * t!r}\n")
        state = "interrupted" if member.name == self.interrupt_at else "finished"
        (d / "status.json").write_text(json.dumps({"state": state, "time": stop, "end_time": 1.0}))
        if state == "interrupted":
            raise KeyboardInterrupt
        return 0


def test_resume_skips_finished_and_restarts_interrupted(study_file):
    s = load_study(study_file())
    names = [m.name for m in s.members]
    first = FakeRunner(interrupt_at=names[1])
    with pytest.raises(KeyboardInterrupt):
        run_study(s, runner=first, say=lambda _: None)
    assert first.calls == [(names[0], False), (names[1], False)]
    assert [st for _, st in member_states(s)] == ["finished", "interrupted", "new", "new"]
    lines = job_lines(s)
    assert len(lines) == 3 and "--restart" in shlex.split(lines[0]) and "--restart" not in lines[1]
    second = FakeRunner()
    assert run_study(s, runner=second, say=lambda _: None)
    assert second.calls == [(names[1], True), (names[2], False), (names[3], False)]
    third = FakeRunner()
    assert run_study(s, runner=third, say=lambda _: None) and third.calls == []
    manifest = json.loads((s.directory / "study.json").read_text())
    assert [m["state"] for m in manifest["members"]] == ["finished"] * 4
    # a failed member is skipped unless retried (from scratch)
    (s.members[2].directory / "status.json").write_text('{"state": "failed", "time": 0.3, "end_time": 1.0}')
    assert not run_study(s, runner=FakeRunner(), say=lambda _: None)
    retry = FakeRunner()
    assert run_study(s, runner=retry, retry_failed=True, say=lambda _: None)
    assert retry.calls == [(names[2], False)]
    # the comparison: means over the study's default window (last half of each member's series)
    table = collect(s, fields=False)
    row = {r["member"]: r for r in table.rows}[names[1]]  # the resumed member: its series is complete
    t = np.arange(0.5, 1.0 + 1e-9, 0.1)
    assert row["dp_bed_mean"] == pytest.approx(np.mean(100 * 0.1 + 10 * t), rel=1e-12)
    assert row["bed_height_mean"] == pytest.approx(np.mean(0.02 + 0.1 * t), rel=1e-12)
    w_a = (1150.0 - 1.2) * 9.81 * 10 * math.pi / 6 * 1.5e-3**3 / (0.09 * 1.5e-3)
    assert row["dp_bed_over_weight"] == pytest.approx(row["dp_bed_mean"] / w_a, rel=1e-9)
    assert table.csv.is_file() and any(f.name == "comparison_contact_friction_pp.png" for f in table.figures)


def test_a_member_still_running_elsewhere_is_skipped(study_file):
    import socket

    from _febed_process import sleeping_febed_process

    s = load_study(study_file())
    m = s.members[0]
    m.directory.mkdir(parents=True)
    (m.directory / "case.resolved.toml").write_text(BASE)
    proc = sleeping_febed_process()  # e.g. a member submitted as a separate job
    try:
        status = {"state": "running", "time": 0.5, "end_time": 1.0, "host": socket.gethostname(), "pid": proc.pid}
        (m.directory / "status.json").write_text(json.dumps(status))
        assert member_state(m) == "live"
        assert len(job_lines(s)) == 3  # not submitted again
        said = []
        runner = FakeRunner()
        run_study(s, runner=runner, say=said.append)
        assert m.name not in [name for name, _ in runner.calls]
        assert f"study {s.name}: {m.name} is still running (another process on this machine), skipped" in said
    finally:
        proc.kill()
        proc.wait()
    assert member_state(m) == "running"  # its process is gone: resumed by the next study run


def test_an_unfinished_run_without_checkpoints_starts_again(study_file, capsys, monkeypatch):
    from febed import restart

    s = load_study(study_file())
    m = s.members[0]
    m.directory.mkdir(parents=True)
    (m.directory / "case.resolved.toml").write_text(BASE.replace('mode = "dem"', 'mode = "one-way"'))
    (m.directory / "status.json").write_text('{"state": "interrupted", "time": 0.005, "end_time": 0.01}')
    cmd = shlex.split(job_lines(s)[0])
    assert "--restart" in cmd and "--overwrite" not in cmd  # every mode writes checkpoints: it continues
    monkeypatch.setattr(restart, "RESTARTABLE", ("cfd-dem", "dem", "gas"))  # a mode that could not continue
    cmd = shlex.split(job_lines(s)[0])
    assert "--overwrite" in cmd and "--restart" not in cmd
    assert post_main(["study", str(s.path), "--list"]) == 0  # --list shows the same command lines
    line = capsys.readouterr().out.splitlines()[0]
    assert line.startswith(m.name) and " interrupted " in line and line.endswith("--overwrite")
    (m.directory / "case.resolved.toml").write_text(BASE)  # a DEM run continues from its checkpoint
    cmd = shlex.split(job_lines(s)[0])
    assert "--restart" in cmd and "--overwrite" not in cmd


def test_mpirun_job_lines(study_file):
    s = load_study(study_file(extra='ranks = 2\nmpirun = "mpirun --oversubscribe -n {ranks}"'))
    lines = [shlex.split(line) for line in job_lines(s)]
    assert len(lines) == 4 and all(w[:4] == ["mpirun", "--oversubscribe", "-n", "2"] for w in lines)


def test_real_runs_and_fallback_state(study_file, capsys):
    """Two tiny DEM members through the real `febed run`; rerunning the study runs nothing new."""
    p = study_file("zip")
    assert post_main(["study", str(p), "--no-fields"]) == 0
    s = load_study(p)
    # these runs write no status.json (yet): the particle output reaching end_time says finished
    assert [member_state(m) for m in s.members] == ["finished", "finished"]
    for m in s.members:
        assert (m.directory / "particles" / "particles.pvd").is_file()
        assert (
            "friction_pp = " + str(m.values["contact.friction_pp"]) in (m.directory / "case.resolved.toml").read_text()
        )
    capsys.readouterr()
    assert post_main(["study", str(p), "--no-fields"]) == 0
    out = capsys.readouterr().out
    assert out.count("finished, skipped") == 2 and "running" not in out
