"""Walls: planes (the fast path for boxes) and mesh facets (triangles in 3D, segments in 2D).

A wall is a particle of infinite mass and zero radius (seed 001 sec 2.2.1): a contact has the overlap
r - |x - q| where q is the point of the wall closest to the centre x, and the normal along q - x.

* Planes are one-sided half-spaces (point, unit normal into the domain): overlap r - (x - p).n, so a
  particle can never leak through, even when it is pushed across.
  A mesh's walls use planes for the faces of its bounding box that wall facets cover completely
  (`Walls.from_facets`): a box-shaped bed then costs a few plane distances per particle.
* Facets are two-sided; quads are split into two triangles. The closest point of a triangle lies on its
  face, one of its edges or one of its vertices (Ericson, Real-Time Collision Detection, sec 5.1.5), so
  edges and corners push like rounded edges and nothing leaks between facets.

Rule for several contacts of one particle (documented choice, see `accept_contacts`): the contacts are
taken face first, then edges, then vertices (largest overlap first within a kind); a contact is dropped
when its closest point lies on or behind the tangent plane of a contact already accepted,
(q - q_a) . m_a <= tol with m_a the unit vector from q_a to the centre. So a particle on two coplanar
facets (or at their shared edge or vertex) is pushed once; at a concave corner (box corner, cylinder
base) every face pushes; over a convex edge the edge pushes alone.

Candidates (particle, wall) are listed with the pair list (same skin) using a uniform grid over the
facets' bounding boxes, so facet walls cost O(particles near walls).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from febed.kernel_records import fast_typeof

FACE, EDGE, VERTEX = 0, 1, 2
MAX_WALL_CONTACTS = 16


@fast_typeof
class WallGeometry(NamedTuple):
    """The walls as the Numba kernels take them: wall w is plane w if w < len(plane_p), else facet w - len(plane_p)."""

    plane_p: np.ndarray  # (n_planes, 3) m: a point of each plane
    plane_n: np.ndarray  # (n_planes, 3): each plane's unit normal, into the domain
    facets: np.ndarray  # (n_facets, nv, 3) m: segments (nv = 2, 2D) or triangles (nv = 3)
    nv: int  # vertices per facet


@fast_typeof
class FacetGrid(NamedTuple):
    """A uniform grid over the facets' bounding boxes: cell c lists facets items[start[c]:start[c + 1]]."""

    lo: np.ndarray  # (3,) m: the grid's lower corner
    size: float  # m: the cells' edge
    dims: np.ndarray  # (3,) int: cells along each axis
    start: np.ndarray  # (cells + 1,) int: CSR offsets
    items: np.ndarray  # int: facet indices


@njit(cache=True, inline="always")
def _closest_segment(px, py, pz, a, b):
    abx = b[0] - a[0]
    aby = b[1] - a[1]
    abz = b[2] - a[2]
    ll = abx * abx + aby * aby + abz * abz
    t = ((px - a[0]) * abx + (py - a[1]) * aby + (pz - a[2]) * abz) / ll if ll > 0 else 0.0
    if t <= 0.0:
        return a[0], a[1], a[2], VERTEX
    if t >= 1.0:
        return b[0], b[1], b[2], VERTEX
    return a[0] + t * abx, a[1] + t * aby, a[2] + t * abz, EDGE


@njit(cache=True)
def closest_on_facet(px, py, pz, f, nv):
    """Closest point (qx, qy, qz) of facet f (nv=3 triangle, nv=2 segment) to p, and its kind FACE/EDGE/VERTEX."""
    a = f[0]
    b = f[1]
    if nv == 2:  # a segment is the "face" of a 2D wall; its ends are vertices
        qx, qy, qz, kind = _closest_segment(px, py, pz, a, b)
        return qx, qy, qz, FACE if kind == EDGE else VERTEX
    c = f[2]
    abx, aby, abz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    acx, acy, acz = c[0] - a[0], c[1] - a[1], c[2] - a[2]
    apx, apy, apz = px - a[0], py - a[1], pz - a[2]
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return a[0], a[1], a[2], VERTEX
    bpx, bpy, bpz = px - b[0], py - b[1], pz - b[2]
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return b[0], b[1], b[2], VERTEX
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return a[0] + v * abx, a[1] + v * aby, a[2] + v * abz, EDGE
    cpx, cpy, cpz = px - c[0], py - c[1], pz - c[2]
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return c[0], c[1], c[2], VERTEX
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return a[0] + w * acx, a[1] + w * acy, a[2] + w * acz, EDGE
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return b[0] + w * (c[0] - b[0]), b[1] + w * (c[1] - b[1]), b[2] + w * (c[2] - b[2]), EDGE
    den = 1.0 / (va + vb + vc)
    v = vb * den
    w = vc * den
    return a[0] + abx * v + acx * w, a[1] + aby * v + acy * w, a[2] + abz * v + acz * w, FACE


@njit(cache=True, inline="always")
def wall_point(px, py, pz, w, walls):
    """Closest point of wall w of `walls` (a WallGeometry), its kind, and the plane's signed distance (or -1)."""
    plane_p = walls.plane_p
    plane_n = walls.plane_n
    npl = plane_p.shape[0]
    if w < npl:
        d = (px - plane_p[w, 0]) * plane_n[w, 0] + (py - plane_p[w, 1]) * plane_n[w, 1]
        d += (pz - plane_p[w, 2]) * plane_n[w, 2]
        return px - d * plane_n[w, 0], py - d * plane_n[w, 1], pz - d * plane_n[w, 2], FACE, d
    qx, qy, qz, kind = closest_on_facet(px, py, pz, walls.facets[w - npl], walls.nv)
    return qx, qy, qz, kind, -1.0


@njit(cache=True)
def wall_distance(px, py, pz, w, walls):
    """Distance (m) from p to wall w of `walls` (a WallGeometry): signed for planes (negative behind), else unsigned."""
    qx, qy, qz, kind, d = wall_point(px, py, pz, w, walls)
    if w < walls.plane_p.shape[0]:
        return d
    return math.sqrt((px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2)


@njit(cache=True)
def build_wall_pairs(pos, radius, n, skin, walls, grid, wstart, wid):
    """CSR list (wstart, wid) of the walls (WallGeometry, its FacetGrid) within r + skin of each particle.

    Returns the entries needed (more than wid.size: call again with a larger wid).
    """
    cap = wid.size
    plane_p = walls.plane_p
    plane_n = walls.plane_n
    npl = plane_p.shape[0]
    glo = grid.lo
    gsize = grid.size
    gdims = grid.dims
    gstart = grid.start
    gitems = grid.items
    k = 0
    for i in range(n):
        wstart[i] = k
        px = pos[i, 0]
        py = pos[i, 1]
        pz = pos[i, 2]
        reach = radius[i] + skin
        for w in range(npl):  # signed distance to the plane, inline (the hot part for box-shaped beds)
            d = (px - plane_p[w, 0]) * plane_n[w, 0] + (py - plane_p[w, 1]) * plane_n[w, 1]
            if d + (pz - plane_p[w, 2]) * plane_n[w, 2] < reach:
                if k < cap:
                    wid[k] = w
                k += 1
        if gstart.size > 1:
            c = 0
            inside = True
            for a in range(3):
                q = int(math.floor((pos[i, a] - glo[a]) / gsize))
                if q < 0 or q >= gdims[a]:
                    inside = False
                c = c * gdims[a] + min(max(q, 0), gdims[a] - 1)
            if inside:
                for q in range(gstart[c], gstart[c + 1]):
                    w = npl + gitems[q]
                    if wall_distance(px, py, pz, w, walls) < reach:
                        if k < cap:
                            wid[k] = w
                        k += 1
    wstart[n] = k
    return k


@njit(cache=True)
def _facet_cells(facets, nv, f, reach, lo, size, dims):
    blo = np.empty(3, dtype=np.int64)
    bhi = np.empty(3, dtype=np.int64)
    for a in range(3):
        mn = facets[f, 0, a]
        mx = facets[f, 0, a]
        for v in range(1, nv):
            mn = min(mn, facets[f, v, a])
            mx = max(mx, facets[f, v, a])
        blo[a] = max(0, int(math.floor((mn - reach - lo[a]) / size)))
        bhi[a] = min(dims[a] - 1, int(math.floor((mx + reach - lo[a]) / size)))
    return blo, bhi


@njit(cache=True)
def _facet_grid(facets, nv, reach, lo, size, dims):
    nf = facets.shape[0]
    ncell = dims[0] * dims[1] * dims[2]
    counts = np.zeros(ncell + 1, dtype=np.int64)
    for f in range(nf):
        blo, bhi = _facet_cells(facets, nv, f, reach, lo, size, dims)
        for x in range(blo[0], bhi[0] + 1):
            for y in range(blo[1], bhi[1] + 1):
                for z in range(blo[2], bhi[2] + 1):
                    counts[(x * dims[1] + y) * dims[2] + z + 1] += 1
    for c in range(ncell):
        counts[c + 1] += counts[c]
    items = np.empty(counts[ncell], dtype=np.int64)
    fill = counts[:-1].copy()
    for f in range(nf):
        blo, bhi = _facet_cells(facets, nv, f, reach, lo, size, dims)
        for x in range(blo[0], bhi[0] + 1):
            for y in range(blo[1], bhi[1] + 1):
                for z in range(blo[2], bhi[2] + 1):
                    c = (x * dims[1] + y) * dims[2] + z
                    items[fill[c]] = f
                    fill[c] += 1
    return counts, items


@njit(cache=True)
def accept_contacts(kind, qs, ms, delta, cnt, accepted, order, tol):
    """Mark which of the cnt wall contacts of one particle push it (rule in the module docstring)."""
    if cnt == 1:
        accepted[0] = True
        return
    for a in range(cnt):
        order[a] = a
    for a in range(1, cnt):  # insertion sort by (kind, -delta)
        b = order[a]
        c = a - 1
        while c >= 0 and (kind[order[c]] > kind[b] or (kind[order[c]] == kind[b] and delta[order[c]] < delta[b])):
            order[c + 1] = order[c]
            c -= 1
        order[c + 1] = b
    for a in range(cnt):
        accepted[a] = False
    for a in range(cnt):
        b = order[a]
        ok = True
        for c in range(a):
            e = order[c]
            if accepted[e]:
                s = (qs[b, 0] - qs[e, 0]) * ms[e, 0] + (qs[b, 1] - qs[e, 1]) * ms[e, 1]
                s += (qs[b, 2] - qs[e, 2]) * ms[e, 2]
                if s <= tol:
                    ok = False
                    break
        accepted[b] = ok


class Walls:
    """Planes and facets confining the particles; candidates are listed per particle like the pair list."""

    def __init__(self, planes=None, facets=None):
        """planes: list of (point, normal into the domain); facets: array (nf, nv, 3), nv = 2 (2D), 3 or 4 (3D)."""
        pts, nrm = [], []
        for p, nvec in planes or []:
            nvec = np.asarray(nvec, dtype=float)
            ln = np.linalg.norm(nvec)
            if nvec.shape != (3,) or ln == 0:
                raise ValueError("plane normal must be a non-zero 3-vector")
            pts.append(np.asarray(p, dtype=float))
            nrm.append(nvec / ln)
        self.plane_p = np.array(pts, dtype=float).reshape(-1, 3)
        self.plane_n = np.array(nrm, dtype=float).reshape(-1, 3)
        self.nv = 3
        self.facets = np.zeros((0, 3, 3))
        if facets is not None and len(facets):
            f = np.asarray(facets, dtype=float)
            if f.ndim != 3 or f.shape[2] != 3 or f.shape[1] not in (2, 3, 4):
                raise ValueError(f"facets must have shape (nf, 2|3|4, 3), got {f.shape}")
            if f.shape[1] == 4:  # split quads into triangles (0,1,2), (0,2,3)
                f = np.concatenate([f[:, [0, 1, 2]], f[:, [0, 2, 3]]])
            self.nv = f.shape[1]
            self.facets = np.ascontiguousarray(f)
        self._grid_reach = -1.0
        self.glo = np.zeros(3)
        self.gsize = 1.0
        self.gdims = np.ones(3, dtype=np.int64)
        self.gstart = np.zeros(1, dtype=np.int64)
        self.gitems = np.zeros(0, dtype=np.int64)

    @property
    def geometry(self) -> WallGeometry:
        """The planes and facets as the kernels take them."""
        return WallGeometry(self.plane_p, self.plane_n, self.facets, self.nv)

    @property
    def grid(self) -> FacetGrid:
        """The facet grid of the last `prepare` (empty before)."""
        return FacetGrid(self.glo, self.gsize, self.gdims, self.gstart, self.gitems)

    @classmethod
    def from_facets(cls, facets, box=None, rtol: float = 1e-9) -> Walls:
        """Facet walls, with the faces of the domain's bounding box `box` = (lo, hi) (m) made planes.

        Every face of the box that the facets cover completely becomes one plane (inward normal) and its
        facets are dropped.

        Inside the box the two are the same wall (a particle near a fully covered face touches it at its
        projection), but a plane costs one distance per particle instead of a facet grid search and a few
        triangle tests: a box-shaped bed (seed 001's pseudo-2D column) then has only planes. Coverage is
        judged by area: the facets lying on the face (every vertex within rtol of the box size) must add up
        to the face's area within 1e-7 (a conforming boundary mesh has no overlapping facets, and one missing
        facet of a face meshed with up to millions of them is noticed).
        """
        f = np.asarray(facets, dtype=float)
        if box is None or f.shape[0] == 0:
            return cls(facets=f)
        lo, hi = np.asarray(box[0], dtype=float), np.asarray(box[1], dtype=float)
        ext = hi - lo
        tol = rtol * float(np.max(ext))
        size = _facet_sizes(f)
        keep = np.ones(f.shape[0], dtype=bool)
        planes = []
        for a in range(3):
            if ext[a] <= tol:  # the z axis of a 2D mesh
                continue
            others = [b for b in range(3) if b != a and ext[b] > tol]
            face = float(np.prod(ext[others]))
            for side, normal in ((lo, 1.0), (hi, -1.0)):
                on = keep & np.all(np.abs(f[:, :, a] - side[a]) <= tol, axis=1)
                if on.any() and abs(float(size[on].sum()) - face) <= 1e-7 * face:
                    e = np.zeros(3)
                    e[a] = normal
                    planes.append((side.copy(), e))
                    keep &= ~on
        return cls(planes=planes, facets=f[keep] if keep.any() else None)

    @classmethod
    def box(cls, lo, hi, dim: int = 3) -> Walls:
        """The planes of an axis-aligned box [lo, hi] (m), normals inward; in 2D only the x and y sides."""
        lo = np.asarray(lo, dtype=float)
        hi = np.asarray(hi, dtype=float)
        planes = []
        for a in range(dim):
            e = np.zeros(3)
            e[a] = 1.0
            planes += [(lo.copy(), e), (hi.copy(), -e)]
        return cls(planes=planes)

    @property
    def count(self) -> int:
        """Number of walls (planes + triangles/segments)."""
        return self.plane_p.shape[0] + self.facets.shape[0]

    def prepare(self, reach: float) -> None:
        """(Re)build the facet grid for candidates within `reach` (m) of a facet, if not done for this reach."""
        nf = self.facets.shape[0]
        if nf == 0 or reach <= self._grid_reach:
            return
        reach = 1.25 * reach  # margin so small changes of radius or skin need no rebuild
        lo = self.facets.min(axis=(0, 1)) - reach
        hi = self.facets.max(axis=(0, 1)) + reach
        ext = np.max(self.facets.max(axis=1) - self.facets.min(axis=1), axis=1)
        size = max(2.0 * reach, float(np.median(ext)))
        while np.prod(np.floor((hi - lo) / size) + 1) > max(8 * nf, 1000):
            size *= 1.5
        dims = (np.floor((hi - lo) / size) + 1).astype(np.int64)
        self.gstart, self.gitems = _facet_grid(self.facets, self.nv, reach, lo, size, dims)
        self.glo, self.gsize, self.gdims = lo, float(size), dims
        self._grid_reach = reach

    def distance(self, pos: np.ndarray) -> np.ndarray:
        """Distance (m) of each point (k, 3) to the nearest wall (planes signed), by brute force (for checks)."""
        out = np.full(pos.shape[0], np.inf)
        _nearest_walls(np.ascontiguousarray(pos, dtype=np.float64), self.count, self.geometry, out)
        return out


@njit(cache=True)
def _nearest_walls(pos, count, walls, out):
    """out[i] = distance of point i to the nearest of all `count` walls (brute force)."""
    for i in range(pos.shape[0]):
        for w in range(count):
            d = wall_distance(pos[i, 0], pos[i, 1], pos[i, 2], w, walls)
            if d < out[i]:
                out[i] = d


@njit(cache=True)
def wall_overlap_squares(pos, radius, n, wstart, wid, walls, weight):
    """Σ_i weight_i max(r_i − distance to the nearest candidate wall, 0)² over the rows' wall candidate lists (m²)."""
    total = 0.0
    for i in range(n):
        best = np.inf
        for k in range(wstart[i], wstart[i + 1]):
            d = wall_distance(pos[i, 0], pos[i, 1], pos[i, 2], wid[k], walls)
            if d < best:
                best = d
        if radius[i] > best:
            total += weight[i] * (radius[i] - best) ** 2
    return total


def _facet_sizes(f: np.ndarray) -> np.ndarray:
    """Length (segments), area (triangles) or area (planar quads, cyclic order) of each facet (nf, nv, 3)."""
    if f.shape[1] == 2:
        return np.linalg.norm(f[:, 1] - f[:, 0], axis=1)
    area = 0.5 * np.linalg.norm(np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0]), axis=1)
    if f.shape[1] == 4:
        area += 0.5 * np.linalg.norm(np.cross(f[:, 2] - f[:, 0], f[:, 3] - f[:, 0]), axis=1)
    return area


def touching(walls: Walls, pos: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Boolean mask of the spheres (centres pos (n, 3), radii m) that overlap or cross any wall."""
    n = pos.shape[0]
    walls.prepare(float(np.max(radius)) if n else 0.0)
    wstart = np.zeros(n + 1, dtype=np.int64)
    wid = np.zeros(max(16, n), dtype=np.int64)
    args = (pos, radius, n, 0.0, walls.geometry, walls.grid, wstart)
    need = build_wall_pairs(*args, wid)
    if need > wid.size:
        wid = np.zeros(need, dtype=np.int64)
        build_wall_pairs(*args, wid)
    return np.diff(wstart) > 0
