r"""Simpler coarse grain (SCG), seed 003 eq 7: ρ_CG d_CG² = ρ_O d_O².

With Stokes drag (C_d = 24/Re, seed 003 eq 5) the drag acceleration of a sphere is 18 μ (u - v) / (ρ_p d²),
so a CG particle of diameter d_CG and density ρ_O d_O²/d_CG² has exactly the acceleration of the original
(seed 003 eq 6): same speed history in any prescribed flow, gravity included, collisions excepted.
An SCG particle is a plain DEM particle of its own diameter and the reduced density: its drag is evaluated
on its own diameter (`n_orig` = 1 in the particle arrays; it *stands for* ratio³ originals by volume, which
matters only for statistics). It is meant for dilute, drag-dominated, one-way flows; its mass is not
conserved (m_CG = ratio m_O per CG particle, ratio² less than the ratio³ originals it replaces).
"""

from __future__ import annotations

import numpy as np


def scg_density(rho_orig, d_orig, d_cg):
    """CG particle density ρ_CG = ρ_O d_O² / d_CG² (kg/m^3) of seed 003 eq 7 (scalars or arrays)."""
    rho_orig = np.asarray(rho_orig, dtype=float)
    d_orig = np.asarray(d_orig, dtype=float)
    d_cg = np.asarray(d_cg, dtype=float)
    if np.any(rho_orig <= 0) or np.any(d_orig <= 0) or np.any(d_cg <= 0):
        raise ValueError("rho_orig, d_orig, d_cg: must be > 0")
    r = rho_orig * d_orig**2 / d_cg**2
    return float(r) if r.ndim == 0 else r


def scg_particles(d_orig: float, rho_orig: float, ratio: float) -> tuple[float, float]:
    """Diameter (m) and density (kg/m^3) of an SCG particle `ratio` times larger than the original."""
    if not ratio >= 1.0:
        raise ValueError(f"coarse_grain.ratio: must be >= 1, got {ratio}")
    d = d_orig * ratio
    return d, scg_density(rho_orig, d_orig, d)


def scg_count(count_orig: int, ratio: float) -> int:
    """SCG particles that carry the same solid volume as count_orig originals: round(count_orig / ratio³), >= 1."""
    return max(1, int(round(count_orig / ratio**3)))
