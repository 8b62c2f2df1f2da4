"""A full disk (or any output error) stops a run cleanly: one message naming the file and the error, status.json
"failed" with it, exit status 3, no traceback, the newest checkpoint complete and a restart that finishes.

The faults are injected into the writers of probes, fields (at DOLFINx's level: the bare RuntimeError of its
HDF5 writer), particles and checkpoints at a chosen call; where the machine lets root mount a small tmpfs, a
run also fills a real disk. All runs are the seed-000 2D bed of demos/wang2d for a hundredth of a second.
"""

import errno
import json
import os
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest

from febed.cli import main
from febed.io.checkpoint import latest_valid, list_checkpoints, read_checkpoint
from febed.io.probes import read_probes

ROOT = Path(__file__).resolve().parents[1]
CASE = ROOT / "demos" / "wang2d" / "wang2d.toml"
FAST = ["output.probe_interval=1e-3", "output.field_interval=0.005", "output.particle_interval=0.005",
        "output.checkpoint_interval=0.004", "output.keep_checkpoints=1"]  # fmt: skip
END = 0.012


def febed(out, *extra):
    """`febed run` of the wang2d case into `out` to t = END, in this process; returns the exit status."""
    sets = [a for s in [*FAST, f"output.directory={out}", f"run.end_time={END}"] for a in ("--set", s)]
    return main(["run", str(CASE), *sets, *extra])


def enospc(path=None):
    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), *([str(path)] if path else []))


def at_call(real, call, fault):
    """`real`, except that its `call`-th call (counted from 1) is `fault` instead."""
    calls = []

    def wrapped(*args, **kwargs):
        calls.append(1)
        return (fault if len(calls) == call else real)(*args, **kwargs)

    return wrapped


def probe_row(*args):  # a full disk as the probe file's buffer is flushed: an OSError without a file name
    raise enospc()


def hdf5(*args):  # what DOLFINx raises when HDF5 cannot write
    raise RuntimeError("Failed to write HDF5 local dataset into hyperslab.")


def particle_file(path, data):  # a full disk while writing a particle file
    raise enospc(path)


def partial_checkpoint(f, arrays):  # part of a checkpoint written, then the disk is full
    f.write(b"PK\x03\x04 part of an archive")
    raise enospc()


def where_probes():
    from febed.io.probes import ProbeFile

    return ProbeFile, "write", 1, probe_row, r"cannot write \S*/probes\.csv: \[Errno 28\] No space left on device"


def where_fields():
    import dolfinx.io

    # the calls write u, p, eps, alpha_p at t = 0, then at 0.005 s: the 5th is that second write's
    message = r"cannot write \S*/fields/000001\.h5: \[Errno 5\] HDF5 write failed"
    return dolfinx.io.XDMFFile, "write_function", 5, hdf5, message


def where_particles():
    from febed.io import particles

    # at t = 0 the .vtp and the .pvd, then the .vtp at 0.005 s
    return particles, "atomic_write_bytes", 3, particle_file, r"cannot write \S*/particles_000001\.vtp: \[Errno 28\]"


def where_checkpoints():
    from febed.io import checkpoint

    # checkpoints at 0.004 s, then at 0.008 s (gas step 40)
    return checkpoint, "_savez", 2, partial_checkpoint, r"cannot write checkpoint \S*_000000040\.npz: \[Errno 28\]"


@pytest.mark.parametrize(
    "where",
    [where_probes, where_fields, where_particles, where_checkpoints],
    ids=["first-probe-row", "later-field-write", "later-particle-write", "checkpoint-write"],
)
def test_an_output_error_stops_cleanly_and_the_run_continues_from_its_checkpoint(tmp_path, capsys, monkeypatch, where):
    import re

    owner, name, call, fault, message = where()
    monkeypatch.setattr(owner, name, at_call(getattr(owner, name), call, fault))
    out = tmp_path / "run"
    assert febed(out) == 3
    err = capsys.readouterr().err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    said = [line for line in err.splitlines() if line.startswith("febed: the run failed: ")]
    assert len(said) == 1 and re.search(message, said[0]), err
    info = json.loads((out / "status.json").read_text())
    assert info["state"] == "failed" and said[0] == "febed: the run failed: " + info["message"], (info, err)
    assert "run failed: " + info["message"] in (out / "febed.log").read_text()
    # the newest checkpoint is complete, named in the message, and nothing half-written is left
    ckpts = list_checkpoints(out / "checkpoints")
    assert ckpts and latest_valid(out / "checkpoints") == ckpts[-1]
    assert str(ckpts[-1]) in info["message"] and "then continue" in info["message"] and "--restart" in info["message"]
    _, meta = read_checkpoint(ckpts[-1])
    assert 0.0 <= meta["time"] < END
    assert not [p for p in (out / "checkpoints").iterdir() if p.name.endswith(".tmp")]
    monkeypatch.undo()
    assert febed(out, "--restart") == 0, capsys.readouterr().err
    assert json.loads((out / "status.json").read_text())["state"] == "finished"
    t = read_probes(out / "probes.csv")["time"]
    assert np.allclose(t, np.arange(len(t)) * 1e-3) and t[-1] == pytest.approx(END)  # no row lost or repeated
    pvd = (out / "particles" / "particles.pvd").read_text()
    files = re.findall(r'file="([^"]+)"', pvd)
    assert len(files) == 4 and all((out / "particles" / f).is_file() for f in files)  # 0, 0.005, 0.01, the end


MODES = {
    "dem": """
[run]
mode = "dem"
end_time = 0.012
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
particle_interval = 0.004
""",
    "gas": """
[run]
mode = "gas"
end_time = 0.012
gravity = 0.0
[mesh]
builtin = "wang2d"
[gas]
void_fraction = 0.6
[gas.boundary.inlet]
type = "inlet"
velocity = 0.3
[gas.boundary.walls]
type = "wall"
[gas.boundary.outlet]
type = "outlet"
[output]
field_interval = 0.004
""",
    "one-way": """
[run]
mode = "one-way"
end_time = 0.012
gravity = 0.0
[mesh]
builtin = "box"
extent = [0.02, 0.02, 0.02]
size = 0.005
[particles]
diameter = 5e-5
density = 2500.0
count = 1
region = [0.002, 0.009, 0.009, 0.004, 0.011, 0.011]
[contact]
stiffness = 1e-4
[coupling]
drag = "stokes"
[prescribed_gas]
flow = "uniform"
velocity = [0.1, 0.0, 0.0]
output_interval = 0.004
""",
}


class FullDiskFile:
    """A text file whose `fail_at`-th write raises ENOSPC (as the disk filling up under it would)."""

    def __init__(self, f, fail_at):
        self.f, self.fail_at, self.writes = f, fail_at, 0

    def write(self, text):
        self.writes += 1
        if self.writes == self.fail_at:
            raise enospc()
        return self.f.write(text)

    def __getattr__(self, name):
        return getattr(self.f, name)


@pytest.mark.parametrize("mode", ["dem", "gas", "one-way"])
def test_every_mode_stops_cleanly_on_an_output_error(tmp_path, capsys, monkeypatch, mode):
    """The third output (t = 0.008 s) of a pure-DEM, gas-only and one-way run meets a full disk."""
    import builtins
    import re

    import dolfinx.io

    from febed.io import particles
    from febed.runs import oneway

    case = tmp_path / "case.toml"
    case.write_text(MODES[mode])
    out = tmp_path / "run"
    run = ["run", str(case), "--set", f"output.directory={out}", "--set", "output.checkpoint_interval=0.004"]
    if mode == "dem":  # a .vtp and the .pvd per output
        monkeypatch.setattr(particles, "atomic_write_bytes", at_call(particles.atomic_write_bytes, 5, particle_file))
        name = r"particles/particles_000002\.vtp: \[Errno 28\] No space left on device"
    elif mode == "gas":  # u, p, eps per output
        write = dolfinx.io.XDMFFile.write_function
        monkeypatch.setattr(dolfinx.io.XDMFFile, "write_function", at_call(write, 7, hdf5))
        name = r"fields/000002\.h5: \[Errno 5\] HDF5 write failed"
    else:  # the header, then the rows of each output time
        monkeypatch.setattr(oneway, "open", lambda *a: FullDiskFile(builtins.open(*a), 4), raising=False)
        name = r"particles\.csv: \[Errno 28\] No space left on device"
    assert main(run) == 3
    err = capsys.readouterr().err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    info = json.loads((out / "status.json").read_text())
    assert info["state"] == "failed" and re.search(f"cannot write {out}/{name}", info["message"]), info
    assert f"febed: the run failed: {info['message']}" in err and info["message"] in (out / "febed.log").read_text()
    monkeypatch.undo()
    ckpts = list_checkpoints(out / "checkpoints")
    assert str(ckpts[-1]) in info["message"] and read_checkpoint(ckpts[-1])[1]["time"] == pytest.approx(0.008, abs=1e-4)
    assert main([*run, "--restart"]) == 0
    assert json.loads((out / "status.json").read_text())["state"] == "finished"
    if mode == "dem":  # the output that failed is written by the restart: t = 0, 0.004, 0.008, 0.012
        files = re.findall(r'file="([^"]+)"', (out / "particles" / "particles.pvd").read_text())
        assert len(files) == 4 and all((out / "particles" / f).is_file() for f in files)
    if mode == "one-way":  # the rows that failed are written by the restart, each output time once
        t = np.loadtxt(out / "particles.csv", delimiter=",", skiprows=1, ndmin=2)[:, 0]
        np.testing.assert_allclose(t, [0.0, 0.004, 0.008, 0.012], rtol=0, atol=1e-12)


@pytest.mark.mpi
def test_an_output_error_on_rank_0_alone_stops_every_rank(mpi_tmp_path, monkeypatch):
    """Probe rows and particle files are written by rank 0 alone: the ranks agree on its error."""
    from mpi4py import MPI

    from febed.case import load_case
    from febed.io.probes import ProbeFile
    from febed.io.rundir import get_logger
    from febed.runs.coupled import CoupledRun
    from febed.runs.lifecycle import OutputFailure, run_to_end

    comm = MPI.COMM_WORLD
    out = mpi_tmp_path / "run"
    case = load_case(CASE, [*FAST, f"output.directory={out}", "run.end_time=0.006"])
    write = ProbeFile.write

    def rank0_full(self, *args):
        if comm.rank == 0:
            raise enospc()
        return write(self, *args)

    monkeypatch.setattr(ProbeFile, "write", at_call(write, 4, rank0_full))  # the row at t = 0.003 s
    run = CoupledRun(case, out, get_logger(None, comm), comm)
    with pytest.raises(OutputFailure, match=r"cannot write \S*probes\.csv: \[Errno 28\] No space left on device"):
        run_to_end(run, 0.006)
    comm.barrier()
    info = json.loads((out / "status.json").read_text())
    assert info["state"] == "failed" and "the state at t = 0.003 s is saved in" in info["message"], info
    assert read_checkpoint(latest_valid(out / "checkpoints"))[1]["time"] == pytest.approx(0.003)


def test_a_failed_write_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    """write_checkpoint removes older checkpoints only once the new one is complete."""
    from febed.io import checkpoint as ck

    folder = tmp_path / "checkpoints"
    ck.write_checkpoint(folder, {"a": np.arange(3)}, {"step": 1, "time": 0.1}, keep=1)
    monkeypatch.setattr(ck, "_savez", partial_checkpoint)
    with pytest.raises(ck.CheckpointError, match=r"cannot write checkpoint .*_000000002\.npz: \[Errno 28\] No space"):
        ck.write_checkpoint(folder, {"a": np.arange(3)}, {"step": 2, "time": 0.2}, keep=1)
    assert [p.name for p in folder.iterdir()] == ["checkpoint_000000001.npz"]
    assert read_checkpoint(folder / "checkpoint_000000001.npz")[1]["time"] == 0.1


def test_status_json_is_written_even_when_the_disk_has_no_room_for_its_temporary_copy(tmp_path, monkeypatch):
    from febed.io import rundir

    rundir.write_status(tmp_path, "running", 0.5, 1.0, 10)

    def full(path, text):
        raise enospc(path)

    monkeypatch.setattr(rundir, "atomic_write_text", full)
    rundir.write_status(tmp_path, "failed", 0.5, 1.0, 10, "cannot write x: [Errno 28] No space left on device")
    info = json.loads((tmp_path / "status.json").read_text())
    assert info["state"] == "failed" and "No space" in info["message"]


def test_a_log_file_that_cannot_be_written_is_said_once_without_a_traceback(tmp_path, capsys):
    import logging

    from febed.io.rundir import get_logger

    class FullDisk:
        def write(self, text):
            raise enospc()

        def flush(self):
            pass

        def close(self):
            pass

    log = get_logger(tmp_path)
    (handler,) = [h for h in log.handlers if isinstance(h, logging.FileHandler)]
    handler.stream = FullDisk()
    for k in range(3):
        log.info(f"line {k}")
    said = f"febed: cannot write {tmp_path / 'febed.log'}: [Errno 28] No space left on device"
    assert capsys.readouterr().err == said + " (the console keeps the log)\n"


@pytest.fixture
def small_disk(tmp_path):
    """A 6 MB tmpfs (root only; skipped where mounting is not permitted), unmounted afterwards."""
    where = tmp_path / f"disk-{uuid.uuid4().hex[:6]}"
    where.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root and mount(8)")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=6m", "tmpfs", str(where)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode(errors='replace').strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def test_a_real_full_disk_stops_cleanly_and_keeps_the_last_checkpoint(small_disk, tmp_path):
    """On a 6 MB disk the particle files (0.6 MB each) and checkpoints (2 MB) fill it within 0.05 s; the run
    folder moved to a disk with room continues from its last checkpoint."""
    out = small_disk / "run"
    sets = ["output.probe_interval=1e-3", "output.field_interval=0.005", "output.particle_interval=0.005",
            "output.checkpoint_interval=0.004", "output.keep_checkpoints=1", "run.end_time=0.05"]  # fmt: skip
    cmd = [sys.executable, "-m", "febed.cli", "run", str(CASE), *[a for s in sets for a in ("--set", s)]]
    r = subprocess.run([*cmd, "--set", f"output.directory={out}"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 3, r.stdout[-2000:] + r.stderr[-3000:]
    assert "Traceback" not in r.stderr and "HDF5-DIAG" not in r.stderr and "Exception ignored" not in r.stderr
    said = [line for line in r.stderr.splitlines() if line.startswith("febed: the run failed: cannot write ")]
    assert len(said) == 1 and "[Errno 28] No space left on device" in said[0], r.stderr[-3000:]
    info = json.loads((out / "status.json").read_text())
    assert info["state"] == "failed" and said[0].endswith(info["message"]), info
    ckpts = list_checkpoints(out / "checkpoints")
    assert ckpts and latest_valid(out / "checkpoints") == ckpts[-1]  # the last good one survived, complete
    t = read_checkpoint(ckpts[-1])[1]["time"]
    assert 0 < t < 0.05 and (f"(t = {t:.6g} s)" in info["message"] or f"t = {t:.6g} s is saved" in info["message"])
    assert not [p for p in (out / "checkpoints").iterdir() if p.name.endswith(".tmp")]
    moved = tmp_path / "moved"
    shutil.copytree(out, moved)
    end = ["--set", f"run.end_time={t + 0.002:.6g}", "--set", f"output.directory={moved}", "--restart"]
    r = subprocess.run([*cmd, *end], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    assert json.loads((moved / "status.json").read_text())["state"] == "finished"
