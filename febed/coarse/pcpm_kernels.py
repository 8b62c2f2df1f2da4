r"""Numba kernels of the dynamic coarse grain (PCPM, seed 000 sec 2.3) over plain particle arrays.

Groups are integer counts n of original particles of diameter d_O and one material density: a group's
diameter is d_O n^{1/3} (eqs 43, 46). `equivalent_diameter` evaluates d_cl (eqs 32-39); `group_events` decides
and builds the crush (eqs 40-43) and merge (eqs 44-46) events of one evaluation. See `febed.coarse.pcpm` for the
choices where the paper is silent.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from febed.dem.walls import wall_distance

NO_CRUSH = np.inf  # d_cl where it is not positive and finite: the group does not crush


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
def crush_sizes(n, d, d_cl, d_orig):
    """Children of a group of n originals and diameter d crushed at d_cl (eqs 40-42), as integer counts.

    n_new - 1 = floor(d²/d_cl²) children (eq 41) of k = max(1, floor((d_cl/d_O)³)) originals (diameter <= d_cl),
    capped so that the remainder child (eq 42) keeps at least one original. Returns (k, n_full, remainder);
    n_full = 0 means the group cannot crush (n = 1, or d <= d_cl).
    """
    if n < 2 or not d > d_cl or not d_cl > 0.0:
        return 0, 0, n
    x = d / d_cl
    k = max(1, int(math.floor((d_cl / d_orig) ** 3 * (1.0 + 1e-12))))
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


@njit(cache=True, inline="always")
def _ci(x, lo, h, m):
    c = int((x - lo) / h)
    return min(max(c, 0), m - 1)


@njit(cache=True, inline="always")
def _cell_range(x, y, z, reach, lo, h, dims):
    """Index ranges (i0, i1, j0, j1, k0, k1) of the grid cells within `reach` of (x, y, z)."""
    return (_ci(x - reach, lo[0], h, dims[0]), _ci(x + reach, lo[0], h, dims[0]),
            _ci(y - reach, lo[1], h, dims[1]), _ci(y + reach, lo[1], h, dims[1]),
            _ci(z - reach, lo[2], h, dims[2]), _ci(z + reach, lo[2], h, dims[2]))  # fmt: skip


@njit(cache=True, inline="always")
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
def _overlap_walls(x, y, z, r, plane_p, plane_n, facets, nv):
    worst = 0.0
    for w in range(plane_p.shape[0] + facets.shape[0]):
        ov = r - wall_distance(x, y, z, w, plane_p, plane_n, facets, nv)
        if ov > 0.0:
            worst = max(worst, ov / (2.0 * r))
    return worst


@njit(cache=True)
def _conflicts(x, y, z, ext, ev, n_ev):
    for e in range(n_ev):
        dist = math.sqrt((ev[e, 0] - x) ** 2 + (ev[e, 1] - y) ** 2 + (ev[e, 2] - z) ** 2)
        if dist < ext + ev[e, 3]:
            return True
    return False


@njit(cache=True)
def _place_children(i, nk, r_rem, r_full, R, pos, diam, dim2, tries, tol, lo, h, dims, head, nxt, rmax, plane_p,
                    plane_n, facets, nv, kids):  # fmt: skip
    """Centres of the nk children of group i in kids[:nk] (x, y, z, r); False if an overlap would exceed tol."""
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
            s = max(s, _overlap_walls(x, y, z, rc, plane_p, plane_n, facets, nv))
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
                f = 0.5 * ov / dist
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
        if worst <= 0.5 * tol:
            break
    for c in range(nk):
        x, y, z, rc = kids[c, 0], kids[c, 1], kids[c, 2], kids[c, 3]
        s = _overlap_static(x, y, z, rc, pos, diam, i, i, lo, h, dims, head, nxt, rmax)
        s = max(s, _overlap_walls(x, y, z, rc, plane_p, plane_n, facets, nv))
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
def group_events(
    pos, vel, omega, diam, n_orig, n, n_all, turn, d_orig, dim2, d_cl, do_crush, do_merge, n_max, merge_tol, tol,
    tries, seed, plane_p, plane_n, facets, nv, removed, new_pos, new_vel, new_omega, new_n, counts,
):  # fmt: skip
    """Crush and merge events of one evaluation over rows [0, n); returns the number of new groups written.

    Rows [n, n_all) are another rank's groups (MPI ghosts): obstacles for the overlap checks, never part of an
    event. Unless `turn`, a group within 2 largest radii of a ghost takes part in no event either (it waits
    for this rank's turn, so that two ranks never place groups in the same region in one evaluation).

    Crushing (eqs 40-43): groups with d > d_cl split into `crush_sizes` children with the parent's velocity and
    spin, centres drawn uniformly in the parent's sphere (disk in 2D); for each child the best of `tries` draws
    (smallest overlap with the other groups and the walls, and the largest gap to its siblings) is kept, so the
    children spread through the parent's volume, then the siblings are relaxed apart (pairwise pushes, centres
    kept in the parent's sphere); after 4 failed attempts the crush is deferred if an
    overlap would exceed `tol` (fraction of the smaller diameter). Merging (eqs 44-46): touching groups with
    |v_i - v_j| < merge_tol max(|v_i|, |v_j|), n_i + n_j <= n_max and a merged diameter not above either d_cl
    become one group at their centre of mass with the count-weighted (= mass-weighted) velocity and spin, unless it
    would overlap beyond `tol`. Events whose regions intersect an earlier event of this evaluation wait.
    `removed` (n,) marks parents; counts: [crushed, children, merged, crush deferred, merge deferred, conflicts].
    """
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
    for i in range(n):
        removed[i] = False
    cap = new_n.size
    # ------------------------------------------------------------------ crushing (eqs 40-43)
    kids = np.empty((max(cap, 1), 4))
    for i in range(n):
        if not do_crush:
            break
        k, n_full, rem = crush_sizes(n_orig[i], diam[i], d_cl[i], d_orig)
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
        r_full = 0.5 * d_orig * k ** (1.0 / 3.0)
        r_rem = 0.5 * d_orig * rem ** (1.0 / 3.0)
        ext = R + max(r_full, r_rem)
        if _conflicts(pos[i, 0], pos[i, 1], pos[i, 2], ext, ev, n_ev):
            counts[5] += 1
            continue
        ok = False
        for _attempt in range(4):  # a few fresh attempts before deferring the crush
            ok = _place_children(i, nk, r_rem, r_full, R, pos, diam, dim2, tries, tol, lo, h, dims, head, nxt, rmax,
                                 plane_p, plane_n, facets, nv, kids)  # fmt: skip
            if ok:
                break
        if not ok:
            counts[3] += 1
            continue
        for c in range(nk):
            for a in range(3):
                new_pos[m, a] = kids[c, a]
                new_vel[m, a] = vel[i, a]  # inherited from the parent (seed 000 sec 2.3)
                new_omega[m, a] = omega[i, a]
            first_rem = r_rem >= r_full
            is_rem = (c == 0) if first_rem else (c == nk - 1)
            new_n[m] = rem if is_rem else k
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
                                ext = max(rn, di + ri, dj + rj)
                                if _conflicts(x, y, z, ext, ev, n_ev):
                                    counts[5] += 1
                                elif m >= cap:
                                    counts[4] += 1
                                else:
                                    s = _overlap_static(x, y, z, rn, pos, diam, i, j, lo, h, dims, head, nxt, rmax)
                                    s = max(s, _overlap_walls(x, y, z, rn, plane_p, plane_n, facets, nv))
                                    if s > tol:
                                        counts[4] += 1
                                    else:
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
