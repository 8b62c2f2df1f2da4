"""febed.io.atomic: a file with its final name is always complete; failures leave the old file and no temporary."""

import errno
import os
from pathlib import Path

import pytest

from febed.io import atomic, checkpoint, fields, particles, probes, rundir
from febed.io.atomic import atomic_open, atomic_path, atomic_write_bytes, atomic_write_text, publish, remove_temporaries


def test_a_write_replaces_the_file_and_leaves_nothing_else(tmp_path):
    target = tmp_path / "status.json"
    target.write_text("old")
    atomic_write_text(target, "new ✓\n")
    assert target.read_text(encoding="utf-8") == "new ✓\n"
    atomic_write_bytes(target, b"\x00\x01")
    assert target.read_bytes() == b"\x00\x01"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["status.json"]


def test_the_data_and_the_rename_are_synced_to_disk(tmp_path, monkeypatch):
    synced = []
    real = os.fsync

    def fsync(fd):
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        real(fd)

    monkeypatch.setattr(atomic.os, "fsync", fsync)
    atomic_write_text(tmp_path / "a.txt", "x")
    assert len(synced) == 2
    assert synced[0].startswith(str(tmp_path / ".a.txt.")) and synced[0].endswith(".tmp")  # the data, before
    assert synced[1] == str(tmp_path)  # the folder, after the rename
    synced.clear()
    atomic_write_text(tmp_path / "b.txt", "x", sync=False)
    assert synced == []


def test_a_failed_write_keeps_the_old_file_removes_its_temporary_and_names_the_target(tmp_path):
    target = tmp_path / "probes.csv"
    target.write_text("time\n0.0\n")
    with pytest.raises(OSError) as info, atomic_open(target, "w") as f:
        f.write("time\n")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), f.name)
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(target)
    assert target.read_text() == "time\n0.0\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["probes.csv"]


def test_other_errors_pass_through_unchanged(tmp_path):
    target = tmp_path / "x.bin"
    with pytest.raises(KeyError, match="boom"), atomic_open(target) as f:
        f.write(b"part")
        raise KeyError("boom")
    assert list(tmp_path.iterdir()) == []


def test_a_missing_folder_is_reported_on_the_target(tmp_path):
    target = tmp_path / "no" / "such" / "file.txt"
    with pytest.raises(FileNotFoundError) as info:
        atomic_write_text(target, "x")
    assert info.value.filename == str(target)


def test_a_writer_taking_a_file_name_gets_a_temporary_path_with_the_extension_it_needs(tmp_path):
    target = tmp_path / "mesh.msh"
    with atomic_path(target, suffix=".tmp.msh") as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".mesh.msh.") and tmp.name.endswith(".tmp.msh")
        assert not target.exists()
        tmp.write_text("$MeshFormat")
    assert target.read_text() == "$MeshFormat" and not tmp.exists()


def test_only_writing_modes_are_accepted(tmp_path):
    with pytest.raises(ValueError, match="mode.*'a'"), atomic_open(tmp_path / "x", "a"):
        pass


def test_stale_temporaries_are_removed_by_pattern(tmp_path):
    stale = tmp_path / ".checkpoint_000000040.npz.k3x9_q.tmp"  # as a write killed midway leaves it
    other = tmp_path / ".status.json.a1b2c3.tmp"
    keep = [tmp_path / "checkpoint_000000020.npz", tmp_path / "notes.tmp", tmp_path / ".checkpoint_1.npz"]
    for p in [stale, other, *keep]:
        p.write_text("x")
    assert remove_temporaries(tmp_path, "checkpoint_*.npz") == [stale]
    assert checkpoint.remove_temporaries(tmp_path) == []
    assert remove_temporaries(tmp_path) == [other]
    assert sorted(tmp_path.iterdir()) == sorted(keep)
    assert remove_temporaries(tmp_path / "missing") == []


def test_every_writer_goes_through_this_module():
    """The run's writers use these helpers (no private copy of the temporary-file dance)."""
    assert checkpoint.atomic_open is atomic_open and probes.atomic_open is atomic_open
    assert particles.atomic_write_bytes is atomic_write_bytes and rundir.atomic_write_text is atomic_write_text
    assert fields.publish is publish
    package = Path(checkpoint.__file__).resolve().parents[1]
    for path in package.rglob("*.py"):  # every febed module but this one
        if path.name != "atomic.py":
            source = path.read_text()
            assert "os.replace" not in source and "mkstemp" not in source, path


def test_publish_renames_a_finished_file_and_names_the_target_on_failure(tmp_path):
    tmp, target = tmp_path / ".x.tmp.h5", tmp_path / "x.h5"
    tmp.write_bytes(b"data")
    target.write_bytes(b"old")
    publish(tmp, target)
    assert target.read_bytes() == b"data" and not tmp.exists()
    with pytest.raises(FileNotFoundError) as info:
        publish(tmp, target)  # nothing to publish
    assert info.value.filename == str(target) and target.read_bytes() == b"data"
