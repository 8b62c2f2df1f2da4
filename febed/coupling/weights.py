"""Node weights ω_{p,i} of a particle in its cell: P1 barycentric / Q1 multilinear (seed 001 eq 28).

The same weights serve interpolation (grid -> particle) and projection (particle -> grid). They sum to 1
in every cell (seed 001 eq 28) and are ordered like the cell's dofs (DOLFINx reference vertex order).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from febed.coupling.mesh_arrays import NUM_VERTICES, QUADRILATERAL, TETRAHEDRON, TRIANGLE, MeshArrays


@njit(cache=True, inline="always")
def fill_weights(kind, xi, eta, zeta, w, p):
    """Row p of w: the P1/Q1 basis values at reference coordinates (ξ, η, ζ) (seed 001 eq 28)."""
    if kind == TRIANGLE:  # barycentric
        w[p, 0] = 1.0 - xi - eta
        w[p, 1] = xi
        w[p, 2] = eta
    elif kind == TETRAHEDRON:
        w[p, 0] = 1.0 - xi - eta - zeta
        w[p, 1] = xi
        w[p, 2] = eta
        w[p, 3] = zeta
    elif kind == QUADRILATERAL:  # bilinear, vertex k at bits of k
        w[p, 0] = (1.0 - xi) * (1.0 - eta)
        w[p, 1] = xi * (1.0 - eta)
        w[p, 2] = (1.0 - xi) * eta
        w[p, 3] = xi * eta
    else:  # trilinear
        for k in range(8):
            a = xi if k & 1 else 1.0 - xi
            b = eta if (k >> 1) & 1 else 1.0 - eta
            c = zeta if (k >> 2) & 1 else 1.0 - zeta
            w[p, k] = a * b * c


@njit(cache=True)
def weights_kernel(kind, ref, cell, w):
    """Fill w (N, nv) with the P1/Q1 basis values at reference coordinates ref (N, 3); zero where cell < 0."""
    nv = w.shape[1]
    for p in range(ref.shape[0]):
        if cell[p] < 0:
            for k in range(nv):
                w[p, k] = 0.0
        else:
            fill_weights(kind, ref[p, 0], ref[p, 1], ref[p, 2], w, p)


def compute_weights(ma: MeshArrays, ref: np.ndarray, cell: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Weights ω_{p,i} (N, nv) of each particle on its cell's nodes from reference coordinates ref (N, 3)."""
    nv = NUM_VERTICES[ma.kind]
    if ref.ndim != 2 or ref.shape[1] != 3:
        raise ValueError(f"ref: must have shape (N, 3), got {ref.shape}")
    w = np.empty((ref.shape[0], nv)) if out is None else out
    if w.shape != (ref.shape[0], nv):
        raise ValueError(f"out: must have shape ({ref.shape[0]}, {nv}), got {w.shape}")
    weights_kernel(ma.kind, ref, cell, w)
    return w
