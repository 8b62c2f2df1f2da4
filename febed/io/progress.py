"""Progress of a long run: one live line on a terminal, the same lines in the log file.

On a terminal (rank 0's stdout is a TTY) the line is redrawn in place (carriage return); in a batch job or
a pipe nothing is printed between the start and end messages, and every line goes to `febed.log` only.
"""

from __future__ import annotations

import logging
import math
import sys


def clock(seconds: float) -> str:
    """A duration as 1h02m03s ('?' when unknown)."""
    if not math.isfinite(seconds):
        return "?"
    seconds = int(seconds)
    return f"{seconds // 3600}h{seconds // 60 % 60:02d}m{seconds % 60:02d}s"


class Progress:
    """Shows progress lines: live on a terminal, always in the log file(s) of logger `log`."""

    def __init__(self, log: logging.Logger, rank: int = 0, stream=None):
        """Write to `stream` (default stdout) only on rank 0 and only if it is a terminal."""
        self.log = log
        self.stream = stream if stream is not None else sys.stdout
        self.live = rank == 0 and hasattr(self.stream, "isatty") and self.stream.isatty()
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
