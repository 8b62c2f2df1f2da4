"""Interpolation of nodal fields to particle centres with the node weights (seed 001 eq 28).

Φ_@p = Σ_{i∈C} ω_{p,i} Φ_i over the nodes of the cell C holding particle p. Works for scalars (nd,) and
vectors (nd, k) (u (nd, gdim), ∇p (nd, gdim), ε (nd,)); nodal values must be current on ghost dofs.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from febed.coupling.mesh_arrays import TETRAHEDRON, TRIANGLE, MeshArrays


@njit(cache=True)
def interpolate_kernel(cell_dofs, cell, w, nodal, out):
    """out[p, :] = Σ_i w[p, i] nodal[dof_i, :] for particles with cell >= 0; zero otherwise (seed 001 eq 28)."""
    nv = w.shape[1]
    k = nodal.shape[1]
    for p in range(cell.size):
        for a in range(k):
            out[p, a] = 0.0
        c = cell[p]
        if c < 0:
            continue
        for i in range(nv):
            wi = w[p, i]
            dof = cell_dofs[c, i]
            for a in range(k):
                out[p, a] += wi * nodal[dof, a]


def interpolate(ma: MeshArrays, cell: np.ndarray, w: np.ndarray, nodal: np.ndarray, out=None) -> np.ndarray:
    """Values of a nodal field (nd,) or (nd, k) at the particles: (N,) or (N, k); zero for unlocated particles."""
    if nodal.shape[0] != ma.num_dofs:
        raise ValueError(f"nodal: first dimension must be the local dof count {ma.num_dofs}, got {nodal.shape}")
    vec = nodal.reshape(nodal.shape[0], -1)
    res = np.empty((cell.size, vec.shape[1])) if out is None else out.reshape(cell.size, -1)
    interpolate_kernel(ma.cell_dofs, cell, w, vec, res)
    return res.reshape(cell.size) if nodal.ndim == 1 else res.reshape(cell.size, *nodal.shape[1:])


@njit(cache=True)
def gradient_kernel(kind, gdim, cell_dofs, x_dofs, cell, ref, nodal, out):
    """out[p, :gdim] = ∇Φ_h at the particle: gradient of the P1/Q1 field of nodal scalar Φ in its cell (1/m)."""
    J = np.zeros((3, 3))
    r = np.zeros(3)
    g = np.zeros(3)
    dphi = np.zeros((8, 3))
    simplex = kind == TRIANGLE or kind == TETRAHEDRON
    nv = cell_dofs.shape[1]
    for p in range(cell.size):
        for a in range(3):
            out[p, a] = 0.0
        c = cell[p]
        if c < 0:
            continue
        # reference gradients of the basis at ref[p]
        for k in range(nv):
            for b in range(gdim):
                if simplex:
                    dphi[k, b] = -1.0 if k == 0 else (1.0 if k == b + 1 else 0.0)
                else:
                    v = 1.0
                    for e in range(gdim):
                        bit = (k >> e) & 1
                        if e == b:
                            v *= 1.0 if bit else -1.0
                        else:
                            v *= ref[p, e] if bit else 1.0 - ref[p, e]
                    dphi[k, b] = v
        # Jacobian and reference gradient of Φ
        for a in range(gdim):
            r[a] = 0.0
            for b in range(gdim):
                J[a, b] = 0.0
        for k in range(nv):
            xk = x_dofs[cell_dofs[c, k]]
            fk = nodal[cell_dofs[c, k]]
            for b in range(gdim):
                r[b] += dphi[k, b] * fk
                for a in range(gdim):
                    J[a, b] += xk[a] * dphi[k, b]
        # ∇Φ = J^{-T} ∇_ξ Φ: solve J^T g = r
        for a in range(gdim):
            for b in range(a + 1, gdim):
                J[a, b], J[b, a] = J[b, a], J[a, b]
        _solve_t(gdim, J, r, g)
        for a in range(gdim):
            out[p, a] = g[a]


@njit(cache=True)
def _solve_t(gdim, A, r, out):
    """Solve A out = r (2x2 or 3x3) by Cramer's rule."""
    if gdim == 2:
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        out[0] = (r[0] * A[1, 1] - A[0, 1] * r[1]) / det
        out[1] = (A[0, 0] * r[1] - r[0] * A[1, 0]) / det
        return
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
    c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    c10 = A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]
    c11 = A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]
    c12 = A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1]
    c20 = A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]
    c21 = A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]
    c22 = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    out[0] = (c00 * r[0] + c10 * r[1] + c20 * r[2]) / det
    out[1] = (c01 * r[0] + c11 * r[1] + c21 * r[2]) / det
    out[2] = (c02 * r[0] + c12 * r[1] + c22 * r[2]) / det


def gradient_at_particles(ma: MeshArrays, cell: np.ndarray, ref: np.ndarray, nodal: np.ndarray, out=None):
    """Gradient (N, 3) of the P1/Q1 field of a nodal scalar (nd,) at the particles (cellwise; zero if unlocated).

    An alternative to interpolating a nodal ∇p: the exact gradient of the discrete pressure in each cell.
    """
    if nodal.shape != (ma.num_dofs,):
        raise ValueError(f"nodal: must have shape ({ma.num_dofs},), got {nodal.shape}")
    res = np.empty((cell.size, 3)) if out is None else out
    gradient_kernel(ma.kind, ma.gdim, ma.cell_dofs, ma.x_dofs, cell, ref, nodal, res)
    return res
