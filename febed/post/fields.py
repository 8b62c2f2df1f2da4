"""Time- and depth-averaged Eulerian fields of a run's particles, and profiles through them.

    >>> avg = average_fields("runs/C1", window=(5.0, 20.0))          # seed 001 Figs 12, 14, 16, 17
    >>> x, flux = avg.profile("mass_flux_z", height=0.092 * avg.info.height)   # Figs 13, 18
    >>> flux / (avg.info.rho_g * avg.info.u_f)

Definitions are in `febed.post.grid` (kernels, α_p, flux, q_p²). The default grid is the run's own mesh
resolution when it is a built-in pseudo2d/wang2d mesh (seed 001 averages over the grid cell), else bins
of about three particle diameters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from febed.post.grid import BUBBLE_ALPHA, Grid, TimeAverage, bin_sums
from febed.post.rundata import RunInfo, _get, list_snapshots, read_case, read_snapshot, run_info, select_window

QUANTITIES = ("alpha_p", "mass_flux_x", "mass_flux_z", "velocity_x", "velocity_z", "q2", "bubble_frequency")


def default_bins(run_dir: str | Path, info: RunInfo) -> tuple[int, int]:
    """Bin counts of the plane: the built-in mesh's cells, else cells of about 3 particle diameters."""
    from febed.meshing import PSEUDO2D_LEVELS, WANG2D_CELLS

    case = read_case(run_dir)
    builtin = _get(case, "mesh.builtin", "")
    if builtin == "pseudo2d" and _get(case, "mesh.cell", "hexahedron") == "hexahedron":
        (nx, _, nz), _ = PSEUDO2D_LEVELS[_get(case, "mesh.level", "coarse")]
        return nx, nz
    if builtin == "wang2d":
        return tuple(WANG2D_CELLS)
    a, b = info.axes
    h = 3.0 * info.d_p
    return max(1, round((info.hi[a] - info.lo[a]) / h)), max(1, round((info.hi[b] - info.lo[b]) / h))


def make_grid(info: RunInfo, bins: tuple[int, int]) -> Grid:
    """The plane grid over the run's domain box with `bins` (n_horizontal, n_vertical) bins."""
    a, b = info.axes
    if len(bins) != 2:
        raise ValueError(f"bins: expected (n_horizontal, n_vertical), got {bins}")
    return Grid(
        lo=(float(info.lo[a]), float(info.lo[b])),
        hi=(float(info.hi[a]), float(info.hi[b])),
        n=(int(bins[0]), int(bins[1])),
        axes=(a, b),
        depth=info.depth,
    )


@dataclass
class AveragedFields:
    """Time-averaged, depth-averaged fields of a run on a plane grid.

    Attributes:
        info: the run's scales.
        grid: the bins.
        window: the requested time window (s).
        times: the snapshot times averaged (s).
        kernel, agitation: how the fields were made (see febed.post.grid).
        alpha_p: ⟨α_p⟩ (n0, n1).
        mass_flux: ⟨α_p ρ_p U_p⟩ (n0, n1, 3) in kg/m^2/s, components x, y, z.
        velocity: solid-volume-weighted mean particle velocity (n0, n1, 3) m/s.
        q2: agitation energy q_p² (n0, n1) m^2/s^2.
        solid_volume: mean total particle volume in the snapshots (m^3).
        bubble_frequency: share of the snapshots in which each bin's α_p was below `bubble_alpha` (n0, n1).
        bubble_alpha: that threshold.
    """

    info: RunInfo
    grid: Grid
    window: tuple[float, float]
    times: list[float]
    kernel: str
    agitation: str
    alpha_p: np.ndarray
    mass_flux: np.ndarray
    velocity: np.ndarray
    q2: np.ndarray
    solid_volume: float
    bubble_frequency: np.ndarray
    bubble_alpha: float = BUBBLE_ALPHA
    extra: dict = field(default_factory=dict)

    def quantity(self, name: str) -> np.ndarray:
        """A scalar field by name: one of QUANTITIES ('_z' is the vertical component, '_y' in 2D)."""
        v = self.info.axes[1]
        table = {
            "alpha_p": self.alpha_p,
            "mass_flux_x": self.mass_flux[..., 0],
            "mass_flux_z": self.mass_flux[..., v],
            "velocity_x": self.velocity[..., 0],
            "velocity_z": self.velocity[..., v],
            "q2": self.q2,
            "bubble_frequency": self.bubble_frequency,
        }
        if name not in table:
            raise ValueError(f"quantity: expected one of {QUANTITIES}, got {name!r}")
        return table[name]

    def profile(self, name: str, height: float) -> tuple[np.ndarray, np.ndarray]:
        """Horizontal profile (bin-centre x in m, values) of a quantity at `height` (m above the domain bottom).

        Linear interpolation between the two rows of bin centres around the height (the nearest row's
        values beyond the first/last centre).
        """
        zc = self.grid.centres(1) - self.grid.lo[1]
        if not 0.0 <= height <= self.grid.hi[1] - self.grid.lo[1]:
            raise ValueError(f"height: expected 0..{self.grid.hi[1] - self.grid.lo[1]:g} m, got {height}")
        f = self.quantity(name)
        j = int(np.clip(np.searchsorted(zc, height) - 1, 0, len(zc) - 1))
        j1 = min(j + 1, len(zc) - 1)
        t = 0.0 if j1 == j else float(np.clip((height - zc[j]) / (zc[j1] - zc[j]), 0.0, 1.0))
        return self.grid.centres(0), (1.0 - t) * f[:, j] + t * f[:, j1]

    def circulation(self, bed_height: float, centre: float = 1 / 3, wall: float = 0.15) -> tuple[float, float]:
        """Bed-averaged vertical solid flux (kg/m^2/s) in the central part and next to the side walls.

        The mean of ⟨α_p ρ_p U_p,z⟩ over the bins whose centre lies below `bed_height` (m above the bottom)
        and whose centre x/L lies within the central `centre` of the width, resp. the outer `wall` fraction
        on either side: seed 001's double mixing loop has the first positive and the second negative.
        """
        x = (self.grid.centres(0) - self.grid.lo[0]) / (self.grid.hi[0] - self.grid.lo[0])
        zc = self.grid.centres(1) - self.grid.lo[1]
        rows = zc < bed_height
        if not rows.any():
            return math.nan, math.nan
        col = self.quantity("mass_flux_z")[:, rows].mean(axis=1)
        mid = np.abs(x - 0.5) < 0.5 * centre
        side = (x < wall) | (x > 1.0 - wall)
        return (float(col[mid].mean()) if mid.any() else math.nan, float(col[side].mean()) if side.any() else math.nan)

    def bubble_fraction(self, below: float) -> float:
        """The mean bubble frequency of the bins whose centre lies below `below` (m above the bottom).

        The share of that part of the bed which is bubble, averaged over the snapshots: with `below` ≈ 0.8
        times the bed height, 0 for a bed without bubbles (seed 001 Fig 15, frictionless particles).
        """
        zc = self.grid.centres(1) - self.grid.lo[1]
        rows = zc < below
        return float(self.bubble_frequency[:, rows].mean()) if rows.any() else math.nan

    def bed_agitation(self, bed_height: float) -> float:
        """Solid-volume-weighted mean q_p² (m²/s²) of the bins whose centre lies below `bed_height` (m)."""
        rows = self.grid.centres(1) - self.grid.lo[1] < bed_height
        a = self.alpha_p[:, rows]
        return float((self.q2[:, rows] * a).sum() / a.sum()) if a.sum() > 0 else math.nan

    def scales(self) -> dict[str, float]:
        """Seed 001 §4 scales: L, D, H (m), ρU_f (kg/m^2/s), U_f (m/s), d_p/U_f (s)."""
        i = self.info
        return {
            "L": i.width,
            "D": i.depth,
            "H": i.height,
            "U_f": i.u_f,
            "rhoU_f": i.rho_g * i.u_f,
            "t_ref": i.d_p / i.u_f if i.u_f > 0 else math.nan,
        }


def average_fields(
    run_dir: str | Path,
    window: tuple[float, float] | None = None,
    bins: tuple[int, int] | None = None,
    kernel: str = "ngp",
    agitation: str = "cell",
    box: tuple | None = None,
    snapshots: list[tuple[float, Path]] | None = None,
    bubble_alpha: float = BUBBLE_ALPHA,
    visitors: tuple = (),
) -> AveragedFields:
    """Time-averaged (over `window`, s; default the last half) depth-averaged particle fields of a run.

    Args:
        run_dir: a febed output folder (may still be running).
        window: (t0, t1) in s; every complete snapshot with t0 <= t <= t1 counts equally.
        bins: (n_horizontal, n_vertical); default `default_bins`.
        kernel: "ngp" or "cic" (febed.post.grid).
        agitation: "cell" (seed 001) or "window": the mean velocity u' is taken about.
        box: ((xmin, ymin, zmin), (xmax, ymax, zmax)) to override the domain box.
        snapshots: (t, path) list to use instead of the run's particle output (tests).
        bubble_alpha: bins below this instantaneous α_p count as bubble (`bubble_frequency`).
        visitors: objects whose `add(arrays)` sees every snapshot read (e.g. `febed.post.depth.DepthProfile`),
            so that other averages take no second pass over the files.
    """
    info = run_info(run_dir, box)
    snaps = snapshots if snapshots is not None else list_snapshots(run_dir)
    chosen, window = select_window(snaps, window)
    grid = make_grid(info, bins or default_bins(run_dir, info))
    acc = TimeAverage(grid, info.rho_p, bubble_alpha)
    vol = 0.0
    for t, path in chosen:
        a = read_snapshot(path)
        if a is None:
            continue
        acc.add(t, bin_sums(grid, a["pos"], a["velocity"], a["diameter"], kernel))
        for v in visitors:
            v.add(a)
        vol += float((np.pi / 6.0 * a["diameter"] ** 3).sum())
    if acc.count == 0:
        raise ValueError(f"window {window}: none of the {len(chosen)} snapshots could be read")
    res = acc.result(agitation)
    return AveragedFields(
        info=info,
        grid=grid,
        window=window,
        times=acc.times,
        kernel=kernel,
        agitation=agitation,
        alpha_p=res["alpha_p"],
        mass_flux=res["mass_flux"],
        velocity=res["velocity"],
        q2=res["q2"],
        solid_volume=vol / acc.count,
        bubble_frequency=res["bubble_frequency"],
        bubble_alpha=bubble_alpha,
    )
