"""The run's output folder and its log: created safely, never overwriting a user's files by surprise.

Layout of an output folder (`[output] directory`, default `./runs/<case name>/`):

    case.resolved.toml   the case with every default filled in (what actually ran)
    febed.log            the log (same lines as the console, with time stamps)
    status.json          running / finished / failed / interrupted, the simulated time reached, and the host
                         and process id of the run that wrote it
    mesh/                built-in meshes generated for this run (.msh)
    ...                  fields, particles, probes, checkpoints (written by their modules)

A folder is recognised as febed's by its `case.resolved.toml`. `febed run` refuses an existing non-empty
folder unless `--overwrite`, and even then refuses to clear a folder that is not febed's or whose run is
still going on this machine (`running_process`; `febed run --restart` refuses that too).
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
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
    info.update(host=socket.gethostname(), pid=os.getpid())  # which process wrote it (`running_process`)
    atomic_write_text(Path(outdir) / STATUS_FILE, json.dumps(info, indent=1) + "\n")


def running_process(outdir: Path) -> int | None:
    """The process id of a febed run still writing `outdir`, if it runs on this machine; else None.

    A folder is being written when its status.json says "running", was written on this host, and its
    writer's process (rank 0) is alive and a febed process (its command line names febed, so that a reused
    process id does not count). A run killed without a chance to update its status (kill -9, a node crash)
    is not alive, and a run on another host cannot be checked: both give None.
    """
    import json

    try:
        info = json.loads((Path(outdir) / STATUS_FILE).read_text())
    except (OSError, ValueError):
        return None
    pid = info.get("pid")
    if info.get("state") != "running" or info.get("host") != socket.gethostname() or not isinstance(pid, int):
        return None
    if pid == os.getpid():
        return None
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return None
    return pid if b"febed" in cmdline else None


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
        pid = running_process(out)
        if pid is not None:
            raise OutputError(
                f"output folder {out} belongs to a run that is still going (process {pid} on this machine); "
                f"refusing to clear it even with --overwrite: stop that run first (kill -USR1 {pid}) or choose "
                "another [output] directory"
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


def _last_progress(outdir: Path) -> tuple[str, str] | None:
    """(time stamp, text) of the last progress line in the run's log (its last 64 kB), or None."""
    import re

    try:
        with open(Path(outdir) / LOG_FILE, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - 65536))
            lines = f.read().decode(errors="replace").splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        m = re.match(r"^(\S+ \S+) INFO (t = \S+ / \S+ s .*)$", line)
        if m:
            return m.group(1).split(",")[0], m.group(2)
    return None


def describe_run(outdir: Path) -> str:
    """A few lines on a run folder: its state (and whether its process is alive), progress, newest checkpoint."""
    import json

    from febed.io.checkpoint import FOLDER, CheckpointError, list_checkpoints, read_meta

    outdir = Path(outdir)
    if not (outdir / RESOLVED_CASE).is_file():
        return f"{outdir}: not a febed run folder (no {RESOLVED_CASE})"
    try:
        info = json.loads((outdir / STATUS_FILE).read_text())
    except (OSError, ValueError):
        info = {}
    state = info.get("state", "unknown (no status.json)")
    head = f"{outdir}: {state}"
    if state == "running":
        pid = running_process(outdir)
        if pid is not None:
            head += f" (process {pid} on this machine)"
        elif "pid" not in info:
            head += " (written by a febed before session 10: whether its process is alive is not known)"
        elif info.get("host") != socket.gethostname():
            head += f" on {info['host']} (cannot check from here)"
        elif Path(f"/proc/{info['pid']}").exists():
            head += (
                f" (process {info['pid']} is alive but its command line does not name febed: a script using "
                "febed's Python API, or another program that reused the process id)"
            )
        else:
            head += " according to status.json, but its process is gone (killed?): continue it with --restart"
    lines = [head]
    if "time" in info:
        end = info.get("end_time", float("nan"))
        lines.append(f"  status.json: t = {info['time']:.6g} / {end:g} s, step {info.get('step', '?')}")
    if info.get("message"):
        lines.append(f"  message: {info['message']}")
    progress = _last_progress(outdir)
    if progress is not None:
        lines.append(f"  last progress line ({progress[0]}): {progress[1]}")
    ckpts = list_checkpoints(outdir / FOLDER)
    if ckpts:
        try:
            when = f" (t = {read_meta(ckpts[-1])['time']:.6g} s)"
        except CheckpointError:
            when = " (unreadable: --restart takes the newest readable one)"
        lines.append(f"  newest checkpoint: {ckpts[-1].relative_to(outdir)}{when}")
    return "\n".join(lines)
