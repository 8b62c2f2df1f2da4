"""Checkpoints: the whole state of a run in one file, written so that a crash never leaves it unusable.

A checkpoint is one uncompressed NumPy `.npz` archive `checkpoints/checkpoint_<step>.npz` holding named
arrays (gas nodal fields with their node coordinates, particle arrays, contact history keyed by global
ids, counters) and a JSON `meta` record (time, step, febed version, rank count, the resolved case). Rank 0
writes it to a temporary name in the same folder, flushes and fsyncs it, and renames it into place: a
file with a final name is always complete, so a `kill -9` while writing leaves at worst a stray temporary
file and the previous checkpoint still valid. Only the newest `keep` checkpoints are kept; older ones are
removed after the new one is in place.

Arrays are gathered to rank 0 in a layout that does not depend on the rank count (particles by global id,
nodal fields with their coordinates), so a run can restart on another number of ranks.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
import zipfile
from pathlib import Path

from mpi4py import MPI

import numpy as np

FORMAT = "febed-checkpoint-1"
FOLDER = "checkpoints"
_NAME = re.compile(r"^checkpoint_(\d{9})\.npz$")


class CheckpointError(RuntimeError):
    """A checkpoint cannot be written or read (the message names the file and the reason)."""


def checkpoint_name(step: int) -> str:
    """File name of the checkpoint after gas step `step`."""
    return f"checkpoint_{step:09d}.npz"


def write_checkpoint(folder: Path, arrays: dict[str, np.ndarray], meta: dict, keep: int, comm=MPI.COMM_WORLD) -> Path:
    """Write `arrays` (already gathered on rank 0) and `meta` atomically; keep the newest `keep` (collective).

    Raises CheckpointError on every rank if rank 0 cannot write (full disk, permissions): the previous
    checkpoints stay untouched.
    """
    folder = Path(folder)
    path = folder / checkpoint_name(int(meta["step"]))
    err = None
    if comm.rank == 0:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            _atomic_npz(path, arrays, {**meta, "format": FORMAT})
            for old in list_checkpoints(folder)[:-keep]:
                old.unlink(missing_ok=True)
        except OSError as e:
            err = f"cannot write checkpoint {path}: {e.strerror or e} (check free disk space and permissions)"
    err = comm.bcast(err, root=0)
    if err:
        raise CheckpointError(err)
    return path


def _atomic_npz(path: Path, arrays: dict[str, np.ndarray], meta: dict) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, __meta__=np.array(json.dumps(meta)), **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def list_checkpoints(folder: Path) -> list[Path]:
    """Checkpoint files in `folder`, oldest first (by step)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if _NAME.match(p.name))


def read_checkpoint(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    """Arrays and meta of one checkpoint; CheckpointError if it is not a complete febed checkpoint."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise CheckpointError(f"{path} is not a readable checkpoint ({e})") from None
    if "__meta__" not in arrays:
        raise CheckpointError(f"{path} is not a febed checkpoint (no meta record)")
    meta = json.loads(str(arrays.pop("__meta__")))
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"{path}: checkpoint format {meta.get('format')!r}, this febed reads {FORMAT!r}")
    return arrays, meta


def read_meta(path: Path) -> dict:
    """The meta record of one checkpoint alone (its arrays are not read); CheckpointError if there is none."""
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["__meta__"]))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as e:
        raise CheckpointError(f"{path} is not a readable checkpoint ({e})") from None
    return meta


def latest_valid(folder: Path) -> Path | None:
    """The newest checkpoint in `folder` that reads completely, or None."""
    for path in reversed(list_checkpoints(folder)):
        try:
            read_checkpoint(path)
        except CheckpointError:
            continue
        return path
    return None


def load_checkpoint(where: Path, comm=MPI.COMM_WORLD) -> tuple[Path, dict[str, np.ndarray], dict]:
    """Path, arrays and meta of checkpoint `where`, on every rank.

    `where` is a checkpoint file, a folder of checkpoints or a run folder (its `checkpoints/` folder): of a
    folder, the newest checkpoint that reads completely.
    """
    where = Path(where)
    result = None
    if comm.rank == 0:
        if where.is_dir() and not list_checkpoints(where) and (where / FOLDER).is_dir():
            where = where / FOLDER  # a run folder
        path = latest_valid(where) if where.is_dir() else where
        if path is None:
            found = len(list_checkpoints(where))
            why = f"{found} checkpoint file(s), none readable" if found else "no checkpoint_<step>.npz files"
            result = CheckpointError(f"no valid checkpoint in {where} ({why})")
        else:
            try:
                result = (path, *read_checkpoint(path))
            except CheckpointError as e:
                result = e
    result = comm.bcast(result, root=0)
    if isinstance(result, CheckpointError):
        raise result
    return result


# ---------------------------------------------------------------------------------- distributed arrays
def gather_rows(arrays: dict[str, np.ndarray], comm=MPI.COMM_WORLD) -> dict[str, np.ndarray]:
    """Concatenate each rank's rows of every array on rank 0 (other ranks get an empty dict)."""
    if comm.size == 1:
        return {k: np.ascontiguousarray(v) for k, v in arrays.items()}
    out = {}
    for k, v in arrays.items():
        parts = comm.gather(np.ascontiguousarray(v), root=0)
        if comm.rank == 0:
            out[k] = np.concatenate(parts, axis=0)
    return out


def match_nodes(saved_x: np.ndarray, x: np.ndarray, h: float) -> np.ndarray:
    """Index into `saved_x` (m, 3) of each point of `x` (n, 3): the same node, within 1e-6 h.

    Raises CheckpointError naming the first node without a match (the mesh differs from the checkpoint's).
    """
    from scipy.spatial import cKDTree

    if x.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    dist, idx = cKDTree(saved_x).query(x)
    bad = np.flatnonzero(dist > 1e-6 * h)
    if bad.size:
        k = int(bad[0])
        raise CheckpointError(
            f"node at {x[k].tolist()} m has no counterpart in the checkpoint (nearest {dist[k]:.3g} m away): "
            "the mesh differs from the one the checkpoint was written with"
        )
    return idx.astype(np.int64)
