"""Traditional coarse grain (seed 000 eqs 17-25): l = 1 is plain DEM bit for bit, contact forces are l^3 times
the originals', contact time follows the analytic sqrt(l) law, parcels get n_orig times an original's drag."""

import math

import numpy as np
import pytest

from febed.coarse.tm import check_ratio, tm_contact_params, tm_contact_time, tm_dem_params, tm_parcels
from febed.coupling.drag import AtParticles, GasForces, NodalGas, drag_forces, gas_forces_kernel, get_drag_law
from febed.dem import DEM, DEMParams
from febed.dem.contact import linear, linear_history

D, RHO, KN = 1e-3, 2500.0, 1000.0
M = RHO * math.pi / 6 * D**3


def _cloud(n=30, seed=3):
    rng = np.random.default_rng(seed)
    g = np.array([[i, j, k] for i in range(4) for j in range(4) for k in range(2)], float)[:n]
    pos = g * 1.05 * D + rng.uniform(-0.02, 0.02, g.shape) * D
    vel = rng.normal(0, 0.05, g.shape)
    return pos, vel


def _run(params, d, n_orig, steps=400):
    dem = DEM(params)
    pos, vel = _cloud()
    dem.add_particles(pos, d, RHO, vel=vel, n_orig=n_orig)
    P = dem.particles
    law = get_drag_law("schiller-naumann")
    for _ in range(4):
        n = P.n_owned
        d_orig = P.diameter[:n] / np.cbrt(P.n_orig[:n].astype(float))
        u = np.zeros((n, 3))
        u[:, 2] = 0.3
        _, f = drag_forces(law, np.full(n, 0.9), u, P.vel[:n], d_orig, P.n_orig[:n], 1.2, 1.8e-5)
        dem.advance(steps // 4, dem.dt, f)
    order = np.argsort(P.gid)
    return P.pos[order].copy(), P.vel[order].copy(), P.omega[order].copy(), dem.dt


@pytest.mark.parametrize("law", ["linear", "linear-history"])
def test_ratio_one_is_plain_dem_bit_for_bit(law):
    base = DEMParams(contact_model=law, stiffness=KN, restitution_pp=0.8, friction_pp=0.3, gravity=9.81)
    ref = _run(base, D, 1)
    d, n = tm_parcels(D, 1.0)
    assert (d, n) == (D, 1)
    got = _run(tm_dem_params(base, 1.0), d, n)
    for a, b in zip(ref[:3], got[:3], strict=True):
        assert np.array_equal(a, b)
        assert np.abs(a).max() > 0
    assert ref[3] == got[3]


@pytest.mark.parametrize("ratio", [2.0, 3.0, 2.0 ** (1 / 3)])
def test_parcel_contact_force_is_l3_times_original(ratio):
    """Eq 24-25: at overlap l delta_O and the same relative velocity, the parcel force is l^3 F_O."""
    base = DEMParams(stiffness=KN, restitution_pp=0.7, friction_pp=0.3)
    dem = DEM(base)
    m_o = M / 2
    m_cg = ratio**3 * M / 2
    for p, func in ((dem.pp, linear_history), (DEM(DEMParams(contact_model="linear", stiffness=KN)).pp, linear)):
        q = tm_contact_params(p, ratio)
        delta, h = 2e-6, (1e-7, -2e-7, 0.0)
        n = (0.0, 0.6, 0.8)
        v = (0.01, -0.03, 0.02)
        fo = np.array(func(p, delta, *n, *v, m_o, m_o * 2 / 7, *h, 1e-6, 1e-6)[:3])
        hc = tuple(ratio * x for x in h)  # tangential elongation scales like the overlap
        fc = np.array(func(q, ratio * delta, *n, *v, m_cg, m_cg * 2 / 7, *hc, 1e-6 * ratio, 1e-6 * ratio)[:3])
        assert np.allclose(fc, ratio**3 * fo, rtol=1e-12, atol=0)


def _contact_duration(params, d, rho, dt_frac=1 / 2000):
    """Head-on collision of two equal particles: time (s) during which they overlap."""
    dem = DEM(params)
    v0 = 0.05
    dem.add_particles(np.array([[0, 0, 0], [d * 1.0000001, 0, 0]]), d, rho, vel=np.array([[v0, 0, 0], [-v0, 0, 0]]))
    P = dem.particles
    m = P.mass[0]
    w0 = math.sqrt(dem.pp.stiffness / (m / 2))
    dt = math.pi / w0 * dt_frac
    t, t_in, t_out = 0.0, None, None
    for _ in range(int(4 / dt_frac)):
        dem.advance(1, dt)
        t += dt
        gap = abs(P.pos[1, 0] - P.pos[0, 0]) - d
        if gap < 0 and t_in is None:
            t_in = t
        if gap >= 0 and t_in is not None:
            t_out = t
            break
    assert t_out is not None
    vn = P.vel[1, 0] - P.vel[0, 0]
    return t_out - t_in, vn / (2 * v0), m


@pytest.mark.parametrize("e", [1.0, 0.8])
def test_contact_time_scales_as_analytic(e):
    base = DEMParams(
        contact_model="linear", stiffness=KN, restitution_pp=e, friction_pp=0.0, gravity=0.0, rotation=False
    )
    t1, e1, m1 = _contact_duration(base, D, RHO)
    for ratio in (2.0, 3.0):
        tl, el, _ = _contact_duration(tm_dem_params(base, ratio), ratio * D, RHO)
        exact = tm_contact_time(KN, e, m1 / 2, ratio)
        assert abs(tl - exact) <= 2e-3 * exact  # resolution of the measurement: T_C / 2000 steps
        if e == 1.0:
            assert abs(tl / t1 - math.sqrt(ratio)) <= 2e-3 * math.sqrt(ratio)  # the sqrt(l) law
            assert abs(el - 1.0) < 1e-3
        else:
            assert el < e1 - 0.01  # the literal eq 24 dashpot lowers the parcel restitution
    # the "restitution" variant keeps e and gives sqrt(l) T_C for e < 1 too
    tr, er, _ = _contact_duration(tm_dem_params(base, 2.0, damping="restitution"), 2 * D, RHO)
    assert abs(tr - tm_contact_time(KN, e, m1 / 2, 2.0, "restitution")) <= 2e-3 * tr
    assert abs(tr / t1 - math.sqrt(2.0)) <= 3e-3 * math.sqrt(2)
    assert abs(er - e1) < 2e-3


def test_bad_ratio():
    for bad in (0.5, 1.5, float("nan")):
        with pytest.raises(ValueError, match="coarse_grain.ratio"):
            check_ratio(bad)
    with pytest.raises(ValueError, match="overdamped"):
        tm_dem_params(DEMParams(restitution_pp=0.1), 3.0)


LAWS = ["stokes", "schiller-naumann", "wen-yu", "ergun", "gidaspow-blend", "emms"]


@pytest.mark.parametrize("name", LAWS)
def test_parcel_drag_is_n_orig_times_original(name):
    """The Coupler path: d_orig = d / cbrt(n_orig), K = n_orig law(eps, |u - v|, d_orig) (seed 000 eq 21)."""
    law = get_drag_law(name)
    rng = np.random.default_rng(1)
    ratios = np.array([1.0, 2.0, 3.0, 2.0 ** (1 / 3), 4.0])
    n = ratios.size
    d = np.array([tm_parcels(5e-4, r)[0] for r in ratios])
    n_orig = np.array([tm_parcels(5e-4, r)[1] for r in ratios])
    d_orig = d / np.cbrt(n_orig.astype(float))  # what febed.solver.CoupledSolver._originals passes
    assert np.allclose(d_orig, 5e-4, rtol=1e-15, atol=0)
    eps = rng.uniform(0.45, 0.999, n)
    u = rng.normal(0, 1, (n, 3))
    v = rng.normal(0, 1, (n, 3))
    K, F = drag_forces(law, eps, u, v, d_orig, n_orig, 1.2, 1.8e-5)
    for p in range(n):
        slip = np.linalg.norm(u[p] - v[p])
        k1 = law(eps[p], slip, 5e-4, 1.2, 1.8e-5)  # one original at the parcel velocity
        assert K[p] == pytest.approx(n_orig[p] * k1, rel=1e-14)
        assert np.allclose(F[p], n_orig[p] * k1 * (u[p] - v[p]), rtol=1e-13)
    # the fused sub-step kernel: one triangle, each particle at its centroid, constant nodal fields per particle
    Fp, ep = np.empty((1, 3)), np.empty(1)
    for p in range(n):
        un = np.tile(u[p, :2], (3, 1))
        w = np.full((1, 3), 1 / 3)
        vv = v[p : p + 1].copy()
        vv[0, 2] = 0.0
        at = AtParticles(np.arange(3).reshape(1, 3), np.zeros(1, np.int32), w, vv, d_orig[p : p + 1], n_orig[p : p + 1])
        k = np.empty(1)
        f = np.empty((1, 3))
        gas = NodalGas(un, np.full(3, eps[p]), np.zeros((3, 2)), 1.2, 1.8e-5, True)
        gas_forces_kernel(law, at, gas, GasForces.of(k, f, Fp, ep))
        slip = np.linalg.norm(np.r_[u[p, :2], 0.0] - vv[0])
        assert k[0] == pytest.approx(n_orig[p] * law(eps[p], slip, 5e-4, 1.2, 1.8e-5), rel=1e-12)
        assert np.allclose(f[0], k[0] * (np.r_[u[p, :2], 0.0] - vv[0]), rtol=1e-13)


def test_group_pair_ratio_cube_root():
    """The groups' law takes l = (m_eff/m_ref)^(1/3) from a table for whole numbers: equal to pow to rounding."""
    from febed.dem.contact import _MAX_TABLED, _pair_ratio

    rng = np.random.default_rng(3)
    for n in range(1, _MAX_TABLED + 2):  # whole numbers, their rounding neighbours, and values between them
        for r in (n, n * (1 + 2e-16), n * (1 - 4e-16), n * (1 + 5e-10), n * (1 + 2e-9), n + 0.37):
            assert _pair_ratio(r) == pytest.approx(r ** (1 / 3), rel=1e-15, abs=0)
    for r in np.r_[rng.uniform(0.01, 1.0, 500), rng.uniform(1.0, 200.0, 500)]:  # pieces and large pairs
        assert _pair_ratio(r) == pytest.approx(r ** (1 / 3), rel=1e-15, abs=0)


def test_group_contacts_scale_per_pair():
    """PCPM groups: the per-pair law reproduces the uniform-ratio TM parameters and contact time."""
    from febed.coarse.tm import use_group_contacts
    from febed.dem.contact import GroupParams, linear_groups

    base = DEMParams(
        contact_model="linear", stiffness=KN, restitution_pp=0.8, friction_pp=0.3, gravity=0.0, rotation=False
    )
    p = DEM(base).pp
    for ratio in (1.0, 2.0, 3.0):
        m_eff = ratio**3 * M / 2
        q = tm_contact_params(p, ratio)
        g = GroupParams(p.stiffness, p.ce, p.friction, M / 2)
        args = (2e-6 * ratio, 0.0, 0.6, 0.8, 0.01, -0.03, 0.02, m_eff, m_eff * 2 / 7, 0.0, 0.0, 0.0, 1e-6, 1e-6)
        assert np.allclose(linear_groups(g, *args)[:3], linear(q, *args)[:3], rtol=1e-12, atol=0)
    # two groups of 8 originals colliding in a DEM: contact time of l = 2
    dem = DEM(base)
    use_group_contacts(dem, D, RHO)
    v0 = 0.05
    dem.add_particles(np.array([[0, 0, 0], [2 * D * 1.0000001, 0, 0]]), 2 * D, RHO,
                      vel=np.array([[v0, 0, 0], [-v0, 0, 0]]), n_orig=8)  # fmt: skip
    P = dem.particles
    exact = tm_contact_time(KN, 0.8, M / 2, 2.0)
    dt = exact / 2000
    t, t_in = 0.0, None
    for _ in range(8000):
        dem.advance(1, dt)
        t += dt
        gap = abs(P.pos[1, 0] - P.pos[0, 0]) - 2 * D
        if gap < 0 and t_in is None:
            t_in = t
        if gap >= 0 and t_in is not None:
            break
    assert abs((t - t_in) - exact) <= 2e-3 * exact
