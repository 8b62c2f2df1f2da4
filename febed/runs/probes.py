"""The probe quantities of a coupled run: cross-section averages of nodal fields and the bed height.

`SectionAverage` samples a cross-section of the mesh on a uniform grid of points located once (midpoint rule;
points outside the mesh are dropped) and averages a nodal field over them. `bed_height` is the height (along
gravity) below which a given fraction of the particle volume lies. Both are collective under MPI.
"""

from __future__ import annotations

import math

from mpi4py import MPI

import numpy as np

from febed.coupling.interpolate import interpolate
from febed.coupling.locate import FOUND, locate
from febed.coupling.weights import compute_weights


class SectionAverage:
    """Cross-section average of a nodal field at a fixed height, from sample points located once."""

    def __init__(self, ma, axis: int, height: float, lo: np.ndarray, hi: np.ndarray, per_dim: int = 40):
        """Sample points on a uniform grid over the box [lo, hi] of the cross-section at `height`."""
        gdim = ma.gdim
        others = [a for a in range(gdim) if a != axis]
        axes = [lo[a] + (np.arange(per_dim) + 0.5) * (hi[a] - lo[a]) / per_dim for a in others]
        grid = np.meshgrid(*axes, indexing="ij")
        pts = np.zeros((grid[0].size, 3))
        for a, g in zip(others, grid, strict=True):
            pts[:, a] = g.ravel()
        pts[:, axis] = height
        cell = np.full(pts.shape[0], -1, dtype=np.int32)
        cell, ref, status, _, _ = locate(ma, pts, cell)
        keep = (status == FOUND) & (cell < ma.num_owned_cells)
        self.ma = ma
        self.cell = np.ascontiguousarray(cell[keep])
        self.w = compute_weights(ma, np.ascontiguousarray(ref[keep]), self.cell)
        self.count = ma.comm.allreduce(int(keep.sum())) if ma.comm is not None else int(keep.sum())
        if self.count == 0:
            raise ValueError(f"probe height {height} m lies outside the mesh")

    def __call__(self, nodal: np.ndarray) -> float:
        """The average of nodal field `nodal` (nd,) over the section (collective)."""
        local = float(interpolate(self.ma, self.cell, self.w, nodal).sum())
        total = self.ma.comm.allreduce(local) if self.ma.comm is not None else local
        return total / self.count


def bed_height(heights: np.ndarray, volumes: np.ndarray, fraction: float, comm=MPI.COMM_WORLD) -> float:
    """Height below which `fraction` of the particle volume lies (m); NaN without particles (collective)."""
    h = np.concatenate(comm.allgather(np.asarray(heights, dtype=float)))
    v = np.concatenate(comm.allgather(np.asarray(volumes, dtype=float)))
    if h.size == 0:
        return math.nan
    order = np.argsort(h, kind="stable")
    cum = np.cumsum(v[order])
    k = int(np.searchsorted(cum, fraction * cum[-1]))
    return float(h[order][min(k, h.size - 1)])
