"""Projection of particle quantities onto the nodes, conservative neighbour filter, solid/void fraction.

Seed 001 eqs 29-30: Σ_p ω_{p,i} q_p onto the nodes i of the cell holding p (extensive nodal sums), then the
neighbour filter (eqs 31-34), then division by the node control volume ΔV_i = ∫φ_i dx.

Filter reading (docs/theory.md, interpolation and projection): the intensive filter of eq 31 is node -> cell -> node,
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

import math

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
def filter_kernel(cell_dofs, num_owned_cells, gather, scatter, extensive, out):
    """One pass of the transposed neighbour filter on extensive nodal sums over owned cells (seed 001 eqs 31-34).

    out[i] = Σ_{K∋i} (S_Ki/|K|) Σ_{j∈K} (S_Kj/ΔV_j) E_j, with gather = S_Kj/ΔV_j and scatter = S_Ki/|K|
    from `MeshArrays.filter_weights`; `out` is zeroed first.
    """
    nv = cell_dofs.shape[1]
    k = extensive.shape[1]
    out[:, :] = 0.0
    acc = np.zeros(k)
    for c in range(num_owned_cells):
        for a in range(k):
            acc[a] = 0.0
        for j in range(nv):
            dof = cell_dofs[c, j]
            f = gather[c, j]
            for a in range(k):
                acc[a] += f * extensive[dof, a]
        for i in range(nv):
            dof = cell_dofs[c, i]
            f = scatter[c, i]
            for a in range(k):
                out[dof, a] += f * acc[a]


@njit(cache=True)
def exchange_project_kernel(cell_dofs, cell, w, d3, n_orig, K, v, F, g, nodal):
    """Zero `nodal` (nd, 2 + g [+ g]), then project [V_p, K_p, K_p v_p, -F_p] onto it (seed 001 eqs 27-30).

    g is the geometric dimension; V_p = n_orig π d3 / 6 with d3 (N,) the cubed original diameters (m^3);
    K (N,) kg/s; v (N, 3) m/s; if nodal has 2 + 2g columns, the explicit particle force F (N, 3) N, whose
    reaction -F the gas receives.
    The same sums, in the same order, as `project_kernel` on the stacked values (bit-identical).
    """
    nodal[:, :] = 0.0
    exchange_add_kernel(cell_dofs, cell, w, d3, n_orig, K, v, F, g, nodal)


@njit(cache=True)
def exchange_add_kernel(cell_dofs, cell, w, d3, n_orig, K, v, F, g, nodal):
    """`exchange_project_kernel` without zeroing `nodal` first: the particles' sums are added to it."""
    nv = w.shape[1]
    with_f = nodal.shape[1] == 2 + 2 * g
    for p in range(cell.size):
        c = cell[p]
        if c < 0:
            continue
        vol = n_orig[p] * (math.pi / 6.0) * d3[p]
        kp = K[p]
        kv0 = kp * v[p, 0]
        kv1 = kp * v[p, 1]
        kv2 = kp * v[p, 2]
        f0 = f1 = f2 = 0.0
        if with_f:
            f0 = -F[p, 0]
            f1 = -F[p, 1]
            f2 = -F[p, 2]
        for i in range(nv):
            wi = w[p, i]
            dof = cell_dofs[c, i]
            nodal[dof, 0] += wi * vol
            nodal[dof, 1] += wi * kp
            nodal[dof, 2] += wi * kv0
            nodal[dof, 3] += wi * kv1
            if g == 3:
                nodal[dof, 4] += wi * kv2
            if with_f:
                nodal[dof, 2 + g] += wi * f0
                nodal[dof, 3 + g] += wi * f1
                if g == 3:
                    nodal[dof, 4 + g] += wi * f2


@njit(cache=True)
def exchange_finish_kernel(nodal, node_volume, floor, num_owned, alpha, eps, K, Kv, F):
    """Divide the filtered sums of `exchange_project_kernel` by ΔV_i: α_i, ε_i (floored), K_i, (K v)_i, F_i.

    ε_i = min(1 - α_i, 1), raised to `floor` where below (seed 001 eq 30); F is zero without a force column.
    Returns the number of owned nodes clipped. Same arithmetic as `solid_fraction` and `per_volume`.
    """
    g = Kv.shape[1]
    with_f = nodal.shape[1] == 2 + 2 * g
    clipped = 0
    for i in range(nodal.shape[0]):
        dv = node_volume[i]
        a = nodal[i, 0] / dv
        alpha[i] = a
        e = 1.0 - a
        if e > 1.0:  # round-off in the filter must not give ε > 1 (NaN stays NaN)
            e = 1.0
        if e < floor:
            e = floor
            if i < num_owned:
                clipped += 1
        eps[i] = e
        K[i] = nodal[i, 1] / dv
        for b in range(g):
            Kv[i, b] = nodal[i, 2 + b] / dv
            F[i, b] = nodal[i, 2 + g + b] / dv if with_f else 0.0
    return clipped


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
    gather, scatter = ma.filter_weights()
    return _filter_passes(ma, _as2d(extensive, ma.num_dofs, "extensive"), passes, gather, scatter).reshape(
        extensive.shape
    )


def _filter_passes(ma: MeshArrays, cur: np.ndarray, passes: int, gather: np.ndarray, scatter: np.ndarray):
    """`passes` passes of `filter_kernel` with the given (gather, scatter) weights on (nd, k) rows (a new array)."""
    if not isinstance(passes, int | np.integer) or passes < 0:
        raise ValueError(f"passes: must be an integer >= 0, got {passes!r}")
    cur = np.array(cur, dtype=np.float64, order="C")
    for _ in range(passes):
        out = np.empty_like(cur)
        filter_kernel(ma.cell_dofs, ma.num_owned_cells, gather, scatter, cur, out)
        ma.accumulate(out)
        cur = out
    return cur


def neighbour_filter_transpose(ma: MeshArrays, nodal: np.ndarray, passes: int = 1) -> np.ndarray:
    """Apply `passes` passes of the neighbour filter's transpose to an intensive nodal field (new array; collective).

    The transpose of `neighbour_filter` is the node → cell → node average of seed 001 eq 31,
    Φ̂_j = Σ_{K∋j} (S_Kj/ΔV_j) Σ_{i∈K} (S_Ki/|K|) Φ_i: the same kernel with gather and scatter swapped, equal to
    T(ΦΔV)/ΔV (T = B/ΔV with B symmetric). It keeps constants, and for extensive sums A,
    Σ_i (T A)_i Φ_i = Σ_j A_j (Tᵀ Φ)_j over owned dofs: a field the particles interpolate after Tᵀ gives them in
    total what the filtered sums give the gas against Φ itself. `nodal` is (nd,) or (nd, k), consistent on ghost
    dofs; owned and ghost rows of the result are set.
    """
    gather, scatter = ma.filter_weights()
    return _filter_passes(ma, _as2d(nodal, ma.num_dofs, "nodal"), passes, scatter, gather).reshape(np.shape(nodal))


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
