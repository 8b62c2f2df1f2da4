"""PNG figures of the post-processing (matplotlib, Agg backend): maps, profiles, time series."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from febed.post.depth import BANDS


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _top(avg, threshold: float = 1e-3) -> float:
    """Height (z/H) up to which the maps are drawn: 1.3 x the highest row holding particles, at most 1."""
    rows = np.flatnonzero(avg.alpha_p.max(axis=0) > threshold)
    if rows.size == 0:
        return 1.0
    zc = (avg.grid.centres(1) - avg.grid.lo[1]) / avg.info.height
    return float(min(1.0, 1.3 * zc[rows[-1]] + 0.05))


def field_maps(avg, path: Path) -> Path:
    """Maps of ⟨α_p⟩, vertical solid flux / ρU_f (+ flux arrows), q_p²/U_f², bubble frequency (seed 001 Figs 12-17).

    The bubble frequency is the share of the snapshots in which a bin was void: where bubbles pass (Fig 15).
    """
    plt = _plt()
    s = avg.scales()
    L, H = s["L"], s["H"]
    top = _top(avg)
    ext = [0.0, 1.0, 0.0, 1.0]
    vz = avg.quantity("mass_flux_z") / s["rhoU_f"]
    panels = [
        (avg.alpha_p, r"$\overline{\langle\alpha_p\rangle}_{xz}$", "viridis", (0.0, max(0.6, avg.alpha_p.max()))),
        (vz, r"$\overline{\langle\alpha_p\rho_p U_{p,z}\rangle}_{xz}/\rho U_f$", "RdBu_r", None),
        (avg.q2 / s["U_f"] ** 2, r"$q_p^2/U_f^2$", "magma", None),
        (avg.bubble_frequency, f"bubble frequency\n(α_p < {avg.bubble_alpha:g})", "Blues", (0.0, 1.0)),
    ]
    fig, axes = plt.subplots(1, len(panels), figsize=(3 * len(panels), 1.4 + 2.3 * top * H / L), sharey=True)
    for ax, (f, title, cmap, lim) in zip(axes, panels, strict=True):
        if lim is None:
            m = float(np.nanmax(np.abs(f))) or 1.0
            lim = (-m, m) if cmap == "RdBu_r" else (0.0, m)
        im = ax.imshow(f.T, origin="lower", extent=ext, aspect=H / L, cmap=cmap, vmin=lim[0], vmax=lim[1])
        ax.set(title=title, xlabel="x/L", ylim=(0.0, top))
        fig.colorbar(im, ax=ax, shrink=0.8)
    xs = (avg.grid.centres(0) - avg.grid.lo[0]) / L
    zs = (avg.grid.centres(1) - avg.grid.lo[1]) / H
    step = max(1, avg.grid.n[0] // 12)
    X, Z = np.meshgrid(xs[::step], zs[::step], indexing="ij")
    fx = avg.quantity("mass_flux_x")[::step, ::step]
    fz = avg.quantity("mass_flux_z")[::step, ::step]
    axes[1].quiver(X, Z, fx, fz, angles="uv", color="k", width=0.004)  # the axes have the physical aspect
    axes[0].set_ylabel("z/H")
    t0, t1 = avg.window
    fig.suptitle(f"time average over {len(avg.times)} snapshots, t = {t0:g}..{t1:g} s ({avg.kernel} bins)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def profile_plot(x_over_l: np.ndarray, values: dict[str, np.ndarray], ylabel: str, title: str, path: Path) -> Path:
    """Profiles against x/L (one curve per entry of `values`), e.g. seed 001 Figs 13, 18."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    for label, v in values.items():
        ax.plot(x_over_l, v, marker="o", ms=3, label=label)
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set(xlabel="x/L", ylabel=ylabel, title=title, xlim=(0, 1))
    if len(values) > 1:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def series_plot(series: dict, summary, info, path: Path) -> Path:
    """dp_bed / (W/A) and the bed height / H against time, the averaging window shaded."""
    plt = _plt()
    t = series["time"]
    fig, ax = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    wa = summary.weight_per_area
    ax[0].plot(t, series["dp_bed"] / wa if wa > 0 else series["dp_bed"], lw=0.8)
    ax[0].axhline(1.0 if wa > 0 else 0.0, color="k", ls="--", lw=0.8)
    ax[0].set(ylabel=r"$\Delta p_{bed} / (W/A)$" if wa > 0 else r"$\Delta p_{bed}$ [Pa]")
    ax[1].plot(t, series["bed_height"] / info.height, lw=0.8)
    ax[1].set(xlabel="t [s]", ylabel="bed height / H")
    for a in ax:
        a.axvspan(*summary.window, color="0.85", zorder=0)
    fig.suptitle(
        f"mean over the shaded window: Δp/(W/A) = {summary.dp_ratio:.3f}, "
        f"bed height {1e3 * summary.bed_height_mean:.1f} mm",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def snapshot_maps(grid, info, frames: list[tuple[float, np.ndarray]], path: Path) -> Path:
    """Instantaneous gas volume fraction 1 − α_p maps at a few times (seed 001 Fig 15)."""
    plt = _plt()
    L, H = info.width, info.height
    top = 1.0
    alphas = [a for _, a in frames]
    rows = np.flatnonzero(np.max([a.max(axis=0) for a in alphas], axis=0) > 1e-3)
    if rows.size:
        top = float(min(1.0, 1.3 * (grid.centres(1)[rows[-1]] - grid.lo[1]) / H + 0.05))
    fig, axes = plt.subplots(
        1, len(frames), figsize=(1.6 * len(frames) + 1.0, 1.2 + 1.5 * top * H / L), sharey=True, squeeze=False
    )
    for ax, (t, a) in zip(axes[0], frames, strict=True):
        im = ax.imshow(
            (1.0 - a).T, origin="lower", extent=[0, 1, 0, 1], aspect=H / L, cmap="viridis_r", vmin=0.4, vmax=1.0
        )
        ax.set(title=f"t = {t:.2f} s", xlabel="x/L", ylim=(0, top))
    axes[0][0].set_ylabel("z/H")
    fig.colorbar(im, ax=list(axes[0]), shrink=0.8, label=r"$1-\alpha_p$")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def depth_plot(depth, name: str, path: Path) -> Path:
    """The vertical particle velocity across the depth at one height, per band of the width (seed 001 Fig 11)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(4.5, 3.5))
    labels = {"all": "whole width", "centre": "central third", "walls": "outer 15 % (side walls)"}
    for b in BANDS:
        ax.plot(depth.y_over_d, depth.velocity(b) / depth.info.u_f, marker="o", ms=3, label=labels[b])
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set(xlabel="y/D", ylabel=r"$\overline{U_{p,z}}/U_f$", xlim=(0, 1))
    z0, z1 = (np.asarray(depth.slab) - depth.info.lo[2]) / depth.info.height
    ax.set_title(f"{name}: across the depth, z/H = {z0:.3f}-{z1:.3f}, {depth.snapshots} snapshots", fontsize=8)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
