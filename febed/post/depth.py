"""Profiles across the depth (y) of a pseudo-2D bed: is the bed two-dimensional (seed 001 Fig 11)?

Seed 001 averages every field over the depth because "the hydrodynamic variations in the depth direction
are negligible", shown by the time-averaged vertical particle velocity across the depth at z/H = 0.16
(its Fig 11). `DepthProfile` measures the same in a febed run: in the slab of the plane grid's bin row that
holds the height, the particles are binned by their depth coordinate, and

    U_p,z(y) = Σ_snapshots Σ_particles V_p u_p,z / Σ_snapshots Σ_particles V_p

(the solid-volume-weighted time average: the time-averaged vertical flux over the time-averaged solid
fraction of the bin), over the whole width and over the bands of `AveragedFields.circulation`: the central
third and the outer 15 % on both sides. `spread` is max − min of a band's profile: ~0 for a bed that is
two-dimensional, large when the solid circulates across the depth (up in the middle plane, down along the
front and back walls). `asymmetry` is (front − back) / (front + back) of the slab's solid volume, the front
being the half y < D/2: ~0 for a bed symmetric across the depth.

Only 3D runs have a depth to profile; the default depth bins are the built-in pseudo2d mesh's cells across
the depth (seed 001 Table 2: 3 / 6 / 12), else bins of about three particle diameters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from febed.post.grid import Grid
from febed.post.rundata import RunInfo, _get, read_case

DEPTH_HEIGHT = 0.16  # z/H of seed 001 Fig 11
BANDS = ("all", "centre", "walls")


def default_depth_bins(run_dir, info: RunInfo) -> int:
    """Bins across the depth: the built-in pseudo2d mesh's cells, else about three particle diameters."""
    from febed.meshing import PSEUDO2D_LEVELS

    case = read_case(run_dir)
    if _get(case, "mesh.builtin", "") == "pseudo2d" and _get(case, "mesh.cell", "hexahedron") == "hexahedron":
        (_, ny, _), _ = PSEUDO2D_LEVELS[_get(case, "mesh.level", "coarse")]
        return int(ny)
    return max(1, round(info.depth / (3.0 * info.d_p)))


@dataclass
class DepthProfile:
    """Accumulates the solid-volume-weighted vertical particle velocity across the depth at one height.

    Use: `p = DepthProfile(info, grid, ny)`; `p.add(arrays)` per snapshot (`read_snapshot`'s dict); then
    `p.velocity(band)`, `p.share(band)`, `p.spread(band)`.
    """

    info: RunInfo
    grid: Grid
    ny: int
    height: float = DEPTH_HEIGHT
    centre: float = 1.0 / 3.0
    wall: float = 0.15
    snapshots: int = 0
    _sv: dict = field(default_factory=dict, repr=False)  # band -> Σ V u_z per depth bin
    _s0: dict = field(default_factory=dict, repr=False)  # band -> Σ V per depth bin

    def __post_init__(self):
        if self.info.dim != 3:
            raise ValueError("depth profiles need a 3D run (a 2D run has no depth to profile)")
        if self.ny < 1:
            raise ValueError(f"depth bins: expected >= 1, got {self.ny}")
        if not 0.0 <= self.height <= 1.0:
            raise ValueError(f"depth profile height: expected z/H in [0, 1], got {self.height}")
        for b in BANDS:
            self._sv[b] = np.zeros(self.ny)
            self._s0[b] = np.zeros(self.ny)
        v = self.grid.axes[1]
        z = self.info.lo[v] + self.height * self.info.height
        row = min(int((z - self.grid.lo[1]) / self.grid.spacing[1]), self.grid.n[1] - 1)
        self.slab = (self.grid.lo[1] + row * self.grid.spacing[1], self.grid.lo[1] + (row + 1) * self.grid.spacing[1])

    @property
    def y_over_d(self) -> np.ndarray:
        """Bin centres across the depth, as y/D."""
        return (np.arange(self.ny) + 0.5) / self.ny

    def add(self, arrays: dict) -> None:
        """Add one snapshot: arrays with 'pos' (n, 3), 'velocity' (n, 3), 'diameter' (n,)."""
        pos, vel = arrays["pos"], arrays["velocity"]
        a, v = self.grid.axes
        d = 3 - a - v  # the depth axis
        inside = (pos[:, v] >= self.slab[0]) & (pos[:, v] < self.slab[1])
        xl = (pos[inside, a] - self.info.lo[a]) / self.info.width
        j = np.clip(((pos[inside, d] - self.info.lo[d]) / self.info.depth * self.ny).astype(np.int64), 0, self.ny - 1)
        vol = math.pi / 6.0 * arrays["diameter"][inside] ** 3
        uz = vel[inside, v]
        half = 0.5 * self.centre
        masks = {
            "all": np.ones(xl.size, dtype=bool),
            "centre": np.abs(xl - 0.5) < half,
            "walls": (xl < self.wall) | (xl > 1.0 - self.wall),
        }
        for b, m in masks.items():
            self._sv[b] += np.bincount(j[m], weights=vol[m] * uz[m], minlength=self.ny)
            self._s0[b] += np.bincount(j[m], weights=vol[m], minlength=self.ny)
        self.snapshots += 1

    def velocity(self, band: str = "all") -> np.ndarray:
        """Solid-volume-weighted time-averaged U_p,z per depth bin (m/s); NaN where no particle came."""
        s0 = self._s0[band]
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(s0 > 0, self._sv[band] / np.where(s0 > 0, s0, 1.0), np.nan)

    def share(self, band: str = "all") -> np.ndarray:
        """Share of the band's solid volume in each depth bin (sums to 1)."""
        s0 = self._s0[band]
        total = s0.sum()
        return s0 / total if total > 0 else np.full(self.ny, np.nan)

    def asymmetry(self) -> float:
        """(front − back) / (front + back) of the slab's solid volume over the whole width (front: y < D/2)."""
        s0 = self._s0["all"]
        w = np.clip(self.ny / 2.0 - np.arange(self.ny), 0.0, 1.0)  # share of each bin in the front half
        front, back = float((w * s0).sum()), float(((1.0 - w) * s0).sum())
        return (front - back) / (front + back) if front + back > 0 else math.nan

    def spread(self, band: str = "all") -> float:
        """The band's profile's max − min (m/s); NaN when a bin holds no particle."""
        u = self.velocity(band)
        return float(u.max() - u.min()) if np.all(np.isfinite(u)) else math.nan
