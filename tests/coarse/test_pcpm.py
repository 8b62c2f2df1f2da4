"""PCPM particle-groups (seed 000 sec 2.3): d_cl by hand, no crushing where E_input <= 0, integer crush sizes,
and 10,000 random crush/merge events conserving the original count exactly and momentum to 1e-12."""

import math

import numpy as np
import pytest

from febed.coarse.pcpm import NO_CRUSH, GroupDynamics, crush_sizes, equivalent_diameter, u_mf_wen_yu
from febed.dem import DEM, DEMParams, Walls
from febed.dem.insertion import random_positions

DO, RHO = 1e-3, 2500.0


def _dcl(eps, v, f, u, e_cc=0.0, u_mf=0.3):
    out = np.empty(1)
    equivalent_diameter(np.array([eps]), np.array([u], float), np.array([v], float), np.array([f], float),
                        np.array([1e-6]), np.array([e_cc]), DO, RHO, 1.2, 9.81, u_mf, 0.45, 0.9997, out)  # fmt: skip
    return out[0]


def test_equivalent_diameter_by_hand():
    # eps = 0.8, |v| = 0.5 -> U_p = (1 - eps)|v| = 0.1 m/s; F . u / m = 2e-5 * 1 / 1e-6 = 20 W/kg (eq 37)
    # b = g (rho_p - rho_g)/rho_p = 9.81 * 2498.8 / 2500 = 9.8052912
    # U_mf + eps_mf U_p/(1 - eps_mf) = 0.3 + 0.045/0.55 = 0.381818...
    # (E_st)_mf = 9.8052912 * 0.381818... = 3.74383846 (eq 35)
    # K = 9.8052912 * 1e-3 * (0.1/0.0003 - 0.381818...) = 3.26468656 (eq 36)
    # d_cl = 3.26468656 / (20 - 3.74383846) = 0.200827640 m (eq 39)
    d = _dcl(0.8, (0.3, 0.4, 0.0), (0.0, 0.0, 2e-5), (0.0, 0.0, 1.0))
    assert d == pytest.approx(0.200827640, rel=1e-8)
    # with E_cc = 5 W/kg: 3.26468656 / (25 - 3.74383846) = 0.153587775 m
    d = _dcl(0.8, (0.3, 0.4, 0.0), (0.0, 0.0, 2e-5), (0.0, 0.0, 1.0), e_cc=5.0)
    assert d == pytest.approx(0.153587775, rel=1e-8)


def test_no_crushing_where_d_cl_not_positive():
    # E_input < 0: drag power 2 W/kg below (E_st)_mf = 3.74 W/kg
    assert _dcl(0.8, (0.3, 0.4, 0.0), (0.0, 0.0, 2e-6), (0.0, 0.0, 1.0)) == NO_CRUSH
    # K < 0: particles at rest (U_p = 0), even with a large E_input
    assert _dcl(0.8, (0.0, 0.0, 0.0), (0.0, 0.0, 2e-3), (0.0, 0.0, 1.0)) == NO_CRUSH
    # E_input = 0 exactly would be infinite
    assert _dcl(1.0, (0.3, 0.4, 0.0), (0.0, 0.0, 2e-5), (0.0, 0.0, 1.0)) == NO_CRUSH
    # a group with d_cl = NO_CRUSH is never crushed
    dem = DEM(DEMParams(gravity=0.0))
    dem.add_particles(np.zeros((1, 3)), DO * 2.0, RHO, n_orig=8)
    gd = GroupDynamics(DO, RHO, 1.2, 1.8e-5, 0.45)
    s = gd.apply(dem, np.array([NO_CRUSH]))
    assert s.crushed == 0 and dem.particles.n_owned == 1
    s = gd.apply(dem, np.array([-1.0]))
    assert s.crushed == 0 and dem.particles.n_owned == 1


def test_crush_sizes_integer_rule():
    # n = 8, d = 2 d_O, d_cl = d_O: floor(d^2/d_cl^2) = 4 children of 1 original, remainder 4 (eqs 41-42)
    assert crush_sizes(8, 2 * DO, DO, DO) == (1, 4, 4)
    # n = 27, d = 3 d_O, d_cl = 2 d_O: children of floor(2^3) = 8, floor(9/4) = 2 of them, remainder 11
    assert crush_sizes(27, 3 * DO, 2 * DO * (1 + 1e-15), DO) == (8, 2, 11)
    # a single original never crushes; nor does a group smaller than d_cl
    assert crush_sizes(1, DO, 0.5 * DO, DO)[1] == 0
    assert crush_sizes(8, 2 * DO, 3 * DO, DO)[1] == 0
    # very small d_cl: as many children of one original as eq 41 allows, remainder >= 1
    k, nf, rem = crush_sizes(27, 3 * DO, 0.1 * DO, DO)
    assert k == 1 and nf == 26 and rem == 1


def test_wen_yu_umf():
    # seed 000 Table 2 particles: Ar = 1.28 * 1148.72 * 9.81 * (1.5e-3)^3 / (1.7e-5)^2 = 168449.25,
    # Re_mf = sqrt(33.7^2 + 0.0408 Ar) - 33.7 = 55.78977, U_mf = Re_mf mu / (rho_g d) = 0.4939720 m/s
    assert u_mf_wen_yu(1.5e-3, 1150.0, 1.28, 1.7e-5) == pytest.approx(0.4939720, rel=1e-6)
    with pytest.raises(ValueError, match="eps_mf"):
        GroupDynamics(DO, RHO, 1.2, 1.8e-5, 1.5)


def _check_groups(P, rho):
    n = P.n_owned
    no = P.n_orig[:n]
    assert no.min() >= 1
    assert np.allclose(P.diameter[:n], DO * np.cbrt(no.astype(float)), rtol=1e-15, atol=0)
    assert np.allclose(P.mass[:n], rho * math.pi / 6 * DO**3 * no, rtol=1e-14, atol=0)


@pytest.mark.parametrize("dim", [3, 2])
def test_random_events_conserve_originals_and_momentum(dim):
    rng = np.random.default_rng(7)
    lo, hi = np.zeros(3), np.array([0.03, 0.03, 0.03]) if dim == 3 else np.array([0.06, 0.06, 0.0])
    dem = DEM(DEMParams(dim=dim, gravity=0.0, stiffness=800.0), walls=Walls.box(lo, hi, dim))
    count = 400 if dim == 3 else 300
    n0 = rng.integers(1, 9, count)
    pos = random_positions(count, lo, hi, 2.05 * DO, dim=dim, seed=1)
    vel = np.array([1.0, 0.5, 0.0]) + 0.3 * rng.normal(size=(count, 3))
    if dim == 2:
        vel[:, 2] = 0.0
    dem.add_particles(pos, DO * np.cbrt(n0), RHO, vel=vel, n_orig=n0)
    gd = GroupDynamics(DO, RHO, 1.2, 1.8e-5, 0.45, merge_tolerance=1e9, overlap_tolerance=0.3, max_group=27,
                       measure_energy=False, seed=3)  # fmt: skip
    P = dem.particles
    total = int(P.n_orig.sum())
    p0 = (P.mass[:, None] * P.vel).sum(axis=0)
    events = crushed = merged = 0
    target = 10_000
    for _ in range(1000):
        if events >= target:
            break
        n = P.n_owned
        big = P.n_orig[:n] > 1
        dcl = np.where(big & (rng.random(n) < 0.2), P.diameter[:n] * rng.uniform(0.3, 0.95, n), NO_CRUSH)
        s = gd.apply(dem, dcl)
        events += s.crushed + s.merged
        crushed += s.crushed
        merged += s.merged
        assert s.originals == total  # exact, after every pass
        # children are placed apart from each other; squeeze the cloud a little so that groups touch and merge
        c = P.pos[: P.n_owned].mean(axis=0)
        P.pos[: P.n_owned] = c + 0.995 * (P.pos[: P.n_owned] - c)
        dem.touch()
    assert events >= target
    _check_groups(P, RHO)
    p1 = (P.mass[:, None] * P.vel).sum(axis=0)
    rel = np.linalg.norm(p1 - p0) / np.linalg.norm(p0)
    print(f"{dim}D: {events} events ({crushed} crushes, {merged} merges), |dp|/|p| = {rel:.2e}")
    assert rel <= 1e-12
    assert crushed > 0.2 * events and merged > 0.2 * events
    if dim == 2:
        assert np.all(P.pos[:n, 2] == 0.0) and np.all(P.vel[:n, 2] == 0.0)


def test_update_on_a_bed_reports_energy():
    """update(): d_cl from the flow, contact power from the contacts, energy injected by the events."""
    rng = np.random.default_rng(2)
    lo, hi = np.zeros(3), np.array([0.02, 0.02, 0.02])
    dem = DEM(DEMParams(gravity=0.0, stiffness=800.0), walls=Walls.box(lo, hi))
    pos = random_positions(60, lo, hi, 2.05 * DO, seed=4)
    dem.add_particles(pos, 2 * DO, RHO, vel=np.array([0.0, 0.0, 5e-4]) + 1e-6 * rng.normal(size=(60, 3)), n_orig=8)
    gd = GroupDynamics(DO, RHO, 1.2, 1.8e-5, 0.45, u_mf=0.3, overlap_tolerance=0.1)
    n = dem.particles.n_owned
    eps = np.full(n, 0.7)
    u = np.tile([0.0, 0.0, 1.0], (n, 1))
    # U_p = 0.3 * 5e-4: K = b d_O (0.5 - 0.3001) ~ 2e-3, E_input ~ 3000 W/kg: d_cl ~ 0.65 um < 2 d_O
    f = np.tile([0.0, 0.0, 3000.0], (n, 1)) * dem.particles.mass[:n, None]
    d_cl = gd.equivalent_diameter(dem, eps, u, f)
    assert np.all(d_cl < 2 * DO)
    s = gd.update(dem, eps, u, f)
    assert s.crushed > 0 and s.originals == 480
    assert math.isfinite(s.energy_injected) and s.energy_injected > -1e-12
    _check_groups(dem.particles, RHO)


def _max_rel_overlap(x, r, rows):
    dist = np.linalg.norm(x[rows][:, None] - x[None], axis=2)
    dist[np.arange(rows.size), rows] = np.inf
    return float(((r[rows][:, None] + r[None] - dist) / (2 * np.minimum(r[rows][:, None], r[None]))).max())


@pytest.mark.parametrize("tol", [0.0, 0.05])
def test_children_and_merged_groups_respect_the_overlap_tolerance(tol):
    lo, hi = np.zeros(3), np.full(3, 0.012)
    dem = DEM(DEMParams(gravity=0.0), walls=Walls.box(lo, hi))
    pos = random_positions(60, lo, hi, 2.2 * DO, seed=5)
    rng = np.random.default_rng(0)
    dem.add_particles(pos, DO * 2.0, RHO, vel=np.array([0.3, 0.0, 0.0]) + 1e-3 * rng.normal(size=(60, 3)), n_orig=8)
    P = dem.particles
    old = set(P.gid.tolist())
    gd = GroupDynamics(DO, RHO, 1.2, 1.8e-5, 0.45, overlap_tolerance=tol, merge_tolerance=1.0, seed=1)
    s = gd.apply(dem, np.where(np.arange(60) % 2 == 0, 1.3 * DO, NO_CRUSH))
    assert s.crushed > 0
    n = P.n_owned
    new = np.array([k for k in range(n) if P.gid[k] not in old])
    assert _max_rel_overlap(P.pos[:n], 0.5 * P.diameter[:n], new) <= tol + 1e-12
    assert np.all(dem.walls.distance(P.pos[new]) >= 0.5 * P.diameter[new] * (1 - 2 * tol) - 1e-15)


def test_interval_stats_and_restart_state():
    def bed():
        dem = DEM(DEMParams(gravity=0.0))
        pos = np.array([[0.0, 0, 0], [0.01, 0, 0], [0.02, 0, 0]])
        dem.add_particles(pos, 2 * DO, RHO, vel=np.tile([0.0, 0.0, 5e-4], (3, 1)), n_orig=8)
        return dem

    args = (np.full(3, 0.7), np.tile([0.0, 0.0, 1.0], (3, 1)))
    gd = GroupDynamics(DO, RHO, 1.2, 1.8e-5, 0.45, u_mf=0.3, contact_power=False, seed=5)
    dem = bed()
    f = np.tile([0.0, 0.0, 3000.0], (3, 1)) * dem.particles.mass[:3, None]
    state = gd.state_dict()
    s1 = gd.update(dem, *args, f)
    iv = gd.interval_stats()
    assert iv.crushed == s1.crushed == 3 and gd.interval_stats().crushed == 0 and gd.total.crushed == 3
    # restart: the same state gives the same children
    gd2 = GroupDynamics(DO, RHO, 1.2, 1.8e-5, 0.45, u_mf=0.3, contact_power=False, seed=99)
    gd2.load_state_dict(state)
    dem2 = bed()
    gd2.update(dem2, *args, f)
    assert np.array_equal(dem.particles.pos, dem2.particles.pos)
