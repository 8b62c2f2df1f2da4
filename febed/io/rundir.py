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

One run owns its folder: before writing or deleting anything in it, a run takes an exclusive lock on
`.febed.lock` in the folder (`lock_output`: `flock` on the open file, kept for the run's life, with the host,
process id and start time of the holder written in the file). A second run, `--overwrite` and `--restart` are
refused while it is held. The kernel drops the lock when its process ends however it ends (kill -9 too), so a
lock file left behind by a dead run is stale and the next run takes it over (with a logged note). The run
removes the file when it ends (`release_output`). Under MPI, rank 0 holds the lock for every rank.
"""

from __future__ import annotations

import atexit
import errno
import fcntl
import json
import logging
import os
import shutil
import socket
import sys
import time
from pathlib import Path

from mpi4py import MPI

from febed import __version__
from febed.io.atomic import atomic_write_text
from febed.io.checkpoint import FOLDER, CheckpointError, list_checkpoints, read_meta

RESOLVED_CASE = "case.resolved.toml"
LOG_FILE = "febed.log"
STATUS_FILE = "status.json"
LOCK_FILE = ".febed.lock"


class OutputError(RuntimeError):
    """The output folder cannot be used (exists, not writable, ...)."""


def write_status(outdir: Path, state: str, time: float, end_time: float, step: int = 0, message: str = "",
                 comm=MPI.COMM_WORLD) -> None:  # fmt: skip
    """Write `status.json` (rank 0, atomically): running / finished / failed / interrupted, time reached."""
    if comm.rank != 0:
        return

    info = {"state": state, "time": float(time), "step": int(step), "end_time": float(end_time)}
    if message:
        info["message"] = message
    info.update(host=socket.gethostname(), pid=os.getpid())  # which process wrote it (`running_process`)
    text = json.dumps(info, indent=1) + "\n"
    try:
        atomic_write_text(Path(outdir) / STATUS_FILE, text)
    except OSError as e:  # a full disk has no room for the temporary copy; the file's own block is enough
        if e.errno != errno.ENOSPC or not (Path(outdir) / STATUS_FILE).is_file():
            raise
        fd = os.open(Path(outdir) / STATUS_FILE, os.O_WRONLY)
        try:
            os.pwrite(fd, text.encode(), 0)
            os.ftruncate(fd, len(text.encode()))
            os.fsync(fd)
        finally:
            os.close(fd)


def running_process(outdir: Path) -> int | None:
    """The process id of a febed run still writing `outdir`, if it runs on this machine; else None.

    A folder is being written when its status.json says "running", was written on this host, and its
    writer's process (rank 0) is alive and a febed process (its command line names febed, so that a reused
    process id does not count). A run killed without a chance to update its status (kill -9, a node crash)
    is not alive, and a run on another host cannot be checked: both give None.
    """
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

    Takes the folder's lock first (`lock_output`; kept until `release_output` or the end of the process) and
    tests that the folder is writable. Collective: every rank gets the same path or OutputError.

    Args:
        case: the loaded case (its `[output] directory` is the folder).
        overwrite: clear a folder written by febed before (never one whose lock is held by another run).
        comm: the communicator of the run; rank 0 does the work.

    Returns:
        The output folder.

    Raises:
        OutputError: the folder is in use, not empty (without `overwrite`), not febed's, or not writable.
    """
    out = case.output_dir()
    err = None
    if comm.rank == 0:
        fresh = held_lock(out) is None
        try:
            _precheck(out, overwrite)
            _acquire(out)
            _prepare(out, overwrite)
            atomic_write_text(out / RESOLVED_CASE, _header(case) + case.to_toml())
        except OutputError as e:
            err = str(e)
        except OSError as e:
            err = f"output folder {out}: {e.strerror or e} (check the path, permissions and free disk space)"
        if err and fresh:
            release_output(out)
    err = comm.bcast(err, root=0)
    if err:
        raise OutputError(err)
    return out


def _precheck(out: Path, overwrite: bool) -> None:
    """Refusals that need no lock; they keep a lock file from being added to a folder febed did not write."""
    if out.exists() and not out.is_dir():
        raise OutputError(f"output path {out} exists and is a file; set [output] directory to a folder")
    if out.is_dir() and not (out / LOCK_FILE).exists() and not (out / RESOLVED_CASE).exists() and any(out.iterdir()):
        _check_contents(out, overwrite)


def _check_contents(out: Path, overwrite: bool) -> None:
    """Refuse a non-empty folder (besides its lock file) unless `overwrite` and it is febed's, not running."""
    if not any(p.name != LOCK_FILE for p in out.iterdir()):
        return
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
    pid = running_process(out)
    if pid is not None:
        raise OutputError(
            f"output folder {out} belongs to a run that is still going (process {pid} on this machine); "
            f"refusing to clear it even with --overwrite: stop that run first (kill -USR1 {pid}) or choose "
            "another [output] directory"
        )


def _prepare(out: Path, overwrite: bool) -> None:
    """Under the folder's lock: check its contents, clear them (`overwrite`), test that it is writable."""
    _check_contents(out, overwrite)
    for p in out.iterdir():
        if p.name == LOCK_FILE:
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    probe = out / ".febed-write-test"
    with open(probe, "wb") as f:
        f.write(b"x" * 4096)
        f.flush()
        os.fsync(f.fileno())
    probe.unlink()


# ---------------------------------------------------------------------------------------- the folder's lock
_HELD: dict[str, FolderLock] = {}  # folder (absolute) -> the lock this process holds on it


class FolderLock:
    """This process's exclusive lock on a run folder: `flock` on the open `.febed.lock`, kept until `release`.

    Attributes:
        folder: the run folder.
        note: a sentence on the stale lock this one took over (a run that ended without releasing it), or "".
    """

    def __init__(self, folder: Path, fd: int, note: str = ""):
        self.folder = Path(os.path.abspath(folder))
        self.fd = fd
        self.note = note

    def release(self) -> None:
        """Remove the lock file and drop the lock (the file first, so that no other run locks a removed file)."""
        if self.fd < 0:
            return
        path = self.folder / LOCK_FILE
        try:
            if _same_file(self.fd, path):
                path.unlink()
        except OSError:
            pass
        os.close(self.fd)
        self.fd = -1
        _HELD.pop(_key(self.folder), None)


def _key(folder: Path) -> str:
    return os.path.abspath(folder)


@atexit.register
def _release_all() -> None:
    """At the end of the process, remove the lock files of folders still held (a script using the Python API)."""
    for lock in list(_HELD.values()):
        lock.release()


def _same_file(fd: int, path: Path) -> bool:
    """Whether the open `fd` is the file at `path` now (not one removed or replaced since it was opened)."""
    try:
        a, b = os.fstat(fd), os.stat(path)
    except FileNotFoundError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def _read_holder(fd: int) -> dict:
    try:
        info = json.loads(os.pread(fd, 4096, 0).decode(errors="replace") or "{}")
    except (OSError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


def describe_holder(info: dict) -> str:
    """The holder of a lock, in words: "process 123 on host h, started 2025-01-31 10:00:00".

    Args:
        info: the contents of a lock file (`host`, `pid`, `started`); missing keys are left out.

    Returns:
        The description ("an unknown process" if the file says nothing).
    """
    if "pid" not in info:
        return "an unknown process"
    words = f"process {info['pid']}"
    if info.get("host") == socket.gethostname():
        words += " on this machine"
    elif info.get("host"):
        words += f" on host {info['host']}"
    if info.get("started"):
        words += f", started {info['started']}"
    return words


def _in_use(folder: Path, info: dict) -> OutputError:
    pid = info.get("pid")
    stop = f", stop it (kill -USR1 {pid})" if isinstance(pid, int) and info.get("host") == socket.gethostname() else ""
    return OutputError(
        f"output folder {folder} is in use by another febed run ({describe_holder(info)}): wait for it to end{stop} "
        "or choose another [output] directory"
    )


def _holder_of_held(fd: int) -> dict:
    """The record of a lock's holder, given a moment to write it (it does so right after taking the lock)."""
    for _ in range(100):
        info = _read_holder(fd)
        if info:
            return info
        time.sleep(0.01)
    return {}


def _pid_alive(info: dict) -> bool:
    """Whether the process named in a lock file may still run (on another host: cannot tell, so yes)."""
    pid = info.get("pid")
    if info.get("host") != socket.gethostname() or not isinstance(pid, int):
        return bool(info)
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _acquire(folder: Path) -> FolderLock:
    """Take the lock on `folder` in this process (created if missing) or raise OutputError naming its holder.

    Re-entrant: a lock this process holds already is returned as it is.
    """
    held = held_lock(folder)
    if held is not None:
        return held
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_FILE
    for _ in range(100):  # another run may remove the file between our open and flock: open it again
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise _in_use(folder, _holder_of_held(fd)) from None
            except OSError as e:
                if e.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                    raise
                # a file system without flock: the process id in the file is all there is to go by
                if _pid_alive(_read_holder(fd)):
                    raise _in_use(folder, _read_holder(fd)) from None
            if not _same_file(fd, path):
                os.close(fd)
                continue
            previous = _read_holder(fd)
            me = {"host": socket.gethostname(), "pid": os.getpid(), "started": time.strftime("%Y-%m-%d %H:%M:%S")}
            data = (json.dumps(me) + "\n").encode()
            os.ftruncate(fd, 0)
            os.pwrite(fd, data, 0)
            os.fsync(fd)
        except BaseException:
            os.close(fd)
            raise
        note = ""
        if previous and (previous.get("pid"), previous.get("host")) != (me["pid"], me["host"]):
            note = (
                f"took over the stale lock of output folder {folder} left by {describe_holder(previous)}: "
                "that run ended without releasing it (killed?)"
            )
        lock = _HELD[_key(folder)] = FolderLock(folder, fd, note)
        return lock
    raise OutputError(f"output folder {folder}: could not take its lock {path} (it keeps being replaced)")


def held_lock(folder: Path) -> FolderLock | None:
    """The lock this process holds on `folder` (`lock_output`, `prepare_output`), or None.

    Args:
        folder: a run folder.

    Returns:
        The lock, or None (always None on ranks other than 0 of a run).
    """
    return _HELD.get(_key(folder))


def lock_output(folder: Path, comm=MPI.COMM_WORLD) -> FolderLock | None:
    """Take the exclusive lock on a run folder before anything is written to it (collective).

    Rank 0 takes it and the outcome is broadcast, so that every rank goes on or every rank raises. A lock
    left by a run that is gone (its process ended without releasing it) is taken over; the lock's `note`
    says so. Re-entrant within a process.

    Args:
        folder: the run folder (created if missing).
        comm: the communicator of the run.

    Returns:
        The lock on rank 0, None on the other ranks.

    Raises:
        OutputError: another run holds the lock (the message names its process), or the folder is unusable.
    """
    lock, err = None, None
    if comm.rank == 0:
        try:
            lock = _acquire(Path(folder))
        except OutputError as e:
            err = str(e)
        except OSError as e:
            err = f"output folder {folder}: {e.strerror or e} (check the path, permissions and free disk space)"
    err = comm.bcast(err, root=0)
    if err:
        raise OutputError(err)
    return lock


def release_output(folder: Path) -> None:
    """Release this process's lock on `folder`, if it holds one (removes `.febed.lock`).

    Args:
        folder: a run folder.
    """
    lock = held_lock(folder)
    if lock is not None:
        lock.release()


def _header(case) -> str:
    src = f" from {case.path}" if case.path else ""
    return f"# resolved by febed {__version__}{src}: every parameter, defaults filled in\n\n"


class _RankFilter(logging.Filter):
    def __init__(self, rank: int):
        super().__init__()
        self.rank = rank

    def filter(self, record: logging.LogRecord) -> bool:
        return self.rank == 0 or record.levelno >= logging.WARNING


class _LogFile(logging.FileHandler):
    """febed.log: a write that fails (a full disk) is said once on stderr, not as a traceback per line."""

    failed = False

    def handleError(self, record: logging.LogRecord) -> None:
        error = sys.exc_info()[1]
        if not self.failed:
            self.failed = True
            print(f"febed: cannot write {self.baseFilename}: {error} (the console keeps the log)", file=sys.stderr)


def get_logger(outdir: Path | None = None, comm=MPI.COMM_WORLD, verbose: bool = False) -> logging.Logger:
    """The `febed` logger: console (rank 0; warnings from every rank) and, if `outdir`, `outdir/febed.log`.

    Args:
        outdir: the run's output folder (from `prepare_output`); None logs to the console only.
        comm: the MPI communicator of the run.
        verbose: log debug messages too.

    Returns:
        The configured `logging.Logger` named "febed".
    """
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
        fh = _LogFile(Path(outdir) / LOG_FILE, mode="a")
        fh.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
        log.addHandler(fh)
    return log


def log_file_on_this_rank(log: logging.Logger, outdir: Path, comm=MPI.COMM_WORLD) -> None:
    """Let this rank write to the run's `febed.log` too, its lines marked `[rank k]` (rank 0 writes it already).

    For a rank that stops alone: rank 0, which writes the log, may be waiting for it in a collective call.
    """
    if comm.rank == 0 or any(isinstance(h, _LogFile) for h in log.handlers):
        return
    fh = _LogFile(Path(outdir) / LOG_FILE, mode="a")
    fh.setFormatter(logging.Formatter(f"%(asctime)s %(levelname)s [rank {comm.rank}] %(message)s"))
    log.addHandler(fh)


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
            head += " (written by an older febed that does not record its process: whether it is alive is not known)"
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
