"""Progress of a long run: one live line on a terminal, the same lines in the log file.

On a terminal (rank 0's stdout is a TTY) the line is redrawn in place (carriage return); in a batch job or
a pipe nothing is printed between the start and end messages, and every line goes to `febed.log` only.
Open MPI gives its ranks a pseudo-terminal even when `mpirun`'s own output goes to a file, so under an MPI
launcher the launcher's standard output decides (`launcher_is_terminal`).

The rate of a progress line (`RateMeter`) is measured over the last few minutes of wall time, not since the
start: a restart's compilation and set-up, or a bed that starts bubbling, would otherwise bias the ETA of a
long run for hours.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import resource
import sys
import time

from mpi4py import MPI

#: Environment variables set by MPI launchers in the processes they start (Open MPI, PMIx, MPICH/Hydra, Slurm).
LAUNCHER_VARIABLES = ("OMPI_COMM_WORLD_SIZE", "PMIX_RANK", "PMI_RANK", "SLURM_STEP_ID")


def clock(seconds: float) -> str:
    """A duration as 1h02m03s ('?' when unknown)."""
    if not math.isfinite(seconds):
        return "?"
    seconds = int(seconds)
    return f"{seconds // 3600}h{seconds // 60 % 60:02d}m{seconds % 60:02d}s"


def peak_memory(comm) -> str:
    """The processes' peak resident memory, for a run's last log line: the sum and the largest (collective)."""
    try:
        mine = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0  # kB on Linux
    except OSError:
        mine = float("nan")
    total, largest = comm.allreduce(mine), comm.allreduce(mine, op=MPI.MAX)
    if not math.isfinite(total):
        return "peak memory unknown"
    if comm.size == 1:
        return f"peak memory {total / 1e9:.2f} GB"
    return f"peak memory {total / 1e9:.2f} GB ({largest / 1e9:.2f} GB on the largest of {comm.size} ranks)"


def launcher_is_terminal(env=None, launcher_pid: int | None = None) -> bool:
    """False when this process was started by an MPI launcher whose own standard output is not a terminal.

    `mpirun ... > run.out` hands the ranks a pseudo-terminal, and a carriage-return line redrawn every few
    seconds would fill run.out. The launcher is the parent process (`launcher_pid`); its fd 1 is read from
    /proc. True when not under a launcher, or when that cannot be read (not Linux, launcher gone).
    """
    env = os.environ if env is None else env
    if not any(k in env for k in LAUNCHER_VARIABLES):
        return True
    pid = os.getppid() if launcher_pid is None else launcher_pid
    try:
        target = os.readlink(f"/proc/{pid}/fd/1")
    except OSError:
        return True
    return target.startswith(("/dev/pts/", "/dev/tty", "/dev/console"))


class RateMeter:
    """Wall seconds per simulated second over the last `window` wall seconds, and the ETA it gives."""

    def __init__(self, t: float, window: float = 300.0, now: float | None = None):
        """Start at simulated time `t` (s); `now` is a `time.perf_counter()` reading (default: now)."""
        self.window = window
        self.samples = collections.deque([(time.perf_counter() if now is None else now, t)])

    def rate(self, t: float, now: float | None = None) -> float:
        """Wall s per simulated s from the oldest sample within the window to (`now`, `t`); NaN before any progress."""
        now = time.perf_counter() if now is None else now
        self.samples.append((now, t))
        while len(self.samples) > 2 and self.samples[1][0] <= now - self.window:
            self.samples.popleft()
        wall0, t0 = self.samples[0]
        return (now - wall0) / (t - t0) if t > t0 else math.nan

    def text(self, t: float, end: float, now: float | None = None) -> str:
        """'R min wall per simulated s  ETA 1h02m03s' of a progress line at simulated time `t` of `end`."""
        rate = self.rate(t, now)
        return f"{rate / 60:.2f} min wall per simulated s  ETA {clock(rate * (end - t))}"


class Progress:
    """Shows progress lines: live on a terminal, always in the log file(s) of logger `log`."""

    def __init__(self, log: logging.Logger, rank: int = 0, stream=None, env=None, launcher_pid: int | None = None):
        """Write to `stream` (default stdout) only on rank 0 and only if it is a terminal.

        `env` and `launcher_pid` are for tests (see `launcher_is_terminal`).
        """
        self.log = log
        self.stream = stream if stream is not None else sys.stdout
        self.live = (
            rank == 0
            and hasattr(self.stream, "isatty")
            and self.stream.isatty()
            and launcher_is_terminal(env, launcher_pid)
        )
        self._width = 0

    def show(self, line: str) -> None:
        """Redraw the live line (terminal) and append `line` to the log files."""
        if self.live:
            pad = max(0, self._width - len(line))
            self.stream.write("\r" + line + " " * pad)
            self.stream.flush()
            self._width = len(line)
        record = self.log.makeRecord(self.log.name, logging.INFO, __file__, 0, line, None, None)
        for h in self.log.handlers:
            if isinstance(h, logging.FileHandler):
                h.handle(record)

    def end(self) -> None:
        """Finish the live line so that the next message starts on a fresh line."""
        if self.live and self._width:
            self.stream.write("\n")
            self.stream.flush()
            self._width = 0
