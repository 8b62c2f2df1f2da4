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

from typing import NamedTuple

import numpy as np
from numba import njit

from febed.coupling.mesh_arrays import (
    NBR_DOMAIN_BOUNDARY,
    NUM_VERTICES,
    QUADRILATERAL,
    TETRAHEDRON,
    TRIANGLE,
    MeshArrays,
)
from febed.coupling.weights import fill_weights
from febed.kernel_records import fast_typeof

FOUND, OUTSIDE_DOMAIN, OUTSIDE_LOCAL = 0, 1, 2
INSIDE_TOL = 1e-10  # tolerance on reference coordinates for "inside"
_NEWTON_ITERS = 30


@fast_typeof
class CellMesh(NamedTuple):
    """The local cells as the location kernels take them (from `MeshArrays`, see `locate`)."""

    kind: int  # TRIANGLE, QUADRILATERAL, TETRAHEDRON or HEXAHEDRON
    gdim: int
    cell_dofs: np.ndarray  # (cells, nv) int: each cell's nodes
    x_dofs: np.ndarray  # (nodes, 3) m
    affine: np.ndarray  # (cells,) bool: affine map (a simplex, or a parallelogram/parallelepiped)
    cell_nbr: np.ndarray  # (cells, facets) int: the neighbour across each facet (< 0: none, see NBR_*)
    cell_facets: np.ndarray  # (cells, facets) int: local topology facet index of each facet
    bbox: np.ndarray  # (cells, 2, 3) m: each cell's bounding box


@fast_typeof
class CellGrid(NamedTuple):
    """The uniform grid of bins over the local cells of `MeshArrays`: bin b lists cells[start[b]:start[b + 1]]."""

    origin: np.ndarray  # (3,) m
    h: np.ndarray  # (3,) m: bin size
    n: np.ndarray  # (3,) int: bins along each axis
    start: np.ndarray  # (bins + 1,) int
    cells: np.ndarray  # int


@fast_typeof
class Location(NamedTuple):
    """Where points are, filled by `locate_kernel`: one row per point."""

    cell: np.ndarray  # (N,) int32: in: the cell to walk from (-1 = unknown); out: the cell holding it (-1 = none)
    ref: np.ndarray  # (N, 3): reference coordinates in that cell
    status: np.ndarray  # (N,) int8: FOUND, OUTSIDE_DOMAIN or OUTSIDE_LOCAL
    exit_facet: np.ndarray  # (N,) int32: the boundary facet an OUTSIDE_DOMAIN walk left through, else -1
    w: np.ndarray  # (N, nv) node weights (`febed.coupling.weights`), or 0 rows: not computed


@njit(cache=True)
def _solve2(a00, a01, a10, a11, r0, r1):
    """Solve the 2x2 system [[a00, a01], [a10, a11]] x = r by Cramer's rule: (ok, x0, x1)."""
    det = a00 * a11 - a01 * a10
    if det == 0.0:
        return False, 0.0, 0.0
    return True, (r0 * a11 - a01 * r1) / det, (a00 * r1 - r0 * a10) / det


@njit(cache=True)
def _solve3(a00, a01, a02, a10, a11, a12, a20, a21, a22, r0, r1, r2):
    """Solve the 3x3 system A x = r by Cramer's rule: (ok, x0, x1, x2)."""
    c00 = a11 * a22 - a12 * a21
    c01 = a12 * a20 - a10 * a22
    c02 = a10 * a21 - a11 * a20
    det = a00 * c00 + a01 * c01 + a02 * c02
    if det == 0.0:
        return False, 0.0, 0.0, 0.0
    c10 = a02 * a21 - a01 * a22
    c11 = a00 * a22 - a02 * a20
    c12 = a01 * a20 - a00 * a21
    c20 = a01 * a12 - a02 * a11
    c21 = a02 * a10 - a00 * a12
    c22 = a00 * a11 - a01 * a10
    inv = 1.0 / det
    return (
        True,
        (c00 * r0 + c10 * r1 + c20 * r2) * inv,
        (c01 * r0 + c11 * r1 + c21 * r2) * inv,
        (c02 * r0 + c12 * r1 + c22 * r2) * inv,
    )


@njit(cache=True)
def _affine_ref(gdim, x_dofs, d0, d1, d2, d3, px, py, pz):
    """Solve p = x_d0 + Σ_b ξ_b (x_{d_{b+1}} - x_d0) for ξ: (ok, ξ, η, ζ); d3 unused in 2D.

    Hot helpers take indices and scalars, never array views (views cost reference-count updates).
    """
    if gdim == 2:
        ok, a, b = _solve2(
            x_dofs[d1, 0] - x_dofs[d0, 0], x_dofs[d2, 0] - x_dofs[d0, 0],
            x_dofs[d1, 1] - x_dofs[d0, 1], x_dofs[d2, 1] - x_dofs[d0, 1],
            px - x_dofs[d0, 0], py - x_dofs[d0, 1],
        )  # fmt: skip
        return ok, a, b, 0.0
    return _solve3(
        x_dofs[d1, 0] - x_dofs[d0, 0], x_dofs[d2, 0] - x_dofs[d0, 0], x_dofs[d3, 0] - x_dofs[d0, 0],
        x_dofs[d1, 1] - x_dofs[d0, 1], x_dofs[d2, 1] - x_dofs[d0, 1], x_dofs[d3, 1] - x_dofs[d0, 1],
        x_dofs[d1, 2] - x_dofs[d0, 2], x_dofs[d2, 2] - x_dofs[d0, 2], x_dofs[d3, 2] - x_dofs[d0, 2],
        px - x_dofs[d0, 0], py - x_dofs[d0, 1], pz - x_dofs[d0, 2],
    )  # fmt: skip


@njit(cache=True)
def _newton_quad(x_dofs, cell_dofs, c, px, py):
    """Inverse of the bilinear map of quadrilateral c by Newton from its centre: (converged, ξ, η)."""
    xi, eta = 0.5, 0.5
    for _it in range(_NEWTON_ITERS):
        r0 = -px
        r1 = -py
        j00 = j01 = j10 = j11 = 0.0
        for k in range(4):
            fx = xi if k & 1 else 1.0 - xi
            fy = eta if k & 2 else 1.0 - eta
            gx = 1.0 if k & 1 else -1.0
            gy = 1.0 if k & 2 else -1.0
            dof = cell_dofs[c, k]
            xk0 = x_dofs[dof, 0]
            xk1 = x_dofs[dof, 1]
            phi = fx * fy
            r0 += phi * xk0
            r1 += phi * xk1
            j00 += gx * fy * xk0
            j01 += fx * gy * xk0
            j10 += gx * fy * xk1
            j11 += fx * gy * xk1
        ok, d0, d1 = _solve2(j00, j01, j10, j11, r0, r1)
        if not ok:
            return False, xi, eta
        # clamping keeps far-away points from sending Newton astray: the sign of the violation is what matters
        xi = min(max(xi - d0, -1.0), 2.0)
        eta = min(max(eta - d1, -1.0), 2.0)
        if max(abs(d0), abs(d1)) < 1e-13:
            return True, xi, eta
    return False, xi, eta


@njit(cache=True)
def _newton_hex(x_dofs, cell_dofs, c, px, py, pz):
    """Inverse of the trilinear map of hexahedron c by Newton from its centre: (converged, ξ, η, ζ)."""
    xi, eta, zeta = 0.5, 0.5, 0.5
    for _it in range(_NEWTON_ITERS):
        r0 = -px
        r1 = -py
        r2 = -pz
        j00 = j01 = j02 = j10 = j11 = j12 = j20 = j21 = j22 = 0.0
        for k in range(8):
            fx = xi if k & 1 else 1.0 - xi
            fy = eta if k & 2 else 1.0 - eta
            fz = zeta if k & 4 else 1.0 - zeta
            gx = (1.0 if k & 1 else -1.0) * fy * fz
            gy = (1.0 if k & 2 else -1.0) * fx * fz
            gz = (1.0 if k & 4 else -1.0) * fx * fy
            dof = cell_dofs[c, k]
            xk0 = x_dofs[dof, 0]
            xk1 = x_dofs[dof, 1]
            xk2 = x_dofs[dof, 2]
            phi = fx * fy * fz
            r0 += phi * xk0
            r1 += phi * xk1
            r2 += phi * xk2
            j00 += gx * xk0
            j01 += gy * xk0
            j02 += gz * xk0
            j10 += gx * xk1
            j11 += gy * xk1
            j12 += gz * xk1
            j20 += gx * xk2
            j21 += gy * xk2
            j22 += gz * xk2
        ok, d0, d1, d2 = _solve3(j00, j01, j02, j10, j11, j12, j20, j21, j22, r0, r1, r2)
        if not ok:
            return False, xi, eta, zeta
        xi = min(max(xi - d0, -1.0), 2.0)
        eta = min(max(eta - d1, -1.0), 2.0)
        zeta = min(max(zeta - d2, -1.0), 2.0)
        if max(abs(d0), abs(d1), abs(d2)) < 1e-13:
            return True, xi, eta, zeta
    return False, xi, eta, zeta


@njit(cache=True)
def _violation(simplex, quad, gdim, a, b, e):
    """How far reference point (a, b, e) is outside the reference cell, and the DOLFINx facet it is most outside of.

    Simplex: facet k is opposite vertex k (λ_0 = 1 - a - b - e). Quadrilateral facets: ξ=0 -> 1, ξ=1 -> 2,
    η=0 -> 0, η=1 -> 3; hexahedron: ξ=0 -> 2, ξ=1 -> 3, η=0 -> 1, η=1 -> 4, ζ=0 -> 0, ζ=1 -> 5.
    """
    if simplex:
        worst = a + b + e - 1.0
        facet = 0
        if -a > worst:
            worst = -a
            facet = 1
        if -b > worst:
            worst = -b
            facet = 2
        if gdim == 3 and -e > worst:
            worst = -e
            facet = 3
        return worst, facet
    worst = -a
    facet = 1 if quad else 2
    if a - 1.0 > worst:
        worst = a - 1.0
        facet = 2 if quad else 3
    if -b > worst:
        worst = -b
        facet = 0 if quad else 1
    if b - 1.0 > worst:
        worst = b - 1.0
        facet = 3 if quad else 4
    if gdim == 3:
        if -e > worst:
            worst = -e
            facet = 0
        if e - 1.0 > worst:
            worst = e - 1.0
            facet = 5
    return worst, facet


@njit(cache=True)
def reference_coords(kind, gdim, cell_dofs, x_dofs, affine, c, px, py, pz):
    """Reference coordinates of point (px, py, pz) in cell c: (how far outside, exit facet, ξ, η, ζ).

    The first value is <= 0 inside (minus the distance to the nearest facet in reference units) and > 0
    outside; the second is the DOLFINx reference facet the point is most outside of. affine (nc,) flags
    quadrilaterals/hexahedra whose map is affine (one linear solve instead of Newton). ζ = 0 in 2D.
    """
    if kind == TRIANGLE or kind == TETRAHEDRON:
        ok, a, b, e = _affine_ref(
            gdim, x_dofs, cell_dofs[c, 0], cell_dofs[c, 1], cell_dofs[c, 2], cell_dofs[c, gdim], px, py, pz
        )
        if not ok:
            return 1e300, 0, a, b, e
        worst, facet = _violation(True, False, gdim, a, b, e)
        return worst, facet, a, b, e
    if affine[c]:  # parallelogram / parallelepiped: x = x0 + Σ_b ξ_b (x_{2^b} - x0)
        ok, a, b, e = _affine_ref(
            gdim, x_dofs, cell_dofs[c, 0], cell_dofs[c, 1], cell_dofs[c, 2], cell_dofs[c, 4 if gdim == 3 else 0],
            px, py, pz,
        )  # fmt: skip
    elif kind == QUADRILATERAL:
        ok, a, b = _newton_quad(x_dofs, cell_dofs, c, px, py)
        e = 0.0
    else:
        ok, a, b, e = _newton_hex(x_dofs, cell_dofs, c, px, py, pz)
    worst, facet = _violation(False, kind == QUADRILATERAL, gdim, a, b, e)
    if not ok and worst <= INSIDE_TOL:
        worst = 1e300  # not converged (or singular): not trusted as inside
    return worst, facet, a, b, e


@njit(cache=True)
def _grid_search(mesh, grid, px, py, pz):
    """Cell of the grid bin of (px, py, pz) holding the point: (cell or -1, ξ, η, ζ)."""
    kind, gdim, cell_dofs, x_dofs, affine, _nbr, _facets, bbox = mesh
    origin, h, n, start, cells = grid
    b = 0
    for a in range(3):
        xa = px if a == 0 else (py if a == 1 else pz)
        i = int(np.floor((xa - origin[a]) / h[a]))
        if i < 0 or i >= n[a]:
            return -1, 0.0, 0.0, 0.0
        b = b * n[a] + i
    for s in range(start[b], start[b + 1]):
        c = cells[s]
        out = False
        for a in range(gdim):
            xa = px if a == 0 else (py if a == 1 else pz)
            tol = 1e-9 * (bbox[c, 1, a] - bbox[c, 0, a])
            if xa < bbox[c, 0, a] - tol or xa > bbox[c, 1, a] + tol:
                out = True
        if out:
            continue
        worst, _f, r0, r1, r2 = reference_coords(kind, gdim, cell_dofs, x_dofs, affine, c, px, py, pz)
        if worst <= INSIDE_TOL:
            return c, r0, r1, r2
    return -1, 0.0, 0.0, 0.0


@njit(cache=True)
def _nearest_start(grid, px, py, pz):
    """A cell of the grid bin nearest to the point (clamped into the grid), to start a classifying walk; -1 if none."""
    origin, h, n, start, cells = grid
    idx = np.empty(3, dtype=np.int64)
    for a in range(3):
        xa = px if a == 0 else (py if a == 1 else pz)
        idx[a] = min(max(int(np.floor((xa - origin[a]) / h[a])), 0), n[a] - 1)
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
def locate_kernel(mesh, grid, x, loc, max_steps):
    """Locate points x (N, 3) in the cells of `mesh` (CellMesh, its CellGrid), walking at most max_steps cells.

    Fills `loc` (Location), walking from loc.cell; if loc.w has N rows, also the node weights
    (`febed.coupling.weights`, zero where not found). Returns the number of points not found in the local mesh.
    """
    kind, gdim, cell_dofs, x_dofs, affine, cell_nbr, cell_facets, _bbox = mesh
    cell, ref, status, exit_facet, w = loc
    with_w = w.shape[0] > 0
    nc = cell_dofs.shape[0]
    simplex = kind == TRIANGLE or kind == TETRAHEDRON
    missing = 0
    for p in range(x.shape[0]):
        px = x[p, 0]
        py = x[p, 1]
        pz = x[p, 2]
        c = cell[p]
        found = -1
        last_c = -1
        last_f = -1
        r0 = r1 = r2 = 0.0
        for attempt in range(2):
            if attempt == 1:
                # fallback: the grid index; if that fails too, a walk from a nearby cell classifies the exit
                found, r0, r1, r2 = _grid_search(mesh, grid, px, py, pz)
                if found >= 0 or last_c >= 0:
                    break
                c = _nearest_start(grid, px, py, pz)
            if c < 0 or c >= nc:
                continue
            for _s in range(max_steps):
                if affine[c]:
                    # simplex / affine cell: the solve of `reference_coords` written out here, because a call
                    # with array arguments costs more than the solve itself in Numba (reference counting)
                    d0 = cell_dofs[c, 0]
                    d1 = cell_dofs[c, 1]
                    d2 = cell_dofs[c, 2]
                    if gdim == 2:
                        ok, r0, r1 = _solve2(
                            x_dofs[d1, 0] - x_dofs[d0, 0], x_dofs[d2, 0] - x_dofs[d0, 0],
                            x_dofs[d1, 1] - x_dofs[d0, 1], x_dofs[d2, 1] - x_dofs[d0, 1],
                            px - x_dofs[d0, 0], py - x_dofs[d0, 1],
                        )  # fmt: skip
                        r2 = 0.0
                    else:
                        d3 = cell_dofs[c, 3 if simplex else 4]
                        ok, r0, r1, r2 = _solve3(
                            x_dofs[d1, 0] - x_dofs[d0, 0], x_dofs[d2, 0] - x_dofs[d0, 0], x_dofs[d3, 0] - x_dofs[d0, 0],
                            x_dofs[d1, 1] - x_dofs[d0, 1], x_dofs[d2, 1] - x_dofs[d0, 1], x_dofs[d3, 1] - x_dofs[d0, 1],
                            x_dofs[d1, 2] - x_dofs[d0, 2], x_dofs[d2, 2] - x_dofs[d0, 2], x_dofs[d3, 2] - x_dofs[d0, 2],
                            px - x_dofs[d0, 0], py - x_dofs[d0, 1], pz - x_dofs[d0, 2],
                        )  # fmt: skip
                    if not ok:
                        worst, f = 1e300, 0
                    else:
                        worst, f = _violation(simplex, kind == QUADRILATERAL, gdim, r0, r1, r2)
                else:
                    worst, f, r0, r1, r2 = reference_coords(kind, gdim, cell_dofs, x_dofs, affine, c, px, py, pz)
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
            ref[p, 0] = r0
            ref[p, 1] = r1
            ref[p, 2] = r2
            if with_w:
                fill_weights(kind, r0, r1, r2, w, p)
        else:
            missing += 1
            cell[p] = -1
            ref[p, 0] = ref[p, 1] = ref[p, 2] = 0.0
            if with_w:
                for k in range(w.shape[1]):
                    w[p, k] = 0.0
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
    w: np.ndarray | None = None,
):
    """Locate particle centres x (N, 3) (m) in the local mesh, walking from `cell` (N,) int32 (-1 = unknown).

    `cell` is updated in place (-1 where not found). Returns (cell, ref (N, 3) reference coordinates,
    status (N,) int8 in {FOUND, OUTSIDE_DOMAIN, OUTSIDE_LOCAL}, exit_facet (N,) int32 local facet or -1,
    number not found). Output arrays may be passed in to avoid allocation; `w` (N, nv), if given, receives
    the node weights as from `compute_weights` (in the same pass).
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
    nv = NUM_VERTICES[ma.kind]
    if w is None:
        w = np.empty((0, nv))
    elif w.shape != (n, nv) or w.dtype != np.float64:
        raise ValueError(f"w: must be a float64 array of shape ({n}, {nv}), got {w.dtype} {w.shape}")
    mesh = CellMesh(ma.kind, ma.gdim, ma.cell_dofs, ma.x_dofs, ma.cell_affine, ma.cell_nbr, ma.cell_facets, ma.bbox)
    grid = CellGrid(ma.grid_origin, ma.grid_h, ma.grid_n, ma.grid_start, ma.grid_cells)
    missing = locate_kernel(mesh, grid, x, Location(cell, ref, status, exit_facet, w), max_steps)
    return cell, ref, status, exit_facet, int(missing)


@njit(cache=True)
def brute_force_kernel(kind, gdim, cell_dofs, x_dofs, affine, x, cell, ref):
    """Reference search: the first cell (in local order) holding each point, by testing every cell."""
    for p in range(x.shape[0]):
        cell[p] = -1
        for c in range(cell_dofs.shape[0]):
            worst, _f, r0, r1, r2 = reference_coords(
                kind, gdim, cell_dofs, x_dofs, affine, c, x[p, 0], x[p, 1], x[p, 2]
            )
            if worst <= INSIDE_TOL:
                cell[p] = c
                ref[p, 0] = r0
                ref[p, 1] = r1
                ref[p, 2] = r2
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
