r"""Numba kernels of the dynamic coarse grain (PCPM, seed 000 sec 2.3) over plain particle arrays.

Groups are counts n of original particles of diameter d_O and one material density: a group's diameter is
d_O n^{1/3} (eqs 43, 46); n is a whole number, or a multiple of a unit 2^-j when the originals are divisible.
`equivalent_diameter` evaluates d_cl (eqs 32-39); `group_events` decides and builds the crush (eqs 40-43) and
merge (eqs 44-46) events of one evaluation. See `febed.coarse.pcpm` for the
choices where the paper is silent.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from febed.dem.walls import wall_distance, wall_point
from febed.kernel_records import fast_typeof

NO_CRUSH = np.inf  # d_cl where it is not positive and finite: the group does not crush


@fast_typeof
class Groups(NamedTuple):
    """The groups of one evaluation: rows [0, n) this rank's, [n, n_all) ghosts (obstacles only)."""

    pos: np.ndarray  # (n_all, 3) m
    vel: np.ndarray  # (n, 3) m/s
    omega: np.ndarray  # (n, 3) rad/s
    diam: np.ndarray  # (n_all,) m
    mass: np.ndarray  # (n_all,) kg
    n_orig: np.ndarray  # (n,) originals per group
    n: int
    n_all: int


@fast_typeof
class EventRules(NamedTuple):
    """How groups crush and merge (`febed.coarse.pcpm.GroupDynamics`'s settings)."""

    d_orig: float  # m: an original particle's diameter
    unit: float  # the smallest group, in originals (1, or 2^-j with divisible originals)
    dim2: bool  # 2D: children placed in a disk
    do_crush: bool
    do_merge: bool
    n_max: float  # largest group a merge may make, in originals
    merge_tol: float  # relative velocity below which touching groups merge
    tol: float  # overlap allowed after an event, relative to the smaller diameter
    tries: int  # placement draws per child
    conserve: bool  # accept an event only if it does not add energy


@fast_typeof
class Springs(NamedTuple):
    """The contact springs the events' elastic energy is counted with, and gravity."""

    kn_pp: float  # N/m: particle-particle normal stiffness
    mref_pp: float  # kg: > 0 for per-pair group scaling k_n (m_eff / m_ref)^(2/3), 0 for a fixed k_n
    kn_pw: float  # N/m: particle-wall
    mref_pw: float  # kg
    gvec: np.ndarray  # (3,) m/s^2


@fast_typeof
class Events(NamedTuple):
    """What `group_events` writes: the parents removed and the new groups."""

    removed: np.ndarray  # (n,) bool: parents of a crush or merge
    new_pos: np.ndarray  # (cap, 3) m
    new_vel: np.ndarray  # (cap, 3) m/s
    new_omega: np.ndarray  # (cap, 3) rad/s
    new_n: np.ndarray  # (cap,) originals per new group
    counts: np.ndarray  # (6,) int: crushed, children, merged, crush deferred, merge deferred, conflicts
    de: np.ndarray  # (2,) J: summed energy change of the accepted crushes and merges


@njit(cache=True)
def equivalent_diameter(eps, u, v, f_drag, mass, e_cc, d_orig, rho_p, rho_g, g, u_mf, eps_mf, eps_max, out):
    """Equivalent group diameter d_cl (m) per particle, seed 000 eqs 32-39; NO_CRUSH where not positive and finite.

    E_st = F_drag · u / m (W/kg, eq 37 per unit mass), U_p = (1 - ε) |v| (local superficial particle velocity),
    (E_st)_mf = g (ρ_p - ρ_g)/ρ_p (U_mf + ε_mf U_p/(1 - ε_mf)) (eq 35),
    K = g d_O (ρ_p - ρ_g)/ρ_p (U_p/(1 - ε_max) - (U_mf + ε_mf U_p/(1 - ε_mf))) (eq 36),
    d_cl = K / (E_st + E_cc - (E_st)_mf) (eq 39). Arrays: eps (N,), u, v, f_drag (N, 3), mass, e_cc (N,).
    """
    b = g * (rho_p - rho_g) / rho_p
    for p in range(eps.size):
        e = eps[p]
        if not (0.0 < e < 1.0):
            out[p] = NO_CRUSH
            continue
        up = (1.0 - e) * math.sqrt(v[p, 0] ** 2 + v[p, 1] ** 2 + v[p, 2] ** 2)
        e_st = (f_drag[p, 0] * u[p, 0] + f_drag[p, 1] * u[p, 1] + f_drag[p, 2] * u[p, 2]) / mass[p]  # eq 37
        mf = u_mf + eps_mf * up / (1.0 - eps_mf)
        e_mf = b * mf  # eq 35
        k = b * d_orig * (up / (1.0 - eps_max) - mf)  # eq 36
        e_in = e_st + e_cc[p] - e_mf  # eqs 33, 38
        if k > 0.0 and e_in > 0.0:
            d = k / e_in  # eqs 32, 39
            out[p] = d if d > 0.0 and math.isfinite(d) else NO_CRUSH
        else:
            out[p] = NO_CRUSH


@njit(cache=True)
def crush_sizes(n, d, d_cl, d_unit):
    """Children of a group of n units and diameter d crushed at d_cl (eqs 40-42), as integer counts of units.

    A unit is the smallest group (diameter d_unit): one original, or a fraction 2^-j of one when the originals
    are divisible (`GroupDynamics(min_group=...)`). n_new - 1 = floor(d²/d_cl²) children (eq 41) of
    k = max(1, floor((d_cl/d_unit)³)) units (diameter <= d_cl), capped so that the remainder child (eq 42) keeps
    at least one unit. Returns (k, n_full, remainder); n_full = 0 means the group cannot crush (n = 1 unit, or
    d <= d_cl).
    """
    if n < 2 or not d > d_cl or not d_cl > 0.0:
        return 0, 0, n
    x = d / d_cl
    k = max(1, int(math.floor((d_cl / d_unit) ** 3 * (1.0 + 1e-12))))
    n_full = min(math.floor(min(x * x, 1e18)), (n - 1) // k)  # eq 41 (x² capped: d_cl -> 0 gives inf)
    if n_full < 1:
        return 0, 0, n
    return k, n_full, n - n_full * k  # eq 42


@njit(cache=True)
def _grid(pos, n, h):
    lo = np.empty(3)
    dims = np.ones(3, dtype=np.int64)
    for a in range(3):
        lo[a] = pos[:n, a].min() - h if n else 0.0
    for a in range(3):
        ext = (pos[:n, a].max() + h - lo[a]) if n else 0.0
        dims[a] = max(1, int(ext / h) + 1)
    while dims[0] * dims[1] * dims[2] > 8 * n + 64:  # keep the grid O(n) for sparse clouds
        h *= 2.0
        for a in range(3):
            dims[a] = max(1, (dims[a] + 1) // 2)
    head = -np.ones(dims[0] * dims[1] * dims[2], dtype=np.int64)
    nxt = -np.ones(max(n, 1), dtype=np.int64)
    for i in range(n):
        c = _cell(pos[i, 0], pos[i, 1], pos[i, 2], lo, h, dims)
        nxt[i] = head[c]
        head[c] = i
    return lo, h, dims, head, nxt


# The small helpers below are plain Numba calls, not `inline="always"`: LLVM inlines them all the same (the
# PCPM probes are bit for bit those of the IR-inlined version), while Numba's IR inlining made the kernels
# that use them compile in 40 s instead of 12 (benchmarks/kernel_compile.py).
@njit(cache=True)
def _ci(x, lo, h, m):
    c = int((x - lo) / h)
    return min(max(c, 0), m - 1)


@njit(cache=True)
def _cell_range(x, y, z, reach, lo, h, dims):
    """Index ranges (i0, i1, j0, j1, k0, k1) of the grid cells within `reach` of (x, y, z)."""
    return (_ci(x - reach, lo[0], h, dims[0]), _ci(x + reach, lo[0], h, dims[0]),
            _ci(y - reach, lo[1], h, dims[1]), _ci(y + reach, lo[1], h, dims[1]),
            _ci(z - reach, lo[2], h, dims[2]), _ci(z + reach, lo[2], h, dims[2]))  # fmt: skip


@njit(cache=True)
def _cell(x, y, z, lo, h, dims):
    return (_ci(x, lo[0], h, dims[0]) * dims[1] + _ci(y, lo[1], h, dims[1])) * dims[2] + _ci(z, lo[2], h, dims[2])


@njit(cache=True)
def _overlap_static(x, y, z, r, pos, diam, skip1, skip2, lo, h, dims, head, nxt, rmax):
    """Largest overlap / min(diameters) of a sphere (x, r) with the listed particles other than skip1, skip2."""
    reach = r + rmax
    worst = 0.0
    i0, i1, j0, j1, k0, k1 = _cell_range(x, y, z, reach, lo, h, dims)
    for ci in range(i0, i1 + 1):
        for cj in range(j0, j1 + 1):
            for ck in range(k0, k1 + 1):
                q = head[(ci * dims[1] + cj) * dims[2] + ck]
                while q >= 0:
                    if q != skip1 and q != skip2:
                        rq = 0.5 * diam[q]
                        dist = math.sqrt((pos[q, 0] - x) ** 2 + (pos[q, 1] - y) ** 2 + (pos[q, 2] - z) ** 2)
                        ov = r + rq - dist
                        if ov > 0.0:
                            worst = max(worst, ov / (2.0 * min(r, rq)))
                    q = nxt[q]
    return worst


@njit(cache=True)
def _overlap_walls(x, y, z, r, walls):
    worst = 0.0
    for w in range(walls.plane_p.shape[0] + walls.facets.shape[0]):
        ov = r - wall_distance(x, y, z, w, walls)
        if ov > 0.0:
            worst = max(worst, ov / (2.0 * r))
    return worst


@njit(cache=True)
def _stiffness(kn, m_ref, ma, mb):
    """Normal stiffness (N/m) of a pair of masses ma, mb (kg; mb = inf for a wall): k_n, or k_n (m_eff/m_ref)^(2/3)."""
    if m_ref > 0.0:
        m_eff = ma if math.isinf(mb) else ma * mb / (ma + mb)
        return kn * (m_eff / m_ref) ** (2.0 / 3.0)
    return kn


@njit(cache=True)
def _energy_static(x, y, z, r, mq, pos, diam, mass, skip1, skip2, lo, h, dims, head, nxt, rmax, kn, m_ref):
    """Spring energy (J) of a sphere (x, r, mass mq) overlapping the listed particles other than skip1, skip2."""
    reach = r + rmax
    e = 0.0
    i0, i1, j0, j1, k0, k1 = _cell_range(x, y, z, reach, lo, h, dims)
    for ci in range(i0, i1 + 1):
        for cj in range(j0, j1 + 1):
            for ck in range(k0, k1 + 1):
                q = head[(ci * dims[1] + cj) * dims[2] + ck]
                while q >= 0:
                    if q != skip1 and q != skip2:
                        dist = math.sqrt((pos[q, 0] - x) ** 2 + (pos[q, 1] - y) ** 2 + (pos[q, 2] - z) ** 2)
                        ov = r + 0.5 * diam[q] - dist
                        if ov > 0.0:
                            e += 0.5 * _stiffness(kn, m_ref, mq, mass[q]) * ov * ov
                    q = nxt[q]
    return e


@njit(cache=True)
def _energy_walls(x, y, z, r, mq, walls, kn, m_ref):
    """Spring energy (J) of a sphere (x, r, mass mq) against its nearest wall (as `DEM.elastic_energy`)."""
    best = np.inf
    for w in range(walls.plane_p.shape[0] + walls.facets.shape[0]):
        best = min(best, wall_distance(x, y, z, w, walls))
    if r > best:
        return 0.5 * _stiffness(kn, m_ref, mq, np.inf) * (r - best) ** 2
    return 0.0


@njit(cache=True)
def _pair_energy(a, b, pos, diam, mass, kn, m_ref):
    """Spring energy (J) of the pair of rows a, b (0 if they do not touch)."""
    dist = math.sqrt((pos[a, 0] - pos[b, 0]) ** 2 + (pos[a, 1] - pos[b, 1]) ** 2 + (pos[a, 2] - pos[b, 2]) ** 2)
    ov = 0.5 * (diam[a] + diam[b]) - dist
    return 0.5 * _stiffness(kn, m_ref, mass[a], mass[b]) * ov * ov if ov > 0.0 else 0.0


@njit(cache=True)
def _conflicts(x, y, z, ext, ev, n_ev):
    for e in range(n_ev):
        dist = math.sqrt((ev[e, 0] - x) ** 2 + (ev[e, 1] - y) ** 2 + (ev[e, 2] - z) ** 2)
        if dist < ext + ev[e, 3]:
            return True
    return False


@njit(cache=True)
def _place_children(i, nk, r_rem, r_full, R, pos, diam, dim2, tries, tol, target, lo, h, dims, head, nxt, rmax,
                    walls, kids):  # fmt: skip
    """Centres of the nk children of group i in kids[:nk] (x, y, z, r); False if an overlap would exceed tol.

    The siblings are relaxed apart until their largest overlap is at most `target` (fraction of the smaller
    diameter; 0: apart) or for 200 sweeps.
    """
    for c in range(nk):  # the larger of remainder / full children first
        first_rem = r_rem >= r_full
        is_rem = (c == 0) if first_rem else (c == nk - 1)
        rc = r_rem if is_rem else r_full
        best = np.inf
        bx = by = bz = 0.0
        for _ in range(tries):
            while True:
                qx = 2.0 * np.random.random() - 1.0  # noqa: NPY002
                qy = 2.0 * np.random.random() - 1.0  # noqa: NPY002
                qz = 0.0 if dim2 else 2.0 * np.random.random() - 1.0  # noqa: NPY002
                if qx * qx + qy * qy + qz * qz <= 1.0:
                    break
            x = pos[i, 0] + R * qx
            y = pos[i, 1] + R * qy
            z = pos[i, 2] + R * qz
            s = _overlap_static(x, y, z, rc, pos, diam, i, i, lo, h, dims, head, nxt, rmax)
            s = max(s, _overlap_walls(x, y, z, rc, walls))
            sib = -np.inf  # relative overlap with the closest sibling: negative = gap, maximised
            for b in range(c):
                dist = math.sqrt((kids[b, 0] - x) ** 2 + (kids[b, 1] - y) ** 2 + (kids[b, 2] - z) ** 2)
                sib = max(sib, (rc + kids[b, 3] - dist) / (2.0 * min(rc, kids[b, 3])))
            s = max(s, sib)
            if s < best:
                best = s
                bx, by, bz = x, y, z
        kids[c, 0] = bx
        kids[c, 1] = by
        kids[c, 2] = bz
        kids[c, 3] = rc
    # relax the siblings apart (pairwise half-overlap pushes, centres kept in the parent's sphere), then check all
    cx, cy, cz = pos[i, 0], pos[i, 1], pos[i, 2]
    for _ in range(200):
        worst = 0.0
        for a in range(nk):
            for b in range(a + 1, nk):
                dx = kids[b, 0] - kids[a, 0]
                dy = kids[b, 1] - kids[a, 1]
                dz = kids[b, 2] - kids[a, 2]
                dist = math.sqrt(dx * dx + dy * dy + dz * dz)
                ov = kids[a, 3] + kids[b, 3] - dist
                if ov <= 0.0:
                    continue
                worst = max(worst, ov / (2.0 * min(kids[a, 3], kids[b, 3])))
                if dist == 0.0:
                    dx, dist = 1.0, 1.0
                hair = 1e-9 * min(kids[a, 3], kids[b, 3]) if target <= 0.0 else 0.0  # target 0: apart by a hair
                f = 0.5 * (ov + hair) / dist
                kids[a, 0] -= f * dx
                kids[a, 1] -= f * dy
                kids[b, 0] += f * dx
                kids[b, 1] += f * dy
                if not dim2:
                    kids[a, 2] -= f * dz
                    kids[b, 2] += f * dz
        for a in range(nk):
            dx = kids[a, 0] - cx
            dy = kids[a, 1] - cy
            dz = kids[a, 2] - cz
            dist = math.sqrt(dx * dx + dy * dy + dz * dz)
            if dist > R:
                kids[a, 0] = cx + dx * R / dist
                kids[a, 1] = cy + dy * R / dist
                kids[a, 2] = cz + dz * R / dist
        if worst <= target:
            break
    for c in range(nk):
        x, y, z, rc = kids[c, 0], kids[c, 1], kids[c, 2], kids[c, 3]
        s = _overlap_static(x, y, z, rc, pos, diam, i, i, lo, h, dims, head, nxt, rmax)
        s = max(s, _overlap_walls(x, y, z, rc, walls))
        for b in range(c):
            dist = math.sqrt((kids[b, 0] - x) ** 2 + (kids[b, 1] - y) ** 2 + (kids[b, 2] - z) ** 2)
            s = max(s, (rc + kids[b, 3] - dist) / (2.0 * min(rc, kids[b, 3])))
        if s > tol:
            return False
    return True


@njit(cache=True)
def _near_ghosts(pos, diam, n, lo, h, dims, head, nxt, rmax, out):
    """Mark the rows i < n whose sphere comes within 2 rmax of a row j >= n (a ghost)."""
    for i in range(n):
        ri = 0.5 * diam[i]
        reach = ri + 3.0 * rmax
        i0, i1, j0, j1, k0, k1 = _cell_range(pos[i, 0], pos[i, 1], pos[i, 2], reach, lo, h, dims)
        for ci in range(i0, i1 + 1):
            for cj in range(j0, j1 + 1):
                for ck in range(k0, k1 + 1):
                    j = head[(ci * dims[1] + cj) * dims[2] + ck]
                    while j >= 0 and not out[i]:
                        if j >= n:
                            dx = pos[j, 0] - pos[i, 0]
                            dy = pos[j, 1] - pos[i, 1]
                            dz = pos[j, 2] - pos[i, 2]
                            if dx * dx + dy * dy + dz * dz < (ri + 0.5 * diam[j] + 2.0 * rmax) ** 2:
                                out[i] = True
                        j = nxt[j]


@njit(cache=True)
def _relax_merged(x, y, z, rn, i, j, smax, dim2, pos, diam, lo, h, dims, head, nxt, rmax, walls):  # fmt: skip
    """Centre of a merged group of radius rn moved from (x, y, z) out of its overlaps, by at most smax (m).

    Pushes of the overlaps with the other groups (not i, j) and the walls, 20 sweeps at most.
    """
    cx, cy, cz = x, y, z
    reach = rn + rmax
    for _ in range(20):
        px = py = pz = 0.0
        hit = False
        i0, i1, j0, j1, k0, k1 = _cell_range(x, y, z, reach, lo, h, dims)
        for ci in range(i0, i1 + 1):
            for cj in range(j0, j1 + 1):
                for ck in range(k0, k1 + 1):
                    q = head[(ci * dims[1] + cj) * dims[2] + ck]
                    while q >= 0:
                        if q != i and q != j:
                            dx = x - pos[q, 0]
                            dy = y - pos[q, 1]
                            dz = z - pos[q, 2]
                            dist = math.sqrt(dx * dx + dy * dy + dz * dz)
                            ov = rn + 0.5 * diam[q] - dist
                            if ov > 0.0 and dist > 0.0:
                                px += ov * dx / dist
                                py += ov * dy / dist
                                pz += ov * dz / dist
                                hit = True
                        q = nxt[q]
        for w in range(walls.plane_p.shape[0] + walls.facets.shape[0]):
            qx, qy, qz, _kind, sd = wall_point(x, y, z, w, walls)
            if w < walls.plane_p.shape[0]:
                ov = rn - sd
                nx, ny, nz = walls.plane_n[w, 0], walls.plane_n[w, 1], walls.plane_n[w, 2]
            else:
                dist = math.sqrt((x - qx) ** 2 + (y - qy) ** 2 + (z - qz) ** 2)
                ov = rn - dist
                if dist == 0.0:
                    continue
                nx, ny, nz = (x - qx) / dist, (y - qy) / dist, (z - qz) / dist
            if ov > 0.0:
                px += ov * nx
                py += ov * ny
                pz += ov * nz
                hit = True
        if not hit:
            break
        x += 0.5 * px
        y += 0.5 * py
        if not dim2:
            z += 0.5 * pz
        d = math.sqrt((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2)
        if d > smax:
            x = cx + (x - cx) * smax / d
            y = cy + (y - cy) * smax / d
            z = cz + (z - cz) * smax / d
    return x, y, z


@njit(cache=True)
def _merge_energy(i, j, x, y, z, cx, cy, cz, rn, pos, vel, omega, diam, mass, lo, h, dims, head, nxt, rmax,
                  walls, kn_pp, mref_pp, kn_pw, mref_pw, gvec):  # fmt: skip
    """ΔE (J) of merging rows i, j (centre of mass c) into one group of radius rn at (x, y, z) (`group_events`).

    Kinetic: the relative translation energy and some spin energy are lost (momentum and the summed I ω kept);
    elastic: the springs of i and j (with each other, the others, the nearest wall) go, the merged group's come;
    gravitational: -(m_i + m_j) g · (x - c).
    """
    mi, mj = mass[i], mass[j]
    mn = mi + mj
    dn = 2.0 * rn
    e = -mn * ((x - cx) * gvec[0] + (y - cy) * gvec[1] + (z - cz) * gvec[2])
    ii = 0.1 * mi * diam[i] ** 2  # I = m d² / 10, as `Particles`
    jj = 0.1 * mj * diam[j] ** 2
    inn = 0.1 * mn * dn * dn
    for a in range(3):
        v = (mi * vel[i, a] + mj * vel[j, a]) / mn
        w = (ii * omega[i, a] + jj * omega[j, a]) / inn
        e += 0.5 * mn * v * v + 0.5 * inn * w * w
        e -= 0.5 * mi * vel[i, a] ** 2 + 0.5 * mj * vel[j, a] ** 2
        e -= 0.5 * ii * omega[i, a] ** 2 + 0.5 * jj * omega[j, a] ** 2
    e += _energy_static(x, y, z, rn, mn, pos, diam, mass, i, j, lo, h, dims, head, nxt, rmax, kn_pp, mref_pp)
    e += _energy_walls(x, y, z, rn, mn, walls, kn_pw, mref_pw)
    for p in (i, j):
        rp = 0.5 * diam[p]
        e -= _energy_static(pos[p, 0], pos[p, 1], pos[p, 2], rp, mass[p], pos, diam, mass, i, j, lo, h, dims, head,
                            nxt, rmax, kn_pp, mref_pp)  # fmt: skip
        e -= _energy_walls(pos[p, 0], pos[p, 1], pos[p, 2], rp, mass[p], walls, kn_pw, mref_pw)
    e -= _pair_energy(i, j, pos, diam, mass, kn_pp, mref_pp)
    return e


@njit(cache=True)
def group_events(groups, d_cl, turn, seed, rules, walls, springs, out):
    """Crush and merge events of one evaluation over rows [0, n); returns the number of new groups written.

    groups: `Groups`; d_cl (n,) m: each group's equivalent diameter; turn: this rank's turn (below); seed: of
    the placement draws; rules: `EventRules`; walls: `febed.dem.walls.WallGeometry`; springs: `Springs`;
    out: `Events`, written.

    Rows [n, n_all) are another rank's groups (MPI ghosts): obstacles for the overlap checks, never part of an
    event. Unless `turn`, a group within 2 largest radii of a ghost takes part in no event either (it waits
    for this rank's turn, so that two ranks never place groups in the same region in one evaluation).

    n_orig (n_all,) originals per group, whole multiples of `unit` (1, or 2^-j with divisible originals): a crush
    never makes a group below one unit (diameter d_orig unit^(1/3)).

    Crushing (eqs 40-43): groups with d > d_cl split into `crush_sizes` children with the parent's velocity and
    spin, centres drawn uniformly in the parent's sphere (disk in 2D); for each child the best of `tries` draws
    (smallest overlap with the other groups and the walls, and the largest gap to its siblings) is kept, so the
    children spread through the parent's volume, then the siblings are relaxed apart (pairwise pushes, centres
    kept in the parent's sphere); after 4 failed attempts the crush is deferred if an
    overlap would exceed `tol` (fraction of the smaller diameter). Merging (eqs 44-46): touching groups with
    |v_i - v_j| < merge_tol max(|v_i|, |v_j|), n_i + n_j <= n_max and a merged diameter not above either d_cl
    become one group at their centre of mass with the count-weighted (= mass-weighted) velocity and spin, unless it
    would overlap beyond `tol`. Events whose regions intersect an earlier event of this evaluation wait.

    Energy: ΔE of an event is the change of kinetic (translation + spin), elastic (normal springs with the
    contact law's stiffness: k_n = kn_pp, or kn_pp (m_eff/mref_pp)^(2/3) if mref_pp > 0; walls kn_pw, mref_pw,
    nearest wall) and gravitational (gvec, m/s²) energy of the groups it removes and creates, their contacts
    included. With `conserve`, an event is accepted only if ΔE <= 0 (a crush gets its 4 placement attempts
    first); otherwise it is deferred. `mass` (n_all,) kg; masses of new groups are the parents' by count.
    `removed` (n,) marks parents; counts: [crushed, children, merged, crush deferred, merge deferred, conflicts];
    de (2,) receives the summed ΔE (J) of the accepted crushes and merges.
    """
    pos, vel, omega, diam, mass, n_orig, n, n_all = groups
    d_orig, unit, dim2, do_crush, do_merge, n_max, merge_tol, tol, tries, conserve = rules
    kn_pp, mref_pp, kn_pw, mref_pw, gvec = springs
    removed, new_pos, new_vel, new_omega, new_n, counts, de = out
    np.random.seed(seed)  # noqa: NPY002 (Numba supports only the legacy API)
    rmax = 0.0
    for i in range(n_all):
        rmax = max(rmax, 0.5 * diam[i])
    lo, h, dims, head, nxt = _grid(pos, n_all, max(2.0 * rmax, 1e-300))
    frozen = np.zeros(n, dtype=np.bool_)
    if n_all > n and not turn:
        _near_ghosts(pos, diam, n, lo, h, dims, head, nxt, rmax, frozen)
    ev = np.empty((n + 1, 4))  # event regions: centre, radius
    n_ev = 0
    m = 0
    for a in range(6):
        counts[a] = 0
    de[0] = 0.0
    de[1] = 0.0
    for i in range(n):
        removed[i] = False
    cap = new_n.size
    d_unit = d_orig * unit ** (1.0 / 3.0)
    # ------------------------------------------------------------------ crushing (eqs 40-43)
    kids = np.empty((max(cap, 1), 4))
    for i in range(n):
        if not do_crush:
            break
        k, n_full, rem = crush_sizes(int(round(n_orig[i] / unit)), diam[i], d_cl[i], d_unit)
        if n_full == 0:
            continue
        if frozen[i]:  # at the partition: waits for this rank's turn
            counts[5] += 1
            continue
        R = 0.5 * diam[i]
        nk = n_full + 1
        if m + nk > cap:
            counts[3] += 1
            continue
        r_full = 0.5 * d_unit * k ** (1.0 / 3.0)
        r_rem = 0.5 * d_unit * rem ** (1.0 / 3.0)
        ext = R + max(r_full, r_rem)
        if _conflicts(pos[i, 0], pos[i, 1], pos[i, 2], ext, ev, n_ev):
            counts[5] += 1
            continue
        # energy of the parent: its springs (others, nearest wall) and spin (translation: the children's is equal)
        mi = mass[i]
        e_old = _energy_static(pos[i, 0], pos[i, 1], pos[i, 2], R, mi, pos, diam, mass, i, i, lo, h, dims, head, nxt,
                               rmax, kn_pp, mref_pp)  # fmt: skip
        e_old += _energy_walls(pos[i, 0], pos[i, 1], pos[i, 2], R, mi, walls, kn_pw, mref_pw)
        w2 = omega[i, 0] ** 2 + omega[i, 1] ** 2 + omega[i, 2] ** 2
        e_old += 0.5 * 0.1 * mi * diam[i] ** 2 * w2  # I = m d² / 10 (solid sphere, as `Particles`)
        ok = False
        d_e = 0.0
        for _attempt in range(4):  # a few fresh attempts before deferring the crush
            ok = _place_children(i, nk, r_rem, r_full, R, pos, diam, dim2, tries, tol, 0.0 if conserve else 0.5 * tol,
                                 lo, h, dims, head, nxt, rmax, walls, kids)  # fmt: skip
            if ok:
                d_e = -e_old
                for c in range(nk):
                    rc = kids[c, 3]
                    mc = mi * (rc / R) ** 3
                    d_e += _energy_static(kids[c, 0], kids[c, 1], kids[c, 2], rc, mc, pos, diam, mass, i, i, lo, h,
                                          dims, head, nxt, rmax, kn_pp, mref_pp)  # fmt: skip
                    d_e += _energy_walls(kids[c, 0], kids[c, 1], kids[c, 2], rc, mc, walls,
                                         kn_pw, mref_pw)  # fmt: skip
                    d_e += 0.5 * 0.1 * mc * (2.0 * rc) ** 2 * w2
                    d_e -= mc * ((kids[c, 0] - pos[i, 0]) * gvec[0] + (kids[c, 1] - pos[i, 1]) * gvec[1]
                                 + (kids[c, 2] - pos[i, 2]) * gvec[2])  # fmt: skip
                    for b in range(c):
                        dist = math.sqrt((kids[b, 0] - kids[c, 0]) ** 2 + (kids[b, 1] - kids[c, 1]) ** 2
                                         + (kids[b, 2] - kids[c, 2]) ** 2)  # fmt: skip
                        ov = rc + kids[b, 3] - dist
                        if ov > 0.0:
                            d_e += 0.5 * _stiffness(kn_pp, mref_pp, mc, mi * (kids[b, 3] / R) ** 3) * ov * ov
                ok = d_e <= 0.0 or not conserve
            if ok:
                break
        if not ok:
            counts[3] += 1
            continue
        de[0] += d_e
        for c in range(nk):
            for a in range(3):
                new_pos[m, a] = kids[c, a]
                new_vel[m, a] = vel[i, a]  # inherited from the parent (seed 000 sec 2.3)
                new_omega[m, a] = omega[i, a]
            first_rem = r_rem >= r_full
            is_rem = (c == 0) if first_rem else (c == nk - 1)
            new_n[m] = (rem if is_rem else k) * unit  # exact: unit is a power of 2
            m += 1
        removed[i] = True
        ev[n_ev, 0] = pos[i, 0]
        ev[n_ev, 1] = pos[i, 1]
        ev[n_ev, 2] = pos[i, 2]
        ev[n_ev, 3] = ext
        n_ev += 1
        counts[0] += 1
        counts[1] += nk
    # ------------------------------------------------------------------ merging (eqs 44-46)
    for i in range(n):
        if not do_merge or removed[i] or frozen[i]:
            continue
        ri = 0.5 * diam[i]
        vi = math.sqrt(vel[i, 0] ** 2 + vel[i, 1] ** 2 + vel[i, 2] ** 2)
        reach = ri + rmax
        i0, i1, j0, j1, k0, k1 = _cell_range(pos[i, 0], pos[i, 1], pos[i, 2], reach, lo, h, dims)
        done = False
        for ci in range(i0, i1 + 1):
            for cj in range(j0, j1 + 1):
                for ck in range(k0, k1 + 1):
                    j = head[(ci * dims[1] + cj) * dims[2] + ck]
                    while j >= 0 and not done:
                        if j > i and j < n and not removed[j] and not frozen[j] and n_orig[i] + n_orig[j] <= n_max:
                            rj = 0.5 * diam[j]
                            dx = pos[j, 0] - pos[i, 0]
                            dy = pos[j, 1] - pos[i, 1]
                            dz = pos[j, 2] - pos[i, 2]
                            dist = math.sqrt(dx * dx + dy * dy + dz * dz)
                            dv = math.sqrt((vel[i, 0] - vel[j, 0]) ** 2 + (vel[i, 1] - vel[j, 1]) ** 2
                                           + (vel[i, 2] - vel[j, 2]) ** 2)  # fmt: skip
                            vj = math.sqrt(vel[j, 0] ** 2 + vel[j, 1] ** 2 + vel[j, 2] ** 2)
                            nn = n_orig[i] + n_orig[j]
                            dn = d_orig * nn ** (1.0 / 3.0)  # eq 46
                            if dist < ri + rj and dv < merge_tol * max(vi, vj) and dn <= min(d_cl[i], d_cl[j]):
                                wi = n_orig[i] / nn  # mass fractions: same material, so count fractions
                                wj = n_orig[j] / nn
                                x = wi * pos[i, 0] + wj * pos[j, 0]
                                y = wi * pos[i, 1] + wj * pos[j, 1]
                                z = wi * pos[i, 2] + wj * pos[j, 2]
                                rn = 0.5 * dn
                                di = math.sqrt((x - pos[i, 0]) ** 2 + (y - pos[i, 1]) ** 2 + (z - pos[i, 2]) ** 2)
                                dj = math.sqrt((x - pos[j, 0]) ** 2 + (y - pos[j, 1]) ** 2 + (z - pos[j, 2]) ** 2)
                                smax = 0.5 * min(ri, rj) if conserve else 0.0  # the centre may move off the c.o.m.
                                ext = max(rn + smax, di + ri, dj + rj)
                                if _conflicts(x, y, z, ext, ev, n_ev):
                                    counts[5] += 1
                                elif m >= cap:
                                    counts[4] += 1
                                else:
                                    cx, cy, cz = x, y, z
                                    if smax > 0.0:
                                        x, y, z = _relax_merged(
                                            x, y, z, rn, i, j, smax, dim2, pos, diam, lo, h, dims, head, nxt, rmax,
                                            walls,
                                        )  # fmt: skip
                                    s = _overlap_static(x, y, z, rn, pos, diam, i, j, lo, h, dims, head, nxt, rmax)
                                    s = max(s, _overlap_walls(x, y, z, rn, walls))
                                    d_e = _merge_energy(i, j, x, y, z, cx, cy, cz, rn, pos, vel, omega, diam, mass,
                                                        lo, h, dims, head, nxt, rmax, walls,
                                                        kn_pp, mref_pp, kn_pw, mref_pw, gvec)  # fmt: skip
                                    if s > tol or (conserve and d_e > 0.0):
                                        counts[4] += 1
                                    else:
                                        de[1] += d_e
                                        new_pos[m, 0] = x
                                        new_pos[m, 1] = y
                                        new_pos[m, 2] = z
                                        ii = n_orig[i] * diam[i] ** 2  # spin: I ω summed, I ∝ n d²
                                        jj = n_orig[j] * diam[j] ** 2
                                        for a in range(3):
                                            new_vel[m, a] = wi * vel[i, a] + wj * vel[j, a]  # eq 45, momentum
                                            new_omega[m, a] = (ii * omega[i, a] + jj * omega[j, a]) / (nn * dn * dn)
                                        new_n[m] = nn
                                        m += 1
                                        removed[i] = True
                                        removed[j] = True
                                        ev[n_ev, 0] = x
                                        ev[n_ev, 1] = y
                                        ev[n_ev, 2] = z
                                        ev[n_ev, 3] = ext
                                        n_ev += 1
                                        counts[2] += 1
                                        done = True
                        j = nxt[j] if not done else -1
    return m
