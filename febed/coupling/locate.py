"""Particle location in mesh cells: walk from the previous cell, uniform-grid search as fallback (Numba).

A particle is located in the unique cell holding its centre (seed 001 §2.3). Reference coordinates are
barycentric-type (ξ in the reference simplex) on triangles/tetrahedra and ξ ∈ [0, 1]^d through a Newton
inverse of the bilinear/trilinear map on quadrilaterals/hexahedra (affine or not). The walk steps across the
facet the point is most outside of; when it reaches a facet without neighbour, loops, or starts from an
unknown cell (-1), the grid index of `MeshArrays` is searched.

Status codes returned per particle:
    FOUND (0): inside a local cell (owned or ghost).
    OUTSIDE_DOMAIN (1): outside the mesh, the walk left through a domain-boundary facet (`exit_facet` holds
        its local topology facet index: look it up in the facet tags, e.g. the outlet).
    OUTSIDE_LOCAL (2): outside this rank's local mesh through a partition boundary (another rank owns it).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from febed.coupling.mesh_arrays import NBR_DOMAIN_BOUNDARY, QUADRILATERAL, TETRAHEDRON, TRIANGLE, MeshArrays

FOUND, OUTSIDE_DOMAIN, OUTSIDE_LOCAL = 0, 1, 2
INSIDE_TOL = 1e-10  # tolerance on reference coordinates for "inside"
_NEWTON_ITERS = 30

# facet across which a point leaves, for ξ_a < 0 (row 0) and ξ_a > 1 (row 1), DOLFINx reference facets
_QUAD_FACET = np.array([[1, 0], [2, 3]], dtype=np.int64)
_HEX_FACET = np.array([[2, 1, 0], [3, 4, 5]], dtype=np.int64)


@njit(cache=True)
def _solve(gdim, J, r, out):
    """Solve J out = r for a 2x2 or 3x3 matrix by Cramer's rule; returns False if singular."""
    if gdim == 2:
        det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
        if det == 0.0:
            return False
        out[0] = (r[0] * J[1, 1] - J[0, 1] * r[1]) / det
        out[1] = (J[0, 0] * r[1] - r[0] * J[1, 0]) / det
        out[2] = 0.0
        return True
    c00 = J[1, 1] * J[2, 2] - J[1, 2] * J[2, 1]
    c01 = J[1, 2] * J[2, 0] - J[1, 0] * J[2, 2]
    c02 = J[1, 0] * J[2, 1] - J[1, 1] * J[2, 0]
    det = J[0, 0] * c00 + J[0, 1] * c01 + J[0, 2] * c02
    if det == 0.0:
        return False
    c10 = J[0, 2] * J[2, 1] - J[0, 1] * J[2, 2]
    c11 = J[0, 0] * J[2, 2] - J[0, 2] * J[2, 0]
    c12 = J[0, 1] * J[2, 0] - J[0, 0] * J[2, 1]
    c20 = J[0, 1] * J[1, 2] - J[0, 2] * J[1, 1]
    c21 = J[0, 2] * J[1, 0] - J[0, 0] * J[1, 2]
    c22 = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
    out[0] = (c00 * r[0] + c10 * r[1] + c20 * r[2]) / det
    out[1] = (c01 * r[0] + c11 * r[1] + c21 * r[2]) / det
    out[2] = (c02 * r[0] + c12 * r[1] + c22 * r[2]) / det
    return True


@njit(cache=True)
def reference_coords(kind, gdim, cell_dofs, x_dofs, affine, c, x, ref, J, r, d):
    """Reference coordinates `ref` (3,) of point x in cell c; returns (how far outside, exit reference facet).

    The first value is <= 0 inside (minus the distance to the nearest facet in reference units) and > 0
    outside; the second is the reference facet the point is most outside of. affine (nc,) flags
    quadrilaterals/hexahedra whose map is affine (one linear solve instead of Newton). J (3, 3), r, d (3,)
    are scratch.
    """
    dofs = cell_dofs[c]
    if kind == TRIANGLE or kind == TETRAHEDRON:
        x0 = x_dofs[dofs[0]]
        for a in range(gdim):
            r[a] = x[a] - x0[a]
            for b in range(gdim):
                J[a, b] = x_dofs[dofs[b + 1], a] - x0[a]
        if not _solve(gdim, J, r, ref):
            return 1e300, 0
        lam0 = 1.0
        for a in range(gdim):
            lam0 -= ref[a]
        worst = -lam0
        facet = 0
        for a in range(gdim):
            if -ref[a] > worst:
                worst = -ref[a]
                facet = a + 1
        return worst, facet
    nv = 4 if kind == QUADRILATERAL else 8
    converged = False
    if affine[c]:  # parallelogram / parallelepiped: x = x0 + Σ_b ξ_b (x_{2^b} - x0)
        x0 = x_dofs[dofs[0]]
        for a in range(gdim):
            r[a] = x[a] - x0[a]
            for b in range(gdim):
                J[a, b] = x_dofs[dofs[1 << b], a] - x0[a]
        if not _solve(gdim, J, r, ref):
            return 1e300, 0
        converged = True
        nv = 0  # skip Newton
    # bilinear / trilinear map: Newton from the cell centre
    if nv > 0:
        for a in range(3):
            ref[a] = 0.5 if a < gdim else 0.0
    for _it in range(_NEWTON_ITERS if nv > 0 else 0):
        for a in range(gdim):
            r[a] = -x[a]
            for b in range(gdim):
                J[a, b] = 0.0
        for k in range(nv):
            phi = 1.0
            for b in range(gdim):
                phi *= ref[b] if (k >> b) & 1 else 1.0 - ref[b]
            xk = x_dofs[dofs[k]]
            for b in range(gdim):
                dphi = 1.0
                for e in range(gdim):
                    if e == b:
                        dphi *= 1.0 if (k >> e) & 1 else -1.0
                    else:
                        dphi *= ref[e] if (k >> e) & 1 else 1.0 - ref[e]
                for a in range(gdim):
                    J[a, b] += dphi * xk[a]
            for a in range(gdim):
                r[a] += phi * xk[a]
        if not _solve(gdim, J, r, d):
            return 1e300, 0
        step = 0.0
        for a in range(gdim):
            ref[a] -= d[a]
            step = max(step, abs(d[a]))
            # keep far-away points from sending Newton astray: the sign of the violation is what matters
            ref[a] = min(max(ref[a], -1.0), 2.0)
        if step < 1e-13:
            converged = True
            break
    worst = -1e300
    facet = 0
    for a in range(gdim):
        lo = -ref[a]
        hi = ref[a] - 1.0
        if lo > worst:
            worst = lo
            facet = _QUAD_FACET[0, a] if kind == QUADRILATERAL else _HEX_FACET[0, a]
        if hi > worst:
            worst = hi
            facet = _QUAD_FACET[1, a] if kind == QUADRILATERAL else _HEX_FACET[1, a]
    if not converged and worst <= INSIDE_TOL:
        worst = 1e300  # not converged: not trusted as inside
    return worst, facet


@njit(cache=True)
def _grid_search(kind, gdim, cell_dofs, x_dofs, affine, bbox, origin, h, n, start, cells, x, ref, J, r, d):
    """Cell of the grid bin of x whose reference coordinates put x inside, or -1."""
    b = 0
    for a in range(3):
        i = int(np.floor((x[a] - origin[a]) / h[a]))
        if i < 0 or i >= n[a]:
            return -1
        b = b * n[a] + i
    for s in range(start[b], start[b + 1]):
        c = cells[s]
        out = False
        for a in range(gdim):
            tol = 1e-9 * (bbox[c, 1, a] - bbox[c, 0, a])
            if x[a] < bbox[c, 0, a] - tol or x[a] > bbox[c, 1, a] + tol:
                out = True
        if out:
            continue
        worst, _f = reference_coords(kind, gdim, cell_dofs, x_dofs, affine, c, x, ref, J, r, d)
        if worst <= INSIDE_TOL:
            return c
    return -1


@njit(cache=True)
def _nearest_start(gdim, origin, h, n, start, cells, x):
    """A cell of the grid bin nearest to x (x clamped into the grid), to start a classifying walk; -1 if none."""
    idx = np.empty(3, dtype=np.int64)
    for a in range(3):
        idx[a] = min(max(int(np.floor((x[a] - origin[a]) / h[a])), 0), n[a] - 1)
    # search growing shells of bins around the clamped bin
    for rad in range(max(n[0], n[1], n[2])):
        for i in range(max(idx[0] - rad, 0), min(idx[0] + rad, n[0] - 1) + 1):
            for j in range(max(idx[1] - rad, 0), min(idx[1] + rad, n[1] - 1) + 1):
                for k in range(max(idx[2] - rad, 0), min(idx[2] + rad, n[2] - 1) + 1):
                    b = (i * n[1] + j) * n[2] + k
                    if start[b + 1] > start[b]:
                        return cells[start[b]]
    return -1


@njit(cache=True)
def locate_kernel(
    kind, gdim, cell_dofs, x_dofs, affine, cell_nbr, cell_facets, bbox, origin, h, n, start, cells, x, cell, ref,
    status, exit_facet, max_steps,
):  # fmt: skip
    """Locate points x (N, 3) starting from `cell` (in/out, -1 = unknown); fill ref, status, exit_facet.

    Returns the number of points not found in the local mesh.
    """
    J = np.zeros((3, 3))
    r = np.zeros(3)
    d = np.zeros(3)
    nc = cell_dofs.shape[0]
    missing = 0
    for p in range(x.shape[0]):
        xp = x[p]
        rp = ref[p]
        c = cell[p]
        found = -1
        last_c = -1
        last_f = -1
        for attempt in range(2):
            if attempt == 1:
                # fallback: the grid index; if that fails too, a walk from a nearby cell classifies the exit
                found = _grid_search(
                    kind, gdim, cell_dofs, x_dofs, affine, bbox, origin, h, n, start, cells, xp, rp, J, r, d
                )
                if found >= 0:
                    break
                if last_c >= 0:
                    break
                c = _nearest_start(gdim, origin, h, n, start, cells, xp)
            if c < 0 or c >= nc:
                continue
            for _s in range(max_steps):
                worst, f = reference_coords(kind, gdim, cell_dofs, x_dofs, affine, c, xp, rp, J, r, d)
                if worst <= INSIDE_TOL:
                    found = c
                    break
                nb = cell_nbr[c, f]
                if nb < 0:
                    last_c = c
                    last_f = f
                    break
                c = nb
            if found >= 0:
                break
        if found >= 0:
            cell[p] = found
            status[p] = FOUND
            exit_facet[p] = -1
        else:
            missing += 1
            cell[p] = -1
            for a in range(3):
                rp[a] = 0.0
            if last_c >= 0 and cell_nbr[last_c, last_f] == NBR_DOMAIN_BOUNDARY:
                status[p] = OUTSIDE_DOMAIN
                exit_facet[p] = cell_facets[last_c, last_f]
            else:
                status[p] = OUTSIDE_LOCAL
                exit_facet[p] = -1
    return missing


def locate(
    ma: MeshArrays,
    x: np.ndarray,
    cell: np.ndarray,
    ref: np.ndarray | None = None,
    status: np.ndarray | None = None,
    exit_facet: np.ndarray | None = None,
    max_steps: int = 200,
):
    """Locate particle centres x (N, 3) (m) in the local mesh, walking from `cell` (N,) int32 (-1 = unknown).

    `cell` is updated in place (-1 where not found). Returns (cell, ref (N, 3) reference coordinates,
    status (N,) int8 in {FOUND, OUTSIDE_DOMAIN, OUTSIDE_LOCAL}, exit_facet (N,) int32 local facet or -1,
    number not found). Output arrays may be passed in to avoid allocation.
    """
    x = np.asarray(x)
    if x.ndim != 2 or x.shape[1] != 3 or x.dtype != np.float64:
        raise ValueError(f"x: must be a float64 array of shape (N, 3), got {x.dtype} {x.shape}")
    n = x.shape[0]
    if cell.shape != (n,) or cell.dtype != np.int32:
        raise ValueError(f"cell: must be an int32 array of shape ({n},), got {cell.dtype} {cell.shape}")
    ref = np.zeros((n, 3)) if ref is None else ref
    status = np.zeros(n, dtype=np.int8) if status is None else status
    exit_facet = np.full(n, -1, dtype=np.int32) if exit_facet is None else exit_facet
    missing = locate_kernel(
        ma.kind, ma.gdim, ma.cell_dofs, ma.x_dofs, ma.cell_affine, ma.cell_nbr, ma.cell_facets, ma.bbox,
        ma.grid_origin, ma.grid_h, ma.grid_n, ma.grid_start, ma.grid_cells, x, cell, ref, status, exit_facet, max_steps,
    )  # fmt: skip
    return cell, ref, status, exit_facet, int(missing)


@njit(cache=True)
def brute_force_kernel(kind, gdim, cell_dofs, x_dofs, affine, x, cell, ref):
    """Reference search: the first cell (in local order) holding each point, by testing every cell."""
    J = np.zeros((3, 3))
    r = np.zeros(3)
    d = np.zeros(3)
    for p in range(x.shape[0]):
        cell[p] = -1
        for c in range(cell_dofs.shape[0]):
            worst, _f = reference_coords(kind, gdim, cell_dofs, x_dofs, affine, c, x[p], ref[p], J, r, d)
            if worst <= INSIDE_TOL:
                cell[p] = c
                break


def locate_brute_force(ma: MeshArrays, x: np.ndarray):
    """Locate x (N, 3) by testing every local cell (slow; for tests): returns (cell (N,) int32, ref (N, 3))."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    cell = np.full(x.shape[0], -1, dtype=np.int32)
    ref = np.zeros((x.shape[0], 3))
    brute_force_kernel(ma.kind, ma.gdim, ma.cell_dofs, ma.x_dofs, ma.cell_affine, x, cell, ref)
    bad = cell < 0
    ref[bad] = 0.0
    return cell, ref
