"""The run's output folder and its log: created safely, never overwriting a user's files by surprise.

Layout of an output folder (`[output] directory`, default `./runs/<case name>/`):

    case.resolved.toml   the case with every default filled in (what actually ran)
    febed.log            the log (same lines as the console, with time stamps)
    status.json          running / finished / failed / interrupted, and the simulated time reached
    mesh/                built-in meshes generated for this run (.msh)
    ...                  fields, particles, probes, checkpoints (written by their modules)

A folder is recognised as febed's by its `case.resolved.toml`. `febed run` refuses an existing non-empty
folder unless `--overwrite`, and even then refuses to clear a folder that is not febed's.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
import tempfile
from pathlib import Path

from mpi4py import MPI

RESOLVED_CASE = "case.resolved.toml"
LOG_FILE = "febed.log"
STATUS_FILE = "status.json"


class OutputError(RuntimeError):
    """The output folder cannot be used (exists, not writable, ...)."""


def atomic_write_text(path: Path, text: str) -> None:
    """Write `text` to `path` through a temporary file + fsync + rename: never a half-written file."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_status(outdir: Path, state: str, time: float, end_time: float, step: int = 0, message: str = "",
                 comm=MPI.COMM_WORLD) -> None:  # fmt: skip
    """Write `status.json` (rank 0, atomically): running / finished / failed / interrupted, time reached."""
    if comm.rank != 0:
        return
    import json

    info = {"state": state, "time": float(time), "step": int(step), "end_time": float(end_time)}
    if message:
        info["message"] = message
    atomic_write_text(Path(outdir) / STATUS_FILE, json.dumps(info, indent=1) + "\n")


def prepare_output(case, overwrite: bool = False, comm=MPI.COMM_WORLD) -> Path:
    """Create the case's output folder (or clear it, with `overwrite`) and write the resolved case into it.

    Tests that the folder is writable first. Collective: every rank gets the same path or OutputError.
    """
    out = case.output_dir()
    err = None
    if comm.rank == 0:
        try:
            _prepare(out, overwrite)
            atomic_write_text(out / RESOLVED_CASE, _header(case) + case.to_toml())
        except OutputError as e:
            err = str(e)
        except OSError as e:
            err = f"output folder {out}: {e.strerror or e} (check the path, permissions and free disk space)"
    err = comm.bcast(err, root=0)
    if err:
        raise OutputError(err)
    return out


def _prepare(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise OutputError(f"output path {out} exists and is a file; set [output] directory to a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise OutputError(
                f"output folder {out} already exists and is not empty; run with --overwrite to replace it "
                "or set [output] directory (or --set output.directory=...) to another folder"
            )
        if not (out / RESOLVED_CASE).is_file():
            raise OutputError(
                f"output folder {out} is not empty and was not written by febed (no {RESOLVED_CASE}); "
                "refusing to clear it even with --overwrite: choose another [output] directory"
            )
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    probe = out / ".febed-write-test"
    with open(probe, "wb") as f:
        f.write(b"x" * 4096)
        f.flush()
        os.fsync(f.fileno())
    probe.unlink()


def _header(case) -> str:
    from febed import __version__

    src = f" from {case.path}" if case.path else ""
    return f"# resolved by febed {__version__}{src}: every parameter, defaults filled in\n\n"


class _RankFilter(logging.Filter):
    def __init__(self, rank: int):
        super().__init__()
        self.rank = rank

    def filter(self, record: logging.LogRecord) -> bool:
        return self.rank == 0 or record.levelno >= logging.WARNING


def get_logger(outdir: Path | None = None, comm=MPI.COMM_WORLD, verbose: bool = False) -> logging.Logger:
    """The `febed` logger: console (rank 0; warnings from every rank) and, if `outdir`, `outdir/febed.log`."""
    log = logging.getLogger("febed")
    log.setLevel(logging.DEBUG if verbose else logging.INFO)
    log.propagate = False
    for h in list(log.handlers):
        log.removeHandler(h)
        h.close()
    prefix = f"[rank {comm.rank}] " if comm.size > 1 and comm.rank else ""
    console = logging.StreamHandler(sys.stdout)
    console.setFormatter(logging.Formatter(prefix + "%(message)s"))
    console.addFilter(_RankFilter(comm.rank))
    log.addHandler(console)
    if outdir is not None and comm.rank == 0:
        fh = logging.FileHandler(Path(outdir) / LOG_FILE, mode="a")
        fh.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
        log.addHandler(fh)
    return log
