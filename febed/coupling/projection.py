"""Projection of particle quantities onto the nodes, conservative neighbour filter, solid/void fraction.

Seed 001 eqs 29-30: Σ_p ω_{p,i} q_p onto the nodes i of the cell holding p (extensive nodal sums), then the
neighbour filter (eqs 31-34), then division by the node control volume ΔV_i = ∫φ_i dx.

Filter reading (DESIGN.md "Readings"): the intensive filter of eq 31 is node -> cell -> node,
    Φ̂_i = Σ_{K∋i} (S_{K,i}/ΔV_i) Φ_K,  Φ_K = (1/|K|) Σ_{j∈K} S_{K,j} Φ_j   (S_{K,i} = ∫_K φ_i dx),
i.e. the cell value is the exact cell mean of the P1/Q1 field; on simplices S_{K,i} = |K|/(d+1) and it is
eq 31 itself, on uniform grids eqs 32-33. It is applied to extensive sums E_j = ΔV_j Φ_j in its transposed,
column-stochastic form
    Ê_i = Σ_{K∋i} (S_{K,i}/|K|) Σ_{j∈K} (S_{K,j}/ΔV_j) E_j,
so Σ_i Ê_i = Σ_j E_j exactly (eq 34) on any mesh; because ΔV_i F_ij = Σ_K S_{K,i} S_{K,j}/|K| is symmetric,
this is the same as filtering the intensive field and multiplying back by ΔV_i (constants are preserved).

With MPI, each rank sums over its particles and owned cells; `MeshArrays.accumulate` adds the ghost-dof
contributions into their owners and refreshes the ghosts (reverse then forward scatter), so the result is
exact across the partition. Every particle must be projected by exactly one rank.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from febed.coupling.mesh_arrays import MeshArrays


@njit(cache=True)
def project_kernel(cell_dofs, cell, w, values, nodal):
    """nodal[dof_i, :] += w[p, i] values[p, :] for the particles with cell >= 0 (seed 001 eqs 29-30).

    Returns the number of particles skipped because they are not located (cell < 0).
    """
    nv = w.shape[1]
    k = values.shape[1]
    skipped = 0
    for p in range(cell.size):
        c = cell[p]
        if c < 0:
            skipped += 1
            continue
        for i in range(nv):
            wi = w[p, i]
            dof = cell_dofs[c, i]
            for a in range(k):
                nodal[dof, a] += wi * values[p, a]
    return skipped


@njit(cache=True)
def filter_kernel(cell_dofs, num_owned_cells, share, cell_volume, node_volume, extensive, out):
    """One pass of the transposed neighbour filter on extensive nodal sums over owned cells (seed 001 eqs 31-34).

    out[i] += Σ_{K∋i} (S_Ki/|K|) Σ_{j∈K} (S_Kj/ΔV_j) E_j; `out` must be zeroed by the caller.
    """
    nv = cell_dofs.shape[1]
    k = extensive.shape[1]
    acc = np.zeros(k)
    for c in range(num_owned_cells):
        for a in range(k):
            acc[a] = 0.0
        for j in range(nv):
            dof = cell_dofs[c, j]
            f = share[c, j] / node_volume[dof]
            for a in range(k):
                acc[a] += f * extensive[dof, a]
        inv = 1.0 / cell_volume[c]
        for i in range(nv):
            dof = cell_dofs[c, i]
            f = share[c, i] * inv
            for a in range(k):
                out[dof, a] += f * acc[a]


def _as2d(a: np.ndarray, n: int, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.shape[0] != n or a.ndim not in (1, 2):
        raise ValueError(f"{name}: must have shape ({n},) or ({n}, k), got {a.shape}")
    return a.reshape(n, a.shape[1] if a.ndim == 2 else 1)  # (not -1: no particles is fine)


def project(ma: MeshArrays, cell: np.ndarray, w: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Extensive nodal sums Σ_p ω_{p,i} q_p (nd,) or (nd, k), summed over ranks (collective; seed 001 eqs 29-30).

    Args:
        ma: mesh arrays.
        cell: (N,) int32 cell of each particle (-1: skipped).
        w: (N, nv) weights from `compute_weights`.
        values: (N,) or (N, k) particle quantities (e.g. volume m^3, K kg/s, K v N, force N).
    """
    n = cell.size
    vals = _as2d(values, n, "values")
    if w.shape[0] != n:
        raise ValueError(f"w: must have {n} rows (one per particle), got {w.shape}")
    nodal = np.zeros((ma.num_dofs, vals.shape[1]))
    project_kernel(ma.cell_dofs, cell, w, vals, nodal)
    ma.accumulate(nodal)
    return nodal.reshape(ma.num_dofs) if np.ndim(values) == 1 else nodal


def neighbour_filter(ma: MeshArrays, extensive: np.ndarray, passes: int = 1) -> np.ndarray:
    """Apply `passes` passes of the conservative neighbour filter to extensive nodal sums (new array; collective).

    `extensive` is (nd,) or (nd, k), consistent on ghost dofs (as returned by `project`); Σ over owned dofs is
    conserved to round-off on any mesh and any partition (seed 001 eq 34).
    """
    if not isinstance(passes, int | np.integer) or passes < 0:
        raise ValueError(f"passes: must be an integer >= 0, got {passes!r}")
    cur = _as2d(extensive, ma.num_dofs, "extensive").copy()
    for _ in range(passes):
        out = np.zeros_like(cur)
        filter_kernel(ma.cell_dofs, ma.num_owned_cells, ma.cell_node_share, ma.cell_volume, ma.node_volume, cur, out)
        ma.accumulate(out)
        cur = out
    return cur.reshape(extensive.shape)


def solid_fraction(ma: MeshArrays, nodal_volume: np.ndarray, floor: float = 0.0):
    """Solid fraction α_i = V̂_i/ΔV_i and void fraction ε_i = max(1 - α_i, floor) at the nodes (seed 001 eq 30).

    Returns (alpha (nd,), eps (nd,), number of owned nodes clipped to `floor`, summed over ranks).
    """
    if not 0.0 <= floor <= 1.0:
        raise ValueError(f"floor: the void-fraction floor must be in [0, 1], got {floor}")
    if nodal_volume.shape != (ma.num_dofs,):
        raise ValueError(f"nodal_volume: must have shape ({ma.num_dofs},), got {nodal_volume.shape}")
    alpha = nodal_volume / ma.node_volume
    eps = np.minimum(1.0 - alpha, 1.0)  # round-off in the filter must not give ε > 1
    low = eps < floor
    clipped = int(np.count_nonzero(low[: ma.num_owned_dofs]))
    eps[low] = floor
    if ma.comm is not None and ma.comm.size > 1:
        clipped = ma.comm.allreduce(clipped)
    return alpha, eps, clipped


def per_volume(ma: MeshArrays, extensive: np.ndarray) -> np.ndarray:
    """Nodal density of an extensive nodal sum: E_i/ΔV_i (e.g. K_i in kg/(m^3 s) from kg/s)."""
    e = _as2d(extensive, ma.num_dofs, "extensive")
    return (e / ma.node_volume[:, None]).reshape(extensive.shape)
