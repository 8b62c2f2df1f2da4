"""The PCPM criteria kernels against a plain-Python reference on random groups.

d_cl (seed 000 eqs 32-39) to 1e-12 with "no crushing" at the same groups; the crush sizes (eqs 40-42); and the
decisions of `GroupDynamics.apply` (which groups crush into which children, which touching pairs merge: eq 44,
`max_group`, merged diameter not above either d_cl) on isolated groups and pairs, where no overlap or conflict
can defer an event.
"""

import math
from collections import Counter

import numpy as np

from febed.coarse.pcpm import NO_CRUSH, GroupDynamics, crush_sizes, equivalent_diameter
from febed.dem import DEM, DEMParams

DO, RHO, RHO_G, G, U_MF, EPS_MF, EPS_MAX = 1.5e-3, 1150.0, 1.28, 9.81, 0.494, 0.45, 0.9997


def d_cl_reference(eps, u, v, f, m, e_cc):
    """Seed 000 eqs 32-39 for one group, written out in plain Python (E_st = F . u / m, eq 37 per unit mass)."""
    if not 0.0 < eps < 1.0:
        return math.inf
    b = G * (RHO - RHO_G) / RHO
    up = (1.0 - eps) * math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
    e_st = (f[0] * u[0] + f[1] * u[1] + f[2] * u[2]) / m
    mf = U_MF + EPS_MF * up / (1.0 - EPS_MF)
    k = b * DO * (up / (1.0 - EPS_MAX) - mf)
    e_in = e_st + e_cc - b * mf
    if k > 0.0 and e_in > 0.0 and math.isfinite(k / e_in):
        return k / e_in
    return math.inf


def crush_reference(n, d, d_cl):
    """(originals per full child, full children, remainder) of eqs 40-42, or None if the group does not crush."""
    if n < 2 or not (0.0 < d_cl < d):
        return None
    k = max(1, int(math.floor((d_cl / DO) ** 3 * (1.0 + 1e-12))))
    n_full = min(math.floor(min((d / d_cl) ** 2, 1e18)), (n - 1) // k)
    return (k, n_full, n - n_full * k) if n_full >= 1 else None


def test_d_cl_kernel_matches_the_reference():
    rng = np.random.default_rng(28)
    n = 4000
    eps = rng.uniform(0.3, 1.0, n)
    eps[::50] = rng.choice([0.0, 1.0, -0.1, 1.2], eps[::50].size)  # outside (0, 1): no crushing
    u = rng.normal(0.0, 1.5, (n, 3))
    v = rng.normal(0.0, 0.5, (n, 3))
    n_orig = rng.integers(1, 28, n)
    m = RHO * math.pi / 6 * DO**3 * n_orig
    f = m[:, None] * rng.normal(0.0, 30.0, (n, 3))  # drag per unit mass of tens of W/kg per m/s
    e_cc = np.where(rng.random(n) < 0.3, rng.exponential(20.0, n), 0.0)
    out = np.empty(n)
    equivalent_diameter(eps, u, v, f, m, e_cc, DO, RHO, RHO_G, G, U_MF, EPS_MF, EPS_MAX, out)
    ref = np.array([d_cl_reference(eps[p], u[p], v[p], f[p], m[p], e_cc[p]) for p in range(n)])
    crush = np.isfinite(ref)
    assert np.array_equal(np.isfinite(out), crush) and np.all(out[~crush] == NO_CRUSH)
    assert 0.2 * n < crush.sum() < 0.9 * n  # both outcomes are exercised
    assert np.allclose(out[crush], ref[crush], rtol=1e-12, atol=0.0)
    for p in range(0, n, 7):  # crush sizes of these groups at their d_cl
        d = DO * n_orig[p] ** (1 / 3)
        k, n_full, rem = crush_sizes(int(n_orig[p]), d, out[p], DO)
        want = crush_reference(int(n_orig[p]), d, ref[p])
        assert (k, n_full, rem) == (want if want is not None else (0, 0, int(n_orig[p])))


def test_event_decisions_match_the_reference():
    rng = np.random.default_rng(5)
    sites = [(x, y, z) for x in range(6) for y in range(6) for z in range(6)]
    spacing = 12 * DO  # far apart: no event is deferred for overlap or conflict
    pos, n_orig, vel, d_cl, site_of = [], [], [], [], []
    expect = {}  # site -> Counter of the n_orig found there after the events
    for s, c in enumerate(sites):
        x0 = np.array(c, float) * spacing
        if s % 2 == 0:  # a single group: crushes at d_cl, or not
            n = int(rng.integers(1, 9))
            d = DO * n ** (1 / 3)
            dcl = d * rng.uniform(0.3, 1.4)
            pos.append(x0)
            n_orig.append(n)
            vel.append(rng.normal(0, 0.3, 3))
            d_cl.append(dcl)
            site_of.append(s)
            cr = crush_reference(n, d, dcl)
            expect[s] = Counter([n]) if cr is None else Counter({cr[0]: cr[1]}) + Counter([cr[2]])
        else:  # two touching groups: merge or not (eq 44, max_group, merged diameter against both d_cl)
            ni, nj = (int(a) for a in rng.integers(1, 16, 2))
            ri, rj = 0.5 * DO * ni ** (1 / 3), 0.5 * DO * nj ** (1 / 3)
            e = rng.normal(size=3)
            e /= np.linalg.norm(e)
            xi, xj = x0, x0 + e * (ri + rj) * rng.uniform(0.99, 1.01)
            vi = rng.normal(0, 0.3, 3)
            vj = vi + rng.normal(size=3) * np.linalg.norm(vi) * rng.uniform(0.0, 0.012)
            dn = DO * (ni + nj) ** (1 / 3)
            dci = max(2 * ri, dn * rng.uniform(0.85, 1.2))  # never below the group's own diameter: no crush
            dcj = max(2 * rj, dn * rng.uniform(0.85, 1.2))
            pos += [xi, xj]
            n_orig += [ni, nj]
            vel += [vi, vj]
            d_cl += [dci, dcj]
            site_of += [s, s]
            dist = math.sqrt(sum((b - a) ** 2 for a, b in zip(xi, xj, strict=True)))
            dv = math.sqrt(sum((a - b) ** 2 for a, b in zip(vi, vj, strict=True)))
            vmax = max(math.sqrt(sum(a * a for a in vi)), math.sqrt(sum(a * a for a in vj)))
            merge = dist < ri + rj and dv < 0.01 * vmax and ni + nj <= 27 and dn <= min(dci, dcj)
            expect[s] = Counter([ni + nj]) if merge else Counter([ni, nj])
    n_orig = np.array(n_orig)
    dem = DEM(DEMParams(gravity=0.0, stiffness=800.0))
    dem.add_particles(np.array(pos), DO * np.cbrt(n_orig), RHO, vel=np.array(vel), n_orig=n_orig)
    gd = GroupDynamics(DO, RHO, RHO_G, 1.7e-5, EPS_MF, overlap_tolerance=0.3, max_group=27, merge_tolerance=0.01,
                       measure_energy=False, seed=2)  # fmt: skip
    s = gd.apply(dem, np.array(d_cl))
    assert s.crush_deferred == 0 and s.merge_deferred == 0 and s.conflicts == 0
    P = dem.particles
    n = P.n_owned
    centres = np.array(sites, float) * spacing
    found = {k: Counter() for k in expect}
    nearest = np.argmin(np.linalg.norm(P.pos[:n, None] - centres[None], axis=2), axis=1)
    for k, no in zip(nearest.tolist(), P.n_orig[:n].tolist(), strict=True):
        found[k][no] += 1
    assert found == expect
    crushes = sum(1 for k, c in expect.items() if k % 2 == 0 and sum(c.values()) > 1)
    merges = sum(1 for k, c in expect.items() if k % 2 == 1 and sum(c.values()) == 1)
    assert s.crushed == crushes and s.merged == merges
    assert crushes >= 20 and merges >= 10 and len(sites) // 2 - merges >= 10  # every outcome is exercised
