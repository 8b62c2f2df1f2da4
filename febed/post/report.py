"""`febed post RUN_DIR`: averaged fields, profiles, time series, as CSV tables and PNG figures in RUN_DIR/post/.

Files written (x/L, z/H, q_p²/U_f², flux/ρU_f, t/(d_p/U_f): seed 001 §4 scales):

    fields.npz                    every averaged array + grid + window (numpy)
    fields.csv                    one row per bin: x, z, x/L, z/H, alpha_p, flux x/z (and / ρU_f), U_p, q2,
                                  bubble frequency (share of the snapshots with α_p < bubble_alpha)
    profile_zH<h>.csv             horizontal profiles at z/H = h (default 0.092, seed 001 Figs 13, 18)
    depth_zH<h>.csv               3D runs: the vertical particle velocity across the depth at z/H = h
                                  (default 0.16, seed 001 Fig 11), whole width, centre and walls
                                  (febed.post.depth); summary.csv: each profile's spread (max - min) / U_f
                                  and the front/back asymmetry of the solid there
    timeseries.csv                t, t/(d_p/U_f), dp_bed, dp_bed/(W/A), bed_height, bed_height/H
    summary.csv                   key, value: window, snapshots, means of dp_bed and bed height, W/A, ...
                                  bed_flux_centre/walls/rhoUf: vertical solid flux averaged over the bed's
                                  rows, central third and outer 15 % of the width (seed 001's mixing loops);
                                  bubble_fraction: the share of the bins below 0.8 × the bed height that
                                  are void (α_p < bubble_alpha, default 0.15) in a snapshot, averaged;
                                  q2_bed/Uf2: the solid-volume-weighted agitation energy below the bed height;
                                  bottom_support/W: the share of the bed weight the bottom wall carries by
                                  contact (febed.post.support), which dp_bed/(W/A) then lacks
    fields.png, profile_zH<h>.png, depth_zH<h>.png, timeseries.png, snapshots.png (instantaneous 1 - α_p,
    seed 001 Fig 15)
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from febed.post.depth import BANDS, DEPTH_HEIGHT, DepthProfile, default_depth_bins
from febed.post.fields import AveragedFields, average_fields, default_bins, make_grid
from febed.post.figures import depth_plot, field_maps, profile_plot, series_plot, snapshot_maps
from febed.post.grid import BUBBLE_ALPHA, bin_sums
from febed.post.rundata import list_snapshots, read_snapshot, run_info, select_window
from febed.post.series import SeriesSummary, read_series, summarize, weight_per_area
from febed.post.support import bottom_support

DEFAULT_HEIGHTS = (0.092,)  # z/H of seed 001 Figs 13, 18


@dataclass
class PostResult:
    """What `post_run` computed and wrote: the averaged fields (None without particle output), summary, files."""

    fields: AveragedFields | None
    summary: SeriesSummary
    files: list[Path] = field(default_factory=list)
    values: dict = field(default_factory=dict)


def _write_csv(path: Path, header: list[str], rows) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        for r in rows:
            w.writerow([f"{v:.9g}" if isinstance(v, float) else v for v in r])
    return path


def _fields_csv(avg: AveragedFields, path: Path) -> Path:
    s = avg.scales()
    xs, zs = avg.grid.centres(0), avg.grid.centres(1)
    fx, fz = avg.quantity("mass_flux_x"), avg.quantity("mass_flux_z")
    ux, uz = avg.quantity("velocity_x"), avg.quantity("velocity_z")
    rows = []
    for i, x in enumerate(xs):
        for j, z in enumerate(zs):
            rows.append(
                (
                    float(x), float(z), float((x - avg.grid.lo[0]) / s["L"]), float((z - avg.grid.lo[1]) / s["H"]),
                    float(avg.alpha_p[i, j]), float(fx[i, j]), float(fz[i, j]),
                    float(fx[i, j] / s["rhoU_f"]), float(fz[i, j] / s["rhoU_f"]),
                    float(ux[i, j]), float(uz[i, j]), float(avg.q2[i, j]), float(avg.q2[i, j] / s["U_f"] ** 2),
                    float(avg.bubble_frequency[i, j]),
                )
            )  # fmt: skip
    header = [
        "x", "z", "x/L", "z/H", "alpha_p", "mass_flux_x", "mass_flux_z", "mass_flux_x/rhoUf", "mass_flux_z/rhoUf",
        "U_px", "U_pz", "q2", "q2/Uf2", "bubble_frequency",
    ]  # fmt: skip
    return _write_csv(path, header, rows)


def post_run(
    run_dir: str | Path,
    window: tuple[float, float] | None = None,
    bins: tuple[int, int] | None = None,
    kernel: str = "ngp",
    agitation: str = "cell",
    heights: tuple[float, ...] = DEFAULT_HEIGHTS,
    figures: bool = True,
    out: str | Path | None = None,
    bubble_alpha: float = BUBBLE_ALPHA,
    depth_height: float | None = DEPTH_HEIGHT,
    depth_bins: int | None = None,
) -> PostResult:
    """Post-process a run folder into `out` (default RUN_DIR/post): see the module docstring.

    Args:
        run_dir: a febed output folder, finished or still running.
        window: (t0, t1) in s for every time average; default the last half of the particle output.
        bins: plane bins (n_horizontal, n_vertical); default the built-in mesh's cells.
        kernel: "ngp" (particle volume to the bin of its centre) or "cic" (bilinear, folded at walls).
        agitation: "cell" (u' about the bin's instantaneous mean, seed 001) or "window".
        heights: z/H of the horizontal profiles.
        figures: write the PNG figures.
        out: output folder.
        bubble_alpha: a bin below this instantaneous α_p is bubble (bubble_frequency, bubble_fraction).
        depth_height: z/H of the profile across the depth (3D runs; None: none).
        depth_bins: bins across the depth (default the built-in mesh's cells across it).
    """
    run_dir = Path(run_dir)
    info = run_info(run_dir)
    out = Path(out) if out is not None else run_dir / "post"
    for h in heights:
        if not 0.0 <= h <= 1.0:
            raise ValueError(f"heights: z/H values in [0, 1] expected, got {h}")
    try:
        snaps = list_snapshots(run_dir)
    except ValueError:
        snaps = []
    series = read_series(run_dir)
    if not snaps and not series:
        raise ValueError(f"run_dir {run_dir}: neither particle snapshots nor probes.csv to post-process yet")
    out.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    avg = None
    depth = None
    if snaps:
        grid = make_grid(info, bins or default_bins(run_dir, info))
        if depth_height is not None and info.dim == 3:
            ny = depth_bins if depth_bins is not None else default_depth_bins(run_dir, info)
            depth = DepthProfile(info, grid, ny, depth_height)
        visitors = (depth,) if depth is not None else ()
        avg = average_fields(run_dir, window, grid.n, kernel, agitation, bubble_alpha=bubble_alpha, visitors=visitors)
        window = avg.window
        np.savez(
            out / "fields.npz",
            x=avg.grid.centres(0), z=avg.grid.centres(1), alpha_p=avg.alpha_p, mass_flux=avg.mass_flux,
            velocity=avg.velocity, q2=avg.q2, bubble_frequency=avg.bubble_frequency, bubble_alpha=avg.bubble_alpha,
            times=np.asarray(avg.times), window=np.asarray(avg.window),
            kernel=avg.kernel, agitation=avg.agitation, axes=np.asarray(avg.grid.axes), depth=avg.grid.depth,
        )  # fmt: skip
        files += [out / "fields.npz", _fields_csv(avg, out / "fields.csv")]
    elif window is None:
        t = series["time"]
        window = (float(t[0] + 0.5 * (t[-1] - t[0])), float(t[-1]))
    volume = avg.solid_volume if avg is not None else math.nan
    if not math.isfinite(volume) and "particles" in series and series["particles"].size:
        volume = float(series["particles"][-1]) * math.pi / 6.0 * info.d_p**3
    summary = summarize(series, window, weight_per_area(info, volume)) if series else None
    if summary is None:
        summary = SeriesSummary(window, 0, math.nan, math.nan, math.nan, math.nan, weight_per_area(info, volume))
    values = {
        "window_t0": window[0], "window_t1": window[1], "snapshots": len(avg.times) if avg else 0,
        "probe_rows": summary.rows, "dp_bed_mean": summary.dp_mean, "dp_bed_std": summary.dp_std,
        "weight_per_area": summary.weight_per_area, "dp_bed_over_weight": summary.dp_ratio,
        "bed_height_mean": summary.bed_height_mean, "bed_height_std": summary.bed_height_std,
        "bed_height_over_H": summary.bed_height_mean / info.height, "solid_volume": volume,
        "U_f": info.u_f, "rho_g": info.rho_g, "rho_p": info.rho_p, "d_p": info.d_p,
        "L": info.width, "D": info.depth, "H": info.height, "kernel": kernel, "agitation": agitation,
        "bins": f"{avg.grid.n[0]}x{avg.grid.n[1]}" if avg else "",
    }  # fmt: skip
    if avg is not None:
        s = avg.scales()
        nan = math.nan
        c, w = avg.circulation(summary.bed_height_mean) if math.isfinite(summary.bed_height_mean) else (nan, nan)
        values["bed_flux_centre/rhoUf"], values["bed_flux_walls/rhoUf"] = c / s["rhoU_f"], w / s["rhoU_f"]
        h_bed = summary.bed_height_mean
        values["bubble_alpha"] = avg.bubble_alpha
        values["bubble_fraction"] = avg.bubble_fraction(0.8 * h_bed) if math.isfinite(h_bed) else nan
        values["q2_bed/Uf2"] = avg.bed_agitation(h_bed) / s["U_f"] ** 2 if math.isfinite(h_bed) else nan
        values["bottom_support/W"] = bottom_support(run_dir, info, avg.window)
        for h in heights:
            x, fz = avg.profile("mass_flux_z", h * info.height)
            _, a = avg.profile("alpha_p", h * info.height)
            _, uz = avg.profile("velocity_z", h * info.height)
            _, q2 = avg.profile("q2", h * info.height)
            xl = (x - avg.grid.lo[0]) / s["L"]
            rows = zip(x, xl, a, fz, fz / s["rhoU_f"], uz / s["U_f"], q2 / s["U_f"] ** 2, strict=True)
            name = f"profile_zH{h:g}"
            header = ["x", "x/L", "alpha_p", "mass_flux_z", "mass_flux_z/rhoUf", "U_pz/Uf", "q2/Uf2"]
            files.append(_write_csv(out / f"{name}.csv", header, ([float(v) for v in r] for r in rows)))
            values[f"{name}_flux_centre/rhoUf"] = float(np.interp(0.5, xl, fz / s["rhoU_f"]))
            if figures:
                files.append(
                    profile_plot(
                        xl,
                        {run_dir.name: fz / s["rhoU_f"]},
                        r"$\overline{\langle\alpha_p\rho_p U_{p,z}\rangle}_{xz}/\rho U_f$",
                        f"vertical solid mass flux at z/H = {h:g}",
                        out / f"{name}.png",
                    )
                )
        if depth is not None:
            files += _depth_files(depth, run_dir.name, out, figures, values)
        if figures:
            files.append(field_maps(avg, out / "fields.png"))
            chosen, _ = select_window(snaps, avg.window)
            frames = []
            for k in np.unique(np.linspace(0, len(chosen) - 1, min(6, len(chosen))).astype(int)):
                t, path = chosen[k]
                a = read_snapshot(path)
                if a is not None:
                    s0 = bin_sums(avg.grid, a["pos"], a["velocity"], a["diameter"], kernel).s0
                    frames.append((t, s0 / avg.grid.bin_volume))
            if frames:
                files.append(snapshot_maps(avg.grid, info, frames, out / "snapshots.png"))
    if series:
        t = series["time"]
        tref = info.d_p / info.u_f if info.u_f > 0 else math.nan
        wa = summary.weight_per_area
        cols = [t, t / tref, series.get("dp_bed", t * np.nan), series.get("dp_bed", t * np.nan) / wa]
        cols += [series.get("bed_height", t * np.nan), series.get("bed_height", t * np.nan) / info.height]
        header = ["time", "t/(d_p/U_f)", "dp_bed", "dp_bed/(W/A)", "bed_height", "bed_height/H"]
        rows = ([float(v) for v in r] for r in zip(*cols, strict=True))
        files.append(_write_csv(out / "timeseries.csv", header, rows))
        if figures and "dp_bed" in series and "bed_height" in series:
            files.append(series_plot(series, summary, info, out / "timeseries.png"))
    files.append(_write_csv(out / "summary.csv", ["key", "value"], values.items()))
    return PostResult(fields=avg, summary=summary, files=files, values=values)


def _depth_files(depth: DepthProfile, name: str, out: Path, figures: bool, values: dict) -> list[Path]:
    """depth_zH<h>.csv (+ .png) of a `DepthProfile`; its spreads / U_f go into `values`."""
    u_f = depth.info.u_f
    stem = f"depth_zH{depth.height:g}"
    y = depth.info.lo[1] + depth.y_over_d * depth.info.depth
    cols = [y, depth.y_over_d, *(depth.velocity(b) / u_f for b in BANDS), depth.share("all")]
    header = ["y", "y/D", *(f"U_pz/Uf_{b}" for b in BANDS), "solid_share_all"]
    files = [_write_csv(out / f"{stem}.csv", header, ([float(v) for v in r] for r in zip(*cols, strict=True)))]
    for b in BANDS:
        values[f"{stem}_spread_{b}/Uf"] = depth.spread(b) / u_f
    values[f"{stem}_front_back_asymmetry"] = depth.asymmetry()
    if figures:
        files.append(depth_plot(depth, name, out / f"{stem}.png"))
    return files
