"""Checkpoints: the whole state of a run in one file, written so that a crash never leaves it unusable.

A checkpoint is one uncompressed NumPy `.npz` archive `checkpoints/checkpoint_<step>.npz` holding named
arrays (gas nodal fields with their node coordinates, particle arrays, contact history keyed by global
ids, counters) and a JSON `meta` record (time, step, febed version, rank count, the resolved case). Rank 0
writes it to a temporary name in the same folder, flushes and fsyncs it, and renames it into place
(`febed.io.atomic`): a file with a final name is always complete, so a `kill -9` while writing leaves at worst
a stray temporary file (`.checkpoint_<step>.npz.*.tmp`, removed by `remove_temporaries` when the next run of
the folder starts) and the previous checkpoint still valid. Only the newest `keep` checkpoints are kept; older ones
are removed after the new one is in place, so a failed write (a full disk) never costs the last good one.

Arrays are gathered to rank 0 in a layout that does not depend on the rank count (particles by global id,
nodal fields with their coordinates), so a run can restart on another number of ranks.

The meta record also says what the checkpoint belongs to (`identity`, written by `write_checkpoint`): a
digest of its case's physics keys, its mesh (node count and bounding box of the gas nodes) and its particles
(held and left the domain); `febed.restart.checkpoint_differences` compares it with a case to continue.
"""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed.io import atomic
from febed.io.atomic import atomic_open
from febed.schema import physics_digest

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
            _atomic_npz(path, arrays, {**meta, "identity": identity(arrays, meta), "format": FORMAT})
            for old in list_checkpoints(folder)[:-keep]:
                old.unlink(missing_ok=True)
        except OSError as e:
            why = f"[Errno {e.errno}] {e.strerror}" if e.errno and e.strerror else str(e)
            err = f"cannot write checkpoint {path}: {why}"
    err = comm.bcast(err, root=0)
    if err:
        raise CheckpointError(err)
    return path


def _atomic_npz(path: Path, arrays: dict[str, np.ndarray], meta: dict) -> None:
    with atomic_open(path, "wb") as f:
        _savez(f, {"__meta__": np.array(json.dumps(meta)), **arrays})


def _savez(f, arrays: dict[str, np.ndarray]) -> None:
    """`np.savez(f, **arrays)`, with the archive closed even when a write fails (a full disk).

    np.savez leaves a failed archive open until the garbage collector closes it on a closed file, which
    prints an ignored exception; here the first error is the one raised.
    """
    with zipfile.ZipFile(f, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as z:
        for key, val in arrays.items():
            with z.open(key + ".npy", "w", force_zip64=True) as out:
                np.lib.format.write_array(out, np.asanyarray(val), allow_pickle=False)


def identity(arrays: dict[str, np.ndarray], meta: dict) -> dict:
    """What a checkpoint belongs to: physics digest of its case, its mesh and its particles (None: not known).

    `mesh` is the node count and bounding box [xmin, ymin, zmin, xmax, ymax, zmax] of the gas nodes (runs
    with gas); `particles` the particles held and `left` those removed from the domain so far (runs with
    particles).
    """
    out: dict = {"physics": physics_digest(meta["case"]) if meta.get("case") else None, "mesh": None}
    x = arrays.get("gas/x")
    if x is not None and len(x):
        x = np.asarray(x)
        out["mesh"] = {"nodes": int(x.shape[0]), "bounds": [float(v) for v in (*x.min(axis=0), *x.max(axis=0))]}
    if "dem/p_gid" in arrays:
        out["particles"] = int(np.asarray(arrays["dem/p_gid"]).shape[0])
        left = (meta.get("solver") or {}).get("left_outlet", (meta.get("run") or {}).get("left"))
        out["left"] = int(left) if left is not None else None
    return out


def remove_temporaries(folder: Path) -> list[Path]:
    """Remove the temporary files of checkpoint writes that never finished (a run killed while writing).

    Call it only while holding the run folder's lock (`febed.io.rundir.lock_output`): no other process then
    writes checkpoints there. Returns the files removed.
    """
    return atomic.remove_temporaries(folder, "checkpoint_*.npz")


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


def latest_valid(folder: Path, skipped: list[str] | None = None) -> Path | None:
    """The newest checkpoint in `folder` that reads completely, or None; `skipped` gets why newer ones did not."""
    for path in reversed(list_checkpoints(folder)):
        try:
            read_checkpoint(path)
        except CheckpointError as e:
            if skipped is not None:
                skipped.append(str(e))
            continue
        return path
    return None


def load_checkpoint(where: Path, comm=MPI.COMM_WORLD) -> tuple[Path, dict[str, np.ndarray], dict]:
    """Path, arrays and meta of checkpoint `where`, on every rank.

    `where` is a checkpoint file, a folder of checkpoints or a run folder (its `checkpoints/` folder): of a
    folder, the newest checkpoint that reads completely.
    """

    def read():
        path = resolve_checkpoint(Path(where))
        return (path, *read_checkpoint(path))

    return _on_rank0(read, comm)


def resolve_checkpoint(where: Path, skipped: list[str] | None = None) -> Path:
    """The checkpoint file `where` names: itself, or of a checkpoint or run folder its newest readable one.

    Raises CheckpointError if a folder holds none (this process only: rank 0 in a parallel run); `skipped`
    gets a message for each newer checkpoint that does not read.
    """
    where = Path(where)
    if where.is_dir() and not list_checkpoints(where) and (where / FOLDER).is_dir():
        where = where / FOLDER  # a run folder
    if not where.is_dir():
        return where
    path = latest_valid(where, skipped)
    if path is None:
        found = len(list_checkpoints(where))
        why = f"{found} checkpoint file(s), none readable" if found else "no checkpoint_<step>.npz files"
        raise CheckpointError(f"no valid checkpoint in {where} ({why})")
    return path


def checkpoint_identity(where: Path, comm=MPI.COMM_WORLD) -> tuple[Path, dict, dict, list[str]]:
    """Path, meta and `identity` of the checkpoint `where` names (see `load_checkpoint`), on every rank.

    Reads the whole file on rank 0 (a checkpoint whose arrays do not read is refused here, not mid-restart) and
    broadcasts only its meta record; a checkpoint written before identities were recorded gets one from its
    arrays. The fourth item says why newer checkpoints of a folder were skipped (each names its file).
    """

    def read():
        skipped: list[str] = []
        path = resolve_checkpoint(Path(where), skipped)
        arrays, meta = read_checkpoint(path)
        return path, meta, meta.get("identity") or identity(arrays, meta), skipped

    return _on_rank0(read, comm)


def _on_rank0(read, comm):
    """`read()` on rank 0 and its result on every rank; a CheckpointError it raises is raised on every rank."""
    result = None
    if comm.rank == 0:
        try:
            result = read()
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
