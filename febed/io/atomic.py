"""Atomic file writes: the one way febed replaces a file, so that no reader and no crash sees a half-written one.

Every writer of a run's files (checkpoints, status.json, the resolved case, probes, particle files, meshes,
field files) goes through `atomic_path` or its shorthands `atomic_open`, `atomic_write_bytes` and `atomic_write_text`
(or `publish`, for a file that another library wrote under a temporary name febed chose):
the data go to a temporary file in the target's folder, named `.<name>.<random>.tmp`; once complete it is
flushed to disk (fsync), renamed over the target (`os.replace`, atomic on POSIX) and the folder is synced so
that the rename survives a power cut. A file with its final name is therefore always complete.

A write that fails (a full disk, no permission) removes its temporary file, leaves the target as it was, and
raises an OSError that names the target rather than the temporary file. A process killed between the two
steps leaves the temporary file behind: `remove_temporaries(folder, pattern)` removes those of a folder
(call it only while holding the run folder's lock, when no other process writes there).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

TMP_SUFFIX = ".tmp"


def temporary_glob(name_glob: str, suffix: str = TMP_SUFFIX) -> str:
    """Glob matching the temporary files of targets whose names match `name_glob` (e.g. "checkpoint_*.npz")."""
    return f".{name_glob}.*{suffix}"


def _naming(err: OSError, path: Path) -> OSError:
    """`err` naming `path` (the target) instead of a temporary file; errors without errno are kept as they are."""
    if err.errno is None:
        return err
    return OSError(err.errno, err.strerror, str(path))  # OSError picks the subclass (FileNotFoundError, ...)


def _fsync(path: Path) -> None:
    """Flush a closed file's data to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_folder(folder: Path) -> None:
    """Flush a folder's entries (a rename into it) to disk; file systems that cannot sync a folder are skipped."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # e.g. EINVAL: a file system without folder sync
    finally:
        os.close(fd)


@contextmanager
def atomic_path(path: str | os.PathLike, *, suffix: str = TMP_SUFFIX, sync: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside `path` for the caller to write (by name); on success it replaces `path`.

    For writers that take a file name (gmsh, for instance); `suffix` ends the temporary name (give the target's
    extension when the writer chooses the format by it, e.g. ".tmp.msh"). With `sync`, the temporary file is
    fsynced before the rename and the folder after it. On any error the temporary file is removed and an
    OSError is raised naming `path`.
    """
    path = Path(path)
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
        os.close(fd)
    except OSError as e:
        raise _naming(e, path) from None
    tmp = Path(name)
    try:
        yield tmp
        if sync:
            _fsync(tmp)
        os.replace(tmp, path)
    except BaseException as e:
        tmp.unlink(missing_ok=True)
        if isinstance(e, OSError):
            raise _naming(e, path) from None
        raise
    if sync:
        fsync_folder(path.parent)


@contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb", *, sync: bool = True, **kwargs) -> Iterator[IO]:
    """`open(path, mode, **kwargs)` of a temporary file that replaces `path` when the block ends without error.

    `mode` is a write mode ("w", "wb"); see `atomic_path` for what happens on success and on failure.
    """
    if not mode.startswith("w"):
        raise ValueError(f"mode: atomic_open writes a new file, so the mode must start with 'w', got {mode!r}")
    with atomic_path(path, sync=sync) as tmp, open(tmp, mode, **kwargs) as f:
        yield f
        f.flush()  # (the fsync, once the file is closed, is atomic_path's)


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, sync: bool = True) -> None:
    """Replace `path` by a file holding `data`, atomically (see `atomic_path`)."""
    with atomic_open(path, "wb", sync=sync) as f:
        f.write(data)


def atomic_write_text(path: str | os.PathLike, text: str, *, sync: bool = True, encoding: str = "utf-8") -> None:
    """Replace `path` by a file holding `text`, atomically (see `atomic_path`)."""
    with atomic_open(path, "w", sync=sync, encoding=encoding) as f:
        f.write(text)


def publish(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Give a complete file that a writer made under the temporary name `tmp` its final name `path`.

    For writers that choose their temporary name themselves and write through another process or library
    (HDF5 through DOLFINx, `febed.io.fields`): `tmp` is flushed to disk, renamed over `path` and the folder
    synced, as `atomic_path` does. An OSError names `path`.
    """
    tmp, path = Path(tmp), Path(path)
    try:
        _fsync(tmp)
        os.replace(tmp, path)
    except OSError as e:
        raise _naming(e, path) from None
    fsync_folder(path.parent)


def sync_close(f: IO) -> None:
    """Flush the open file `f` to the disk and close it (closed even if the flush fails)."""
    try:
        f.flush()
        os.fsync(f.fileno())
    finally:
        f.close()


def remove_temporaries(folder: str | os.PathLike, name_glob: str = "*", suffix: str = TMP_SUFFIX) -> list[Path]:
    """Remove the temporary files of writes into `folder` that never finished (a process killed while writing).

    `name_glob` selects the targets (e.g. "checkpoint_*.npz"). Call it only while no other process writes
    into the folder (the run folder's lock is held). Returns the files removed.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return []
    gone = []
    for p in sorted(folder.glob(temporary_glob(name_glob, suffix))):
        try:
            p.unlink()
            gone.append(p)
        except FileNotFoundError:
            pass
    return gone
