"""Comparisons of runs in one table and a few figures: a study's members or any run folders.

`compare_members` serves `febed study` (`febed.study.collect` hands it the members and their states),
`compare_runs` serves `febed compare`.

Per run, over its averaging window (default: the last half of that run's output):

* mean and standard deviation of the bed pressure drop `dp_bed`, its ratio to the buoyant bed weight per
  cross-section, mean and standard deviation of the bed height (probes);
* from the particle output (unless fields=False): the time-averaged vertical solid mass flux / ρU_f at
  z/H = `height`, in the centre (x/L = 0.5) and next to the side walls (mean over the outer 10 % of each
  side), and the whole profile for an overlay figure (seed 001 Figs 13, 18);
* the bed's circulation (the flux averaged below the bed height in the central third and the outer 15 %),
  its bubble fraction and agitation energy, and the share of the weight on the bottom (`febed post`);
* 3D runs: `depth_spread/Uf`, the spread (max − min) of the vertical particle velocity across the depth at
  z/H = 0.16 over the whole width (`febed.post.depth`, seed 001 Fig 11) and `depth_asymmetry`, the solid's
  (front − back)/(front + back) there: both ~0 for a two-dimensional bed.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from febed.post.depth import DepthProfile, default_depth_bins
from febed.post.fields import average_fields, default_bins, make_grid
from febed.post.grid import BUBBLE_ALPHA
from febed.post.rundata import list_snapshots, read_status, run_info, select_window
from febed.post.series import read_series, summarize, weight_per_area
from febed.post.support import bottom_support

NUMBERS = (
    "t_reached", "window_t0", "window_t1", "dp_bed_mean", "dp_bed_std", "weight_per_area", "dp_bed_over_weight",
    "bed_height_mean", "bed_height_std", "bed_height_over_H", "snapshots", "flux_centre/rhoUf", "flux_walls/rhoUf",
    "bed_flux_centre/rhoUf", "bed_flux_walls/rhoUf", "bubble_fraction", "q2_bed/Uf2", "bottom_support/W",
    "depth_spread/Uf", "depth_asymmetry",
)  # fmt: skip


@dataclass
class Comparison:
    """The collected comparison: one row per run, the CSV path and the figures written."""

    rows: list[dict]
    csv: Path
    figures: list[Path]
    profiles: dict[str, tuple] = field(default_factory=dict)


def _empty_numbers() -> dict:
    """The row of a run without data: NaN everywhere, no snapshots."""
    return {**{k: math.nan for k in NUMBERS}, "snapshots": 0}


def run_row(directory, window=None, fields: bool = True, height: float = 0.092, bins=None, kernel: str = "ngp",
            agitation: str = "cell", bubble_alpha: float = BUBBLE_ALPHA) -> tuple[dict, tuple | None]:  # fmt: skip
    """The comparison's numbers of one run folder (NaN where it has no data) and its flux profile (x/L, flux/ρU_f).

    `window` (s): the averaging window, default the last half of the run's output so far; `bins`, `kernel`,
    `agitation` and `bubble_alpha` as `febed.post.post_run`'s (default: the built-in mesh's cells, its defaults).
    """
    nan = math.nan
    row = _empty_numbers()
    try:
        info = run_info(directory)
    except ValueError:
        return row, None
    series = read_series(directory)
    try:
        snaps = list_snapshots(directory)
    except ValueError:
        snaps = []
    status = read_status(directory) or {}
    t_last = max([float(series["time"][-1])] if series.get("time") is not None and series["time"].size else [nan])
    if snaps:
        t_last = max(t_last, snaps[-1][0]) if math.isfinite(t_last) else snaps[-1][0]
    row["t_reached"] = float(status.get("time", t_last))
    if window is None and math.isfinite(t_last):
        t_first = float(series["time"][0]) if series.get("time") is not None else snaps[0][0]
        window = (t_first + 0.5 * (t_last - t_first), t_last)
    if window is not None:
        row["window_t0"], row["window_t1"] = float(window[0]), float(window[1])
    profile = None
    volume = nan
    avg = None
    depth = None
    if fields and snaps:
        grid = make_grid(info, bins or default_bins(directory, info))
        if info.dim == 3:
            depth = DepthProfile(info, grid, default_depth_bins(directory, info))
        try:
            select_window(snaps, window)
            avg = average_fields(directory, window=window, bins=grid.n, kernel=kernel, agitation=agitation,
                                 bubble_alpha=bubble_alpha, visitors=(depth,) if depth else ())  # fmt: skip
        except ValueError:
            avg = None
        if avg is not None:
            volume = avg.solid_volume
            s = avg.scales()
            x, fz = avg.profile("mass_flux_z", height * info.height)
            xl = (x - avg.grid.lo[0]) / s["L"]
            f = fz / s["rhoU_f"]
            row["flux_centre/rhoUf"] = float(np.interp(0.5, xl, f))
            walls = (xl < 0.1) | (xl > 0.9)
            row["flux_walls/rhoUf"] = float(f[walls].mean()) if walls.any() else nan
            row["snapshots"] = len(avg.times)
            profile = (xl, f)
    if not math.isfinite(volume) and series.get("particles") is not None and series["particles"].size:
        volume = float(series["particles"][-1]) * math.pi / 6.0 * info.d_p**3
    if series and window is not None:
        sm = summarize(series, window, weight_per_area(info, volume))
        row.update({
            "dp_bed_mean": sm.dp_mean, "dp_bed_std": sm.dp_std, "weight_per_area": sm.weight_per_area,
            "dp_bed_over_weight": sm.dp_ratio, "bed_height_mean": sm.bed_height_mean,
            "bed_height_std": sm.bed_height_std, "bed_height_over_H": sm.bed_height_mean / info.height,
        })  # fmt: skip
        h = sm.bed_height_mean
        if avg is not None and math.isfinite(h):  # the bed's loops, bubbles and agitation (seed 001 Figs 14-17)
            s = avg.scales()
            c, w = avg.circulation(h)
            row["bed_flux_centre/rhoUf"], row["bed_flux_walls/rhoUf"] = c / s["rhoU_f"], w / s["rhoU_f"]
            row["bubble_fraction"] = avg.bubble_fraction(0.8 * h)
            row["q2_bed/Uf2"] = avg.bed_agitation(h) / s["U_f"] ** 2
    if avg is not None:
        row["bottom_support/W"] = bottom_support(directory, info, avg.window)
        if depth is not None:
            row["depth_spread/Uf"] = depth.spread("all") / info.u_f
            row["depth_asymmetry"] = depth.asymmetry()
    return row, profile


def _member_row(study, m, state: str, fields: bool, height: float) -> tuple[dict, tuple | None]:
    row = {"member": m.name, "state": state}
    row.update({k: m.values.get(k, "") for k in study.parameters})
    if state == "new":
        numbers, profile = _empty_numbers(), None
    else:
        numbers, profile = run_row(m.directory, study.window, fields, height)
    return {**row, **numbers}, profile


def _numeric(values) -> bool:
    return all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)


def _figures(study, rows: list[dict], profiles: dict, height: float, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    varied = [k for k, vals in study.parameters.items() if len(vals) > 1]
    quantities = _quantities(rows, height)
    for p in varied if quantities else []:
        vals = study.parameters[p]
        numeric = _numeric(vals)
        others = [k for k in varied if k != p]
        fig, axes = plt.subplots(1, len(quantities), figsize=(3.2 * len(quantities), 3.2), squeeze=False)
        axes = axes[0]
        groups: dict[tuple, list[dict]] = {}
        for r in rows:
            if r.get(p, "") == "":
                continue
            groups.setdefault(tuple(r.get(k) for k in others), []).append(r)
        for key, rs in groups.items():
            rs = sorted(rs, key=lambda r: vals.index(r[p]) if r[p] in vals else 0)
            xs = [r[p] if numeric else vals.index(r[p]) for r in rs]
            label = ", ".join(f"{k.rsplit('.', 1)[-1]}={v}" for k, v in zip(others, key, strict=True)) or None
            for ax, (q, _) in zip(axes, quantities, strict=True):
                ax.plot(xs, [r[q] for r in rs], marker="o", label=label)
        for ax, (_, ylabel) in zip(axes, quantities, strict=True):
            ax.set(xlabel=p, ylabel=ylabel)
            if not numeric:
                ax.set_xticks(range(len(vals)), [str(v) for v in vals], rotation=20)
        axes[0].axhline(1.0, color="k", ls="--", lw=0.7)
        if others:
            axes[0].legend(fontsize=7)
        fig.suptitle(f"study {study.name}: means over the averaging window", fontsize=9)
        fig.tight_layout()
        path = out / f"comparison_{p.replace('.', '_')}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        files.append(path)
    if profiles:
        files.append(_profile_figure(profiles, height, out))
    return files


def _quantities(rows: list[dict], height: float) -> list[tuple[str, str]]:
    """The (column, axis label) of the comparison's figures that hold a number for at least one row."""
    quantities = [
        ("dp_bed_over_weight", r"$\overline{\Delta p_{bed}}/(W/A)$"),
        ("bed_height_over_H", "bed height / H"),
        ("flux_centre/rhoUf", f"solid flux/ρU_f, centre, z/H={height:g}"),
        ("flux_walls/rhoUf", f"solid flux/ρU_f, walls, z/H={height:g}"),
        ("bubble_fraction", "bubble fraction below 0.8 H_bed"),
        ("q2_bed/Uf2", r"$q_p^2/U_f^2$ in the bed"),
        ("bottom_support/W", "weight on the bottom by contact / W"),
        ("depth_spread/Uf", "spread of U_p,z across the depth / U_f, z/H = 0.16"),
        ("depth_asymmetry", "solid (front - back)/(front + back), z/H = 0.16"),
    ]
    return [(q, lab) for q, lab in quantities if any(math.isfinite(r[q]) for r in rows)]


def _profile_figure(profiles: dict, height: float, out: Path, title: str = "") -> Path:
    """The runs' vertical solid mass flux profiles at z/H = `height` on one plot (seed 001 Figs 13, 18)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for name, (xl, f) in profiles.items():
        ax.plot(xl, f, marker="o", ms=2, label=name)
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set(xlabel="x/L", ylabel=r"$\overline{\langle\alpha_p\rho_p U_{p,z}\rangle}_{xz}/\rho U_f$", xlim=(0, 1))
    ax.set_title(title or f"vertical solid mass flux at z/H = {height:g}", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = out / "profiles_flux.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_rows(rows: list[dict], path: Path) -> None:
    """Rows of equal keys as a CSV file at `path` (floats to 6 significant digits)."""
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})


def compare_members(study, states, fields: bool = True, height: float = 0.092, out: Path | None = None) -> Comparison:
    """Collect every member's numbers into `out` (default <study directory>/comparison): CSV + figures.

    Args:
        study: a `febed.study.Study`.
        states: (member, state) of each of its members (`febed.study.member_states`).
        fields: also average the particle output (else the probe series only).
        height: z/H of the solid flux profile.
        out: the output folder.
    """
    if not 0.0 <= height <= 1.0:
        raise ValueError(f"height: expected z/H in [0, 1], got {height}")
    out = Path(out) if out is not None else study.directory / "comparison"
    out.mkdir(parents=True, exist_ok=True)
    rows, profiles = [], {}
    for m, state in states:
        row, prof = _member_row(study, m, state, fields, height)
        rows.append(row)
        if prof is not None:
            profiles[m.name] = prof
    path = out / "comparison.csv"
    write_rows(rows, path)
    if profiles:
        xl = next(iter(profiles.values()))[0]
        same = all(len(p[0]) == len(xl) and np.allclose(p[0], xl) for p in profiles.values())
        if same:
            with open(out / "profiles_flux.csv", "w", newline="") as f:
                w = csv.writer(f)
                w.writerow(["x/L", *profiles])
                for k in range(len(xl)):
                    w.writerow([f"{xl[k]:.6g}", *(f"{p[1][k]:.6g}" for p in profiles.values())])
    figs = _figures(study, rows, profiles, height, out)
    return Comparison(rows=rows, csv=path, figures=figs, profiles=profiles)


def compare_runs(
    directories, labels=None, windows=None, fields: bool = True, height: float = 0.092, out="comparison", extra=None
):
    """Compare run folders made independently (e.g. C1, C2, C3 of a mesh study run one by one): `febed compare`.

    One row per run, in the given order, with the numbers of `run_row` (`comparison.csv`), the flux profiles
    at z/H = `height` in long form (`profiles_flux.csv`: run, x/L, flux/ρU_f; the runs' bins may differ),
    and figures: each quantity against the runs (`comparison_runs.png`) and the profiles on one plot.
    `windows`: None (the last half of each run), one (t0, t1) for all, or one per run. `extra`: a function
    (run_dir, (t0, t1)) -> dict whose items are added to each run's row, e.g. the standard errors of
    `febed.post.windows.standard_errors` (`febed compare --split`).
    """
    directories = [Path(d) for d in directories]
    if not directories:
        raise ValueError("give at least one run folder to compare")
    for d in directories:
        if not d.is_dir():
            raise ValueError(f"run folder {d} does not exist")
        run_info(d)  # raises ValueError naming the folder when it holds no run
    labels = list(labels) if labels else [d.resolve().name for d in directories]
    if len(labels) != len(directories):
        raise ValueError(f"labels: {len(labels)} label(s) for {len(directories)} run folder(s)")
    if len(set(labels)) != len(labels):
        raise ValueError(f"labels: the runs' labels must differ (got {labels}); name them with --labels")
    windows = list(windows) if windows else [None]
    if len(windows) == 1:
        windows = windows * len(directories)
    if len(windows) != len(directories):
        raise ValueError(
            f"window: {len(windows)} window(s) for {len(directories)} run folder(s): give one or one per run"
        )
    for w in windows:
        if w is not None and not (len(w) == 2 and w[0] < w[1]):
            raise ValueError(f"window: {w}: expected T0 T1 with T0 < T1")
    if not 0.0 <= height <= 1.0:
        raise ValueError(f"height: expected z/H in [0, 1], got {height}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows, profiles = [], {}
    for d, label, w in zip(directories, labels, windows, strict=True):
        numbers, prof = run_row(d, w, fields, height)
        if extra is not None:
            numbers.update(extra(d, (numbers["window_t0"], numbers["window_t1"])))
        rows.append({"run": label, "directory": str(d), **numbers})
        if prof is not None:
            profiles[label] = prof
    path = out / "comparison.csv"
    write_rows(rows, path)
    figs = []
    if profiles:
        with open(out / "profiles_flux.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["run", "x/L", "flux/rhoUf"])
            for label, (xl, fl) in profiles.items():
                for a, b in zip(xl, fl, strict=True):
                    w.writerow([label, f"{a:.6g}", f"{b:.6g}"])
        figs.append(_profile_figure(profiles, height, out))
    quantities = _quantities(rows, height)
    if quantities:
        figs.append(_runs_figure(rows, quantities, out))
    return Comparison(rows=rows, csv=path, figures=figs, profiles=profiles)


def _runs_figure(rows: list[dict], quantities: list[tuple[str, str]], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncols = min(4, len(quantities))
    nrows = -(-len(quantities) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.4 * ncols, 3.2 * nrows), squeeze=False)
    axes = axes.ravel()
    names = [r["run"] for r in rows]
    for ax, (q, ylabel) in zip(axes, quantities, strict=False):
        ax.plot(range(len(rows)), [r[q] for r in rows], marker="o", ls="none")
        ax.set_xticks(range(len(rows)), names, rotation=20, fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
        if q == "dp_bed_over_weight":
            ax.axhline(1.0, color="k", ls="--", lw=0.7)
    for ax in axes[len(quantities) :]:
        ax.set_visible(False)
    windows = ", ".join(f"{r['run']} {r['window_t0']:g}-{r['window_t1']:g} s" for r in rows)
    fig.suptitle(f"means over the averaging windows ({windows})", fontsize=8)
    fig.tight_layout()
    path = out / "comparison_runs.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
