"""The share of the bed's weight that rests on the bottom wall by contact, from the particle snapshots.

A fluidized bed's gas carries its weight: the bed pressure drop equals W/A. Where part of the bottom lets no
gas in (seed 001's switched-off nozzle, the `bottom_wall` patch), a defluidized heap stands on it, and the
bottom wall carries that part by contact; `dp_bed / (W/A)` then falls short of 1 by about this share.

From each snapshot: the elastic normal force of every particle overlapping the bottom plane (the domain's
lowest face, gravity along −z in 3D, −y in 2D), k_n,w δ with δ = r − (z − z_bottom); summed over the
particles and divided by their buoyant weight (ρ_p − ρ_g) g Σ V_p, then averaged over the snapshots. The
damping force is left out: over a whole contact its time integral is γ [δ] = 0, so it averages out of a long
window. Linear contact laws only; coarse-grained runs (`tm`, `pcpm`, whose contact stiffness depends on the
parcel or group) are not covered (NaN).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from febed.post.rundata import RunInfo, list_snapshots, read_case, read_snapshot, select_window


def wall_stiffness(case: dict) -> float:
    """k_n of particle-wall contacts (N/m) of a resolved case dict as `DEM.from_case` sets it (NaN: coarse grain)."""
    c = case.get("contact", {})
    if case.get("coarse_grain", {}).get("model", "none") in ("tm", "pcpm"):
        return math.nan
    if c.get("stiffness_wall") is not None:
        return float(c["stiffness_wall"])
    if c.get("from_material"):
        from febed.dem.contact import stiffness_from_material

        d = float(case.get("particles", {}).get("diameter", math.nan))
        kn, _ = stiffness_from_material(c["young_modulus"], c["poisson"], 0.5 * d, c["reference_overlap"] * d)
        return float(kn)
    return float(c.get("stiffness", math.nan))


def support_fraction(pos: np.ndarray, diameter: np.ndarray, info: RunInfo, kn_wall: float) -> float:
    """Elastic force of the bottom plane on the particles / their buoyant weight, for one snapshot."""
    v = info.axes[1]
    gap = pos[:, v] - info.lo[v]
    delta = np.maximum(0.5 * diameter - gap, 0.0)
    weight = (info.rho_p - info.rho_g) * info.gravity * float(np.sum(math.pi / 6.0 * diameter**3))
    return kn_wall * float(delta.sum()) / weight if weight > 0 else math.nan


def bottom_support(run_dir: str | Path, info: RunInfo, window: tuple[float, float] | None = None) -> float:
    """Time average over the snapshots in `window` of `support_fraction` (NaN if not computable)."""
    kn = wall_stiffness(read_case(run_dir))
    if not math.isfinite(kn):
        return math.nan
    chosen, _ = select_window(list_snapshots(run_dir), window)
    values = []
    for _, path in chosen:
        a = read_snapshot(path)
        if a is not None:
            values.append(support_fraction(a["pos"], a["diameter"], info, kn))
    return float(np.mean(values)) if values else math.nan
