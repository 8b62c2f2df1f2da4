"""A run's means over consecutive windows: has the bed reached a steady regime, and how much do its means vary?

A bubbling bed is chaotic: the mean of one window is one sample. Cut into consecutive windows of the same
length, a run shows whether its means drift (a start-up not yet over, or a bed that switches between regimes)
and how far the means of windows that long scatter about each other. `split_window` collects, for each window,
the numbers `febed compare` reports for a whole window (`febed.post.collect.run_row`: the bed pressure drop
and the bottom's share of the weight, the bed height, the loops' solid fluxes, the bubble fraction);
`febed post RUN_DIR --window T0 T1 --split DT` writes them to `windows.csv` and `windows.png` and prints
their spread.

Each window [a, b] holds the particle snapshots from a to b inclusive, as `febed post --window a b` does, so
a snapshot at a window boundary counts in both windows. Only whole windows of DT inside [T0, T1] are made.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from febed.post.collect import run_row, write_rows

COLUMNS = (
    "window_t0", "window_t1", "snapshots", "dp_bed_over_weight", "bottom_support/W", "bed_height_mean",
    "bed_flux_centre/rhoUf", "bed_flux_walls/rhoUf", "bubble_fraction",
)  # fmt: skip


def check_width(width: float) -> None:
    """Raise ValueError unless `width` (s) is a finite number > 0."""
    if not (math.isfinite(width) and width > 0.0):
        raise ValueError(f"split: the window length must be a number > 0 s, got {width}")


def window_edges(t0: float, t1: float, width: float) -> list[tuple[float, float]]:
    """Consecutive windows (a, b) of `width` s from t0, the whole ones inside [t0, t1]."""
    check_width(width)
    n = math.floor((t1 - t0) / width * (1.0 + 1e-9))
    if n < 1:
        raise ValueError(f"split: {width:g} s is longer than the averaging window {t0:g}..{t1:g} s")
    return [(round(t0 + k * width, 12), round(t0 + (k + 1) * width, 12)) for k in range(n)]


def split_window(run_dir, window: tuple[float, float], width: float, **options) -> list[dict]:
    """One row of `COLUMNS` per window of `width` s in `window` (s); `options` go to `run_row` (bins, kernel, ...)."""
    rows = []
    for a, b in window_edges(float(window[0]), float(window[1]), width):
        row, _ = run_row(run_dir, (a, b), fields=True, **options)
        rows.append({k: row[k] for k in COLUMNS})
    return rows


def spread(rows: list[dict], key: str) -> dict[str, float]:
    """Mean, spread and the whole window's standard error of `key` over the rows where it is finite.

    Returns n, mean, std (n − 1), min, max, r1 and sem:

    * r1, the lag-1 autocorrelation of the windows' means, Σ d_k d_(k+1) / Σ d_k² with d = v − mean
      (NaN below 3 windows);
    * sem, the standard error of the mean over all the windows, std / √n_eff, with the effective number of
      independent windows n_eff = n (1 − r1) / (1 + r1) of a first-order autoregressive series
      (Bretherton et al. 1999, J. Climate 12:1990-2009). r1 is taken as 0 when it is negative or undefined,
      so that correlated windows widen the error and anti-correlated ones never narrow it.

    Two runs' means differ beyond their sampling when the difference exceeds about 2 √(sem_1² + sem_2²).
    """
    v = np.array([r[key] for r in rows], dtype=float)
    v = v[np.isfinite(v)]
    out = {"n": int(v.size), "mean": math.nan, "std": math.nan, "min": math.nan, "max": math.nan}
    out.update(r1=math.nan, sem=math.nan)
    if v.size == 0:
        return out
    out.update(mean=float(v.mean()), min=float(v.min()), max=float(v.max()))
    if v.size < 2:
        return out
    out["std"] = float(v.std(ddof=1))
    d = v - v.mean()
    ss = float(d @ d)
    if v.size >= 3 and ss > 0.0:
        out["r1"] = float(d[:-1] @ d[1:]) / ss
    r1 = out["r1"] if math.isfinite(out["r1"]) and out["r1"] > 0.0 else 0.0
    n_eff = v.size * (1.0 - r1) / (1.0 + r1)  # > 0: r1 < 1 for any series that is not constant
    out["sem"] = out["std"] / math.sqrt(n_eff)
    return out


# the quantities `standard_errors` gives (as KEY_se): those `febed compare` prints for each run
SE_KEYS = (
    "dp_bed_over_weight", "bed_height_mean", "bed_flux_centre/rhoUf", "bed_flux_walls/rhoUf", "bubble_fraction",
)  # fmt: skip


def standard_errors(run_dir, window: tuple[float, float], width: float, **options) -> dict[str, float]:
    """KEY_se for the `SE_KEYS`: the standard errors (`spread`) of the run's means over `window` (s).

    From its consecutive windows of `width` s; `options` go to `run_row`. `febed compare --split` adds them to
    its rows.
    """
    rows = split_window(run_dir, window, width, **options)
    return {f"{key}_se": spread(rows, key)["sem"] for key in SE_KEYS}


def write_windows(rows: list[dict], out: str | Path, figures: bool = True, title: str = "") -> list[Path]:
    """`windows.csv` (one row per window) and, with `figures`, `windows.png` in the folder `out`."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "windows.csv"
    write_rows(rows, path)
    files = [path]
    if figures:
        files.append(_figure(rows, out / "windows.png", title))
    return files


def _figure(rows: list[dict], path: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    edges = [r["window_t0"] for r in rows] + [rows[-1]["window_t1"]]

    def steps(key):
        return [r[key] for r in rows] + [rows[-1][key]]

    fig, axes = plt.subplots(3, 1, figsize=(7.0, 6.4), sharex=True)
    ax = axes[0]
    ax.step(edges, steps("bed_flux_centre/rhoUf"), where="post", label="central third")
    ax.step(edges, steps("bed_flux_walls/rhoUf"), where="post", label="outer 15 %")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_ylabel(r"bed solid flux / $\rho U_f$", fontsize=9)
    ax.legend(fontsize=8)
    ax = axes[1]
    ax.step(edges, steps("dp_bed_over_weight"), where="post", label=r"$\Delta p$ / W")
    total = [a + b for a, b in zip(steps("dp_bed_over_weight"), steps("bottom_support/W"), strict=True)]
    ax.step(edges, total, where="post", label=r"$\Delta p$ / W + bottom / W")
    ax.axhline(1.0, color="k", ls="--", lw=0.6)
    ax.set_ylabel("force / bed weight", fontsize=9)
    ax.legend(fontsize=8)
    ax = axes[2]
    ax.step(edges, steps("bubble_fraction"), where="post")
    ax.set_ylabel("bubble fraction", fontsize=9)
    ax.set_xlabel("t [s]")
    fig.suptitle(title or "means over consecutive windows", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
