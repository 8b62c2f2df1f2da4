"""The contact force loop: gravity + particle-particle + particle-wall forces and torques, written once.

The contact law enters through the type of its parameters (`pp` for particle pairs, `pw` for walls, see
`febed.dem.contact`), so this loop is compiled once per law. Pair forces are accumulated on both
partners of the half list (Newton's third law holds to round-off: the same numbers are added and
subtracted). Rows >= n_owned are ghosts: they receive forces that are ignored.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from febed.dem.contact import FAST, pair_force
from febed.dem.walls import MAX_WALL_CONTACTS, accept_contacts, wall_point


@njit(cache=True, fastmath=FAST, error_model="numpy")
def compute_forces(bodies, vel, omega, lists, hist_out, whist_out, walls, model, dt_eval, dt_store):
    """Set force (N) = m g + contact forces, torque (N m) = contact torques of the rows of `bodies` (`Bodies`).

    vel, omega: the velocities the contact forces see (the rows' own, or Verlet's predicted ones). The
    elongations are read from `lists` (`Lists`) and written to hist_out, whist_out (the same arrays, or
    scratch copies); `walls` is a `febed.dem.walls.WallGeometry`, `model` a `Model`. dt_eval (s): the step
    the elongation is advanced by; dt_store (s): the step of the regularised Coulomb cap.
    Returns the largest overlap relative to the smaller diameter of its pair (a wall: the particle's).
    """
    pos = bodies.pos
    diameter = bodies.diameter
    mass = bodies.mass
    inertia = bodies.inertia
    force = bodies.force
    torque = bodies.torque
    n_owned = bodies.n_owned
    n = bodies.n
    start = lists.start
    nbr = lists.nbr
    hist_in = lists.hist
    wstart = lists.wstart
    wid = lists.wid
    whist_in = lists.whist
    pp = model.pp
    pw = model.pw
    rotation = model.rotation
    gvec = model.gvec
    rot = 1.0 if rotation else 0.0
    invm = np.empty(n)  # 1/m, r^2/I and 1/d once per particle instead of once per pair
    kr = np.empty(n)
    invd = np.empty(n)
    for i in range(n):
        invm[i] = 1.0 / mass[i]
        invd[i] = 1.0 / diameter[i]
        r = 0.5 * diameter[i]
        kr[i] = r * r / inertia[i] * rot
        for a in range(3):
            force[i, a] = mass[i] * gvec[a] if i < n_owned else 0.0
            torque[i, a] = 0.0
    worst = 0.0
    # ---------------------------------------------------------------- particle-particle (seed 001 eqs 6-15)
    for i in range(n_owned):
        xi = pos[i, 0]
        yi = pos[i, 1]
        zi = pos[i, 2]
        ri = 0.5 * diameter[i]
        imi = invm[i]
        ki = kr[i]
        fxi = 0.0
        fyi = 0.0
        fzi = 0.0
        txi = 0.0
        tyi = 0.0
        tzi = 0.0
        for k in range(start[i], start[i + 1]):
            j = nbr[k]
            rj = 0.5 * diameter[j]
            dx = pos[j, 0] - xi
            dy = pos[j, 1] - yi
            dz = pos[j, 2] - zi
            d2 = dx * dx + dy * dy + dz * dz
            rs = ri + rj
            if d2 >= rs * rs or d2 == 0.0:
                # no contact: no elongation (written only if there is one: most separated pairs stay at zero)
                if hist_out[k, 0] != 0.0 or hist_out[k, 1] != 0.0 or hist_out[k, 2] != 0.0:
                    hist_out[k, 0] = 0.0
                    hist_out[k, 1] = 0.0
                    hist_out[k, 2] = 0.0
                continue
            dist = math.sqrt(d2)
            delta = rs - dist  # seed 001 eq 10
            worst = max(worst, delta * max(invd[i], invd[j]))  # relative to the smaller sphere
            inv = 1.0 / dist
            nx = dx * inv  # seed 001 eq 12: from i towards j
            ny = dy * inv
            nz = dz * inv
            # velocity of i's surface relative to j's at the contact point (seed 000 eq 9)
            wx = ri * omega[i, 0] + rj * omega[j, 0]
            wy = ri * omega[i, 1] + rj * omega[j, 1]
            wz = ri * omega[i, 2] + rj * omega[j, 2]
            vx = vel[i, 0] - vel[j, 0] + (wy * nz - wz * ny)
            vy = vel[i, 1] - vel[j, 1] + (wz * nx - wx * nz)
            vz = vel[i, 2] - vel[j, 2] + (wx * ny - wy * nx)
            im = imi + invm[j]
            m_eff = 1.0 / im  # seed 001 eq 11
            mt_eff = 1.0 / (im + ki + kr[j])
            fx, fy, fz, hx, hy, hz = pair_force(
                pp, delta, nx, ny, nz, vx, vy, vz, m_eff, mt_eff, hist_in[k, 0], hist_in[k, 1], hist_in[k, 2],
                dt_eval, dt_store,
            )  # fmt: skip
            hist_out[k, 0] = hx
            hist_out[k, 1] = hy
            hist_out[k, 2] = hz
            fxi += fx
            fyi += fy
            fzi += fz
            force[j, 0] -= fx
            force[j, 1] -= fy
            force[j, 2] -= fz
            if rotation:
                fn = fx * nx + fy * ny + fz * nz
                tx = fx - fn * nx
                ty = fy - fn * ny
                tz = fz - fn * nz
                # torque on i: (r_i n) x f_t ; on j: (-r_j n) x (-f_t)
                cx = ny * tz - nz * ty
                cy = nz * tx - nx * tz
                cz = nx * ty - ny * tx
                txi += ri * cx
                tyi += ri * cy
                tzi += ri * cz
                torque[j, 0] += rj * cx
                torque[j, 1] += rj * cy
                torque[j, 2] += rj * cz
        force[i, 0] += fxi
        force[i, 1] += fyi
        force[i, 2] += fzi
        torque[i, 0] += txi
        torque[i, 1] += tyi
        torque[i, 2] += tzi
    # ---------------------------------------------------------------- particle-wall (infinite mass, zero radius)
    if wid.size == 0:
        return worst
    kind = np.empty(MAX_WALL_CONTACTS, dtype=np.int64)
    qs = np.empty((MAX_WALL_CONTACTS, 3))
    ms = np.empty((MAX_WALL_CONTACTS, 3))
    dl = np.empty(MAX_WALL_CONTACTS)
    kk = np.empty(MAX_WALL_CONTACTS, dtype=np.int64)
    acc = np.empty(MAX_WALL_CONTACTS, dtype=np.bool_)
    order = np.empty(MAX_WALL_CONTACTS, dtype=np.int64)
    plane_n = walls.plane_n
    npl = plane_n.shape[0]
    for i in range(n_owned):
        a0 = wstart[i]
        a1 = wstart[i + 1]
        if a0 == a1:
            continue
        xi = pos[i, 0]
        yi = pos[i, 1]
        zi = pos[i, 2]
        ri = 0.5 * diameter[i]
        cnt = 0
        for k in range(a0, a1):
            w = wid[k]
            qx, qy, qz, kd, sd = wall_point(xi, yi, zi, w, walls)
            if w < npl:
                dist = sd
                mx = plane_n[w, 0]
                my = plane_n[w, 1]
                mz = plane_n[w, 2]
            else:
                mx = xi - qx
                my = yi - qy
                mz = zi - qz
                dist = math.sqrt(mx * mx + my * my + mz * mz)
                if dist == 0.0:
                    continue
                mx /= dist
                my /= dist
                mz /= dist
            if dist >= ri or cnt == MAX_WALL_CONTACTS:
                continue
            kind[cnt] = kd
            qs[cnt, 0] = qx
            qs[cnt, 1] = qy
            qs[cnt, 2] = qz
            ms[cnt, 0] = mx
            ms[cnt, 1] = my
            ms[cnt, 2] = mz
            dl[cnt] = ri - dist
            kk[cnt] = k
            cnt += 1
        for k in range(a0, a1):  # walls not in accepted contact lose their history
            keep = False
            for c in range(cnt):
                if kk[c] == k:
                    keep = True
            if not keep:
                whist_out[k, 0] = 0.0
                whist_out[k, 1] = 0.0
                whist_out[k, 2] = 0.0
        if cnt == 0:
            continue
        accept_contacts(kind, qs, ms, dl, cnt, acc, order, 1e-9 * ri)
        mi = mass[i]
        mt_eff = 1.0 / (1.0 / mi + ri * ri / inertia[i] * rot)
        for c in range(cnt):
            k = kk[c]
            if not acc[c]:
                whist_out[k, 0] = 0.0
                whist_out[k, 1] = 0.0
                whist_out[k, 2] = 0.0
                continue
            nx = -ms[c, 0]  # from the particle towards the wall
            ny = -ms[c, 1]
            nz = -ms[c, 2]
            delta = dl[c]
            worst = max(worst, delta / (2.0 * ri))
            vx = vel[i, 0] + ri * (omega[i, 1] * nz - omega[i, 2] * ny)
            vy = vel[i, 1] + ri * (omega[i, 2] * nx - omega[i, 0] * nz)
            vz = vel[i, 2] + ri * (omega[i, 0] * ny - omega[i, 1] * nx)
            fx, fy, fz, hx, hy, hz = pair_force(
                pw, delta, nx, ny, nz, vx, vy, vz, mi, mt_eff, whist_in[k, 0], whist_in[k, 1], whist_in[k, 2],
                dt_eval, dt_store,
            )  # fmt: skip
            whist_out[k, 0] = hx
            whist_out[k, 1] = hy
            whist_out[k, 2] = hz
            force[i, 0] += fx
            force[i, 1] += fy
            force[i, 2] += fz
            if rotation:
                fn = fx * nx + fy * ny + fz * nz
                tx = fx - fn * nx
                ty = fy - fn * ny
                tz = fz - fn * nz
                torque[i, 0] += ri * (ny * tz - nz * ty)
                torque[i, 1] += ri * (nz * tx - nx * tz)
                torque[i, 2] += ri * (nx * ty - ny * tx)
    return worst


@njit(cache=True, fastmath=FAST, error_model="numpy")
def contact_power(bodies, lists, pp, out):
    """Contact power per unit mass E_cc,i = Σ_j F_cont,ij · (v_i - v_j) / m_i (W/kg) of seed 000 eq 38.

    Uses the pair list of the current rows (`Lists`) and the particle-pair law `pp` (walls are not
    particle-groups and do not count); rows [0, n_owned) of `bodies` are filled in `out`, ghosts add to their
    owners elsewhere.
    """
    pos = bodies.pos
    vel = bodies.vel
    omega = bodies.omega
    diameter = bodies.diameter
    mass = bodies.mass
    start = lists.start
    nbr = lists.nbr
    hist = lists.hist
    for i in range(out.shape[0]):
        out[i] = 0.0
    for i in range(bodies.n_owned):
        ri = 0.5 * diameter[i]
        for k in range(start[i], start[i + 1]):
            j = nbr[k]
            rj = 0.5 * diameter[j]
            dx = pos[j, 0] - pos[i, 0]
            dy = pos[j, 1] - pos[i, 1]
            dz = pos[j, 2] - pos[i, 2]
            d2 = dx * dx + dy * dy + dz * dz
            rs = ri + rj
            if d2 >= rs * rs or d2 == 0.0:
                continue
            dist = math.sqrt(d2)
            inv = 1.0 / dist
            nx = dx * inv
            ny = dy * inv
            nz = dz * inv
            wx = ri * omega[i, 0] + rj * omega[j, 0]
            wy = ri * omega[i, 1] + rj * omega[j, 1]
            wz = ri * omega[i, 2] + rj * omega[j, 2]
            rvx = vel[i, 0] - vel[j, 0]
            rvy = vel[i, 1] - vel[j, 1]
            rvz = vel[i, 2] - vel[j, 2]
            m_eff = 1.0 / (1.0 / mass[i] + 1.0 / mass[j])
            fx, fy, fz, _, _, _ = pair_force(
                pp, rs - dist, nx, ny, nz, rvx + (wy * nz - wz * ny), rvy + (wz * nx - wx * nz),
                rvz + (wx * ny - wy * nx), m_eff, m_eff, hist[k, 0], hist[k, 1], hist[k, 2], 0.0, 0.0,
            )  # fmt: skip
            p = fx * rvx + fy * rvy + fz * rvz  # the same on j: (-F) . (v_j - v_i)
            out[i] += p / mass[i]
            if j < out.shape[0]:
                out[j] += p / mass[j]
