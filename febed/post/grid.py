"""Particles -> Eulerian fields on a Cartesian grid of the bed's plane, averaged over the depth.

The grid covers the domain box in the plane (x, z) in 3D — each bin spans the whole depth y, so a bin
value is the depth average ⟨ψ⟩_xz of seed 001 §4 — and (x, y) in 2D, where the bin volume uses the
case's depth (one particle diameter by default; docs/theory.md, 2D cases). Bin volume ΔV = Δx Δz D.

Kernels (how a particle's volume is shared among bins; the weights of one particle sum to 1):

* ``"ngp"`` (default): nearest grid point — the whole particle volume V_p = π d³/6 goes to the bin that
  holds its centre. This is seed 001's "spatial average over the grid cell" (§4).
* ``"cic"``: cloud in cell — bilinear weights between the four nearest bin centres; weight that would fall
  outside the domain is folded back into the boundary bin, so the total volume is conserved.

Per snapshot and bin b, with weights w_pb:

* solid volume fraction  α_p = Σ_p w_pb V_p / ΔV
* solid mass flux        α_p ρ_p U_p = Σ_p w_pb ρ_p V_p u_p / ΔV   (U_p: the volume-weighted bin mean)
* agitation energy       q_p² = Σ_p w_pb V_p |u_p − U_p|² / Σ_p w_pb V_p   (seed 001 §4.2, u' = u − U_p)

Velocity components are kept in 3D (x, y, z) whatever the plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KERNELS = ("ngp", "cic")


@dataclass(frozen=True)
class Grid:
    """A uniform grid of n[0] x n[1] bins over [lo, hi] in the plane axes `axes`, spanning `depth`.

    Attributes:
        lo, hi: bounds (m) along the plane's horizontal and vertical axes.
        n: number of bins along each.
        axes: indices of the plane's axes in the 3-vectors: (0, 2) in 3D, (0, 1) in 2D.
        depth: extent of each bin along the averaged direction (m).
    """

    lo: tuple[float, float]
    hi: tuple[float, float]
    n: tuple[int, int]
    axes: tuple[int, int]
    depth: float

    def __post_init__(self):
        if len(self.n) != 2 or any(int(k) < 1 for k in self.n):
            raise ValueError(f"bins: expected two bin counts >= 1, got {self.n}")
        if any(h <= lo for lo, h in zip(self.lo, self.hi, strict=True)):
            raise ValueError(f"grid bounds: need hi > lo along both axes, got lo={self.lo} hi={self.hi}")
        if not self.depth > 0:
            raise ValueError(f"depth: expected > 0 m, got {self.depth}")

    @property
    def spacing(self) -> np.ndarray:
        """Bin sizes (Δ_horizontal, Δ_vertical) in m."""
        return (np.asarray(self.hi) - np.asarray(self.lo)) / np.asarray(self.n)

    @property
    def bin_volume(self) -> float:
        """ΔV = Δx Δz D (m^3)."""
        h = self.spacing
        return float(h[0] * h[1] * self.depth)

    def centres(self, k: int) -> np.ndarray:
        """Bin-centre coordinates (m) along plane axis k (0: horizontal, 1: vertical)."""
        return self.lo[k] + (np.arange(self.n[k]) + 0.5) * self.spacing[k]


def bin_weights(grid: Grid, pos: np.ndarray, kernel: str = "ngp") -> tuple[np.ndarray, np.ndarray]:
    """Flat bin indices and weights (m, k) of each particle's k = 1 (ngp) or 4 (cic) bins; rows sum to 1."""
    if kernel not in KERNELS:
        raise ValueError(f"kernel: expected one of {KERNELS}, got {kernel!r}")
    h = grid.spacing
    idx, wts = [], []
    for k, a in enumerate(grid.axes):
        s = (pos[:, a] - grid.lo[k]) / h[k]
        if kernel == "ngp":
            i = np.clip(np.floor(s).astype(np.int64), 0, grid.n[k] - 1)
            idx.append(i[:, None])
            wts.append(np.ones((pos.shape[0], 1)))
        else:
            f = s - 0.5
            i0 = np.floor(f).astype(np.int64)
            t = f - i0
            # folding: indices outside [0, n-1] are clipped onto the boundary bin, keeping their weight
            idx.append(np.stack([np.clip(i0, 0, grid.n[k] - 1), np.clip(i0 + 1, 0, grid.n[k] - 1)], axis=1))
            wts.append(np.stack([1.0 - t, t], axis=1))
    flat = (idx[0][:, :, None] * grid.n[1] + idx[1][:, None, :]).reshape(pos.shape[0], -1)
    w = (wts[0][:, :, None] * wts[1][:, None, :]).reshape(pos.shape[0], -1)
    return flat, w


def _deposit(grid: Grid, flat: np.ndarray, w: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Σ_p w_pb values_p per bin, shape (n0, n1)."""
    nb = grid.n[0] * grid.n[1]
    s = np.bincount(flat.ravel(), weights=(w * values[:, None]).ravel(), minlength=nb)
    return s.reshape(grid.n)


@dataclass
class BinSums:
    """Per-bin sums of one snapshot: S0 = Σ wV, S1 = Σ wV u (n0, n1, 3), S2 = Σ wV |u|², Q = Σ wV |u − U_b|²."""

    s0: np.ndarray
    s1: np.ndarray
    s2: np.ndarray
    q: np.ndarray


def bin_sums(grid: Grid, pos: np.ndarray, vel: np.ndarray, diameter: np.ndarray, kernel: str = "ngp") -> BinSums:
    """Volume-weighted per-bin sums of a snapshot (m^3, m^4/s, m^5/s^2); see the module docstring."""
    pos = np.asarray(pos, dtype=float).reshape(-1, 3)
    vel = np.asarray(vel, dtype=float).reshape(-1, 3)
    vol = np.pi / 6.0 * np.asarray(diameter, dtype=float) ** 3
    if not (pos.shape[0] == vel.shape[0] == vol.shape[0]):
        raise ValueError(f"pos, vel, diameter: lengths differ ({pos.shape[0]}, {vel.shape[0]}, {vol.shape[0]})")
    flat, w = bin_weights(grid, pos, kernel)
    s0 = _deposit(grid, flat, w, vol)
    s1 = np.stack([_deposit(grid, flat, w, vol * vel[:, c]) for c in range(3)], axis=-1)
    s2 = _deposit(grid, flat, w, vol * (vel**2).sum(axis=1))
    # second pass: fluctuations about the bin's own mean velocity (exact, no S2 - S1²/S0 cancellation)
    mean = np.divide(s1, s0[..., None], out=np.zeros_like(s1), where=s0[..., None] > 0).reshape(-1, 3)
    du2 = ((vel[:, None, :] - mean[flat]) ** 2).sum(axis=2)  # (m, k)
    nb = grid.n[0] * grid.n[1]
    q = np.bincount(flat.ravel(), weights=(w * vol[:, None] * du2).ravel(), minlength=nb).reshape(grid.n)
    return BinSums(s0=s0, s1=s1, s2=s2, q=q)


def snapshot_fields(grid: Grid, sums: BinSums, rho_p: float) -> dict[str, np.ndarray]:
    """Instantaneous fields of one snapshot: alpha_p, mass_flux (kg/m^2/s, 3 comps), velocity U_p, q2 (m^2/s^2)."""
    dv = grid.bin_volume
    has = sums.s0 > 0
    vel = np.divide(sums.s1, sums.s0[..., None], out=np.zeros_like(sums.s1), where=has[..., None])
    q2 = np.divide(sums.q, sums.s0, out=np.zeros_like(sums.q), where=has)
    return {"alpha_p": sums.s0 / dv, "mass_flux": rho_p * sums.s1 / dv, "velocity": vel, "q2": q2}


BUBBLE_ALPHA = 0.15  # a bin with α_p below this in a snapshot is bubble (ε > 0.85)


class TimeAverage:
    """Accumulates snapshots and gives the time-averaged fields (see `result` for the definitions)."""

    def __init__(self, grid: Grid, rho_p: float, bubble_alpha: float = BUBBLE_ALPHA):
        """Empty accumulator on `grid` for particles of density `rho_p` (kg/m^3).

        bubble_alpha: a bin whose instantaneous α_p is below it counts as bubble (void) in that snapshot.
        """
        if not 0.0 < bubble_alpha < 1.0:
            raise ValueError(f"bubble_alpha: expected a solid fraction in (0, 1), got {bubble_alpha}")
        self.grid = grid
        self.rho_p = float(rho_p)
        self.bubble_alpha = float(bubble_alpha)
        shape = tuple(grid.n)
        self.count = 0
        self.times: list[float] = []
        self.s0 = np.zeros(shape)
        self.s1 = np.zeros((*shape, 3))
        self.s2 = np.zeros(shape)
        self.q = np.zeros(shape)
        self.voids = np.zeros(shape)  # snapshots in which the bin was void (α_p < bubble_alpha)

    def add(self, t: float, sums: BinSums) -> None:
        """Add the sums of the snapshot at time t (s)."""
        self.count += 1
        self.times.append(float(t))
        self.s0 += sums.s0
        self.s1 += sums.s1
        self.s2 += sums.s2
        self.q += sums.q
        self.voids += sums.s0 < self.bubble_alpha * self.grid.bin_volume

    def result(self, agitation: str = "cell") -> dict[str, np.ndarray]:
        """Time averages over the snapshots added (each snapshot counts equally).

        * alpha_p, mass_flux: arithmetic means of the snapshot fields.
        * velocity: the solid-volume-weighted mean U_p = mean flux / (ρ_p mean α_p) (0 where no particle).
        * q2 with agitation="cell" (seed 001 §4.2): u' about the bin's instantaneous mean U_p, then
          averaged over time weighted by the solid volume: Σ_t Σ_p V|u − U_b(t)|² / Σ_t Σ_p V.
          With agitation="window": u' about the time-averaged U_p of the bin (adds the bubble-scale,
          time-resolved fluctuations): Σ_t Σ_p V|u|²/Σ V − |U_p|².
        * bubble_frequency: the share of the snapshots in which the bin's α_p was below `bubble_alpha`
          (seed 001 Fig 15's bubbles, counted: 0 in a bin that is never void, 1 in one always void).
        """
        if agitation not in ("cell", "window"):
            raise ValueError(f"agitation: expected 'cell' or 'window', got {agitation!r}")
        if self.count == 0:
            raise ValueError("no snapshot was added to the time average")
        dv = self.grid.bin_volume
        has = self.s0 > 0
        vel = np.divide(self.s1, self.s0[..., None], out=np.zeros_like(self.s1), where=has[..., None])
        if agitation == "cell":
            q2 = np.divide(self.q, self.s0, out=np.zeros_like(self.q), where=has)
        else:
            q2 = np.divide(self.s2, self.s0, out=np.zeros_like(self.s2), where=has) - (vel**2).sum(axis=-1)
            q2 = np.maximum(q2, 0.0)
        return {
            "alpha_p": self.s0 / (dv * self.count),
            "mass_flux": self.rho_p * self.s1 / (dv * self.count),
            "velocity": vel,
            "q2": q2,
            "bubble_frequency": self.voids / self.count,
        }
