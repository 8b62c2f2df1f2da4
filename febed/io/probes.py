"""Probes: CSV time series, one row per probe interval, written by rank 0.

The file is plain CSV with a header (`time` first), readable by any spreadsheet, pandas or numpy. Rows are
flushed as they are written, so a run can be post-processed while it is going and a crash loses at most
the row being written. On restart, `ProbeFile(..., restart_time=t)` keeps the rows with time <= t (and
`keep_rows=n` at most the first n rows: those the checkpoint had seen) and appends after them, so the
series has neither duplicated nor missing rows.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

from mpi4py import MPI

from febed.io.atomic import atomic_open, sync_close


class ProbeFile:
    """A CSV time series with fixed columns (`time` + `columns`), appended row by row on rank 0."""

    def __init__(
        self,
        path: Path,
        columns: list[str],
        comm=MPI.COMM_WORLD,
        restart_time: float | None = None,
        keep_rows: int | None = None,
    ):
        """Open `path` for writing (new file) or, with `restart_time`, keep rows up to it and append."""
        self.path = Path(path)
        self.columns = ["time", *columns]
        self.comm = comm
        self.rows = 0  # data rows in the file (rank 0)
        self._f = None
        if comm.rank != 0:
            return
        if restart_time is not None and self.path.is_file():
            self.rows = self._truncate_after(restart_time, keep_rows)
            self._f = open(self.path, "a", newline="")
        else:
            self._f = open(self.path, "w", newline="")
            self._f.write(",".join(self.columns) + "\n")
            self._f.flush()

    def _truncate_after(self, t: float, keep_rows: int | None) -> int:
        with open(self.path, newline="") as f:
            rows = list(csv.reader(f))
        if not rows or rows[0] != self.columns:
            raise ValueError(f"{self.path}: its columns {rows[0] if rows else []} differ from {self.columns}")
        body = [r for r in rows[1:] if r and float(r[0]) <= t * (1 + 1e-12) + 1e-300]
        keep = [rows[0]] + body[:keep_rows]
        with atomic_open(self.path, "w", newline="") as f:
            f.write("\n".join(",".join(r) for r in keep) + "\n")
        return len(keep) - 1

    def write(self, time: float, values: dict[str, float]) -> None:
        """Append one row (rank 0 writes; other ranks ignore the call). Missing values are written empty."""
        if self._f is None:
            return
        row = [repr(float(time))]
        for c in self.columns[1:]:
            v = values.get(c)
            row.append("" if v is None or (isinstance(v, float) and math.isnan(v)) else repr(float(v)))
        self._f.write(",".join(row) + "\n")
        self._f.flush()
        self.rows += 1

    def close(self) -> None:
        """Flush to disk and close; a second call does nothing, even after a failed close (OSError)."""
        f, self._f = self._f, None
        if f is not None:
            sync_close(f)


def read_probes(path: str | os.PathLike) -> dict[str, list[float]]:
    """Read a probe CSV (a run's `probes.csv`).

    Args:
        path: the CSV file.

    Returns:
        {column name: list of values}, one value per row (empty cells as NaN).
    """
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], [r for r in rows[1:] if r]
    return {c: [float(r[k]) if r[k] != "" else math.nan for r in body] for k, c in enumerate(header)}
