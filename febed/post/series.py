"""Time series of a run from its probes (`probes.csv`): bed pressure drop and bed height, and their means.

Non-dimensionalisations (seed 001 §4): time t / (d_p / U_f), heights z / H. The pressure drop is compared
with the buoyant bed weight per cross-section, W/A = (ρ_p − ρ_g) g Σ V_p / A, which is what `dp_bed`
(bottom − top − the gas column's weight, see febed/runs/coupled.py) must equal once the bed is fluidized.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from febed.post.rundata import RunInfo


@dataclass
class SeriesSummary:
    """Means over a time window of the probe series.

    Attributes:
        window: (t0, t1) in s actually covered by rows.
        rows: number of probe rows in the window.
        dp_mean, dp_std: mean and standard deviation of dp_bed (Pa).
        bed_height_mean, bed_height_std: of the bed height (m).
        weight_per_area: buoyant bed weight / cross-section (Pa), NaN if the particle volume is unknown.
    """

    window: tuple[float, float]
    rows: int
    dp_mean: float
    dp_std: float
    bed_height_mean: float
    bed_height_std: float
    weight_per_area: float

    @property
    def dp_ratio(self) -> float:
        """Mean pressure drop / (bed weight per cross-section)."""
        return self.dp_mean / self.weight_per_area if self.weight_per_area > 0 else math.nan


def read_series(run_dir: str | Path) -> dict[str, np.ndarray]:
    """The probe columns of a run as arrays ({} without probe rows yet, or without probes.csv: mode = 'dem').

    Safe on a running run: a row being written (no newline yet, missing or unparsable cells) is dropped.
    """
    path = Path(run_dir) / "probes.csv"
    if not path.is_file():
        return {}
    with open(path, newline="") as f:
        text = f.read()
    lines = text.split("\n")
    if not text.endswith("\n"):
        lines = lines[:-1]  # the last row is still being written
    rows = [r for r in csv.reader(lines) if r]
    if not rows:
        return {}
    header, body = rows[0], []
    for r in rows[1:]:
        if len(r) != len(header):
            continue
        try:
            body.append([float(c) if c != "" else math.nan for c in r])
        except ValueError:
            continue
    if not body:
        return {}
    data = np.asarray(body, dtype=float)
    return {c: data[:, k].copy() for k, c in enumerate(header)}


def weight_per_area(info: RunInfo, solid_volume: float) -> float:
    """Buoyant weight of `solid_volume` (m^3) of particles per cross-section (Pa)."""
    return (info.rho_p - info.rho_g) * info.gravity * solid_volume / info.cross_section


def summarize(series: dict[str, np.ndarray], window: tuple[float, float], w_per_a: float) -> SeriesSummary:
    """Means and standard deviations of dp_bed and bed_height over window (t0, t1) in s."""
    t = series.get("time", np.zeros(0))
    sel = (t >= window[0] - 1e-12) & (t <= window[1] + 1e-12)

    def stats(name):
        v = series.get(name)
        if v is None or not sel.any():
            return math.nan, math.nan
        v = v[sel]
        v = v[np.isfinite(v)]
        return (float(v.mean()), float(v.std())) if v.size else (math.nan, math.nan)

    dp, dps = stats("dp_bed")
    bh, bhs = stats("bed_height")
    covered = (float(t[sel].min()), float(t[sel].max())) if sel.any() else (math.nan, math.nan)
    return SeriesSummary(covered, int(sel.sum()), dp, dps, bh, bhs, w_per_a)
