"""Binary collisions: momentum conservation, Coulomb sliding impulse, sliding-to-rolling at 5/7 v0."""

import math

import numpy as np
import pytest

from febed.dem import DEM, DEMParams, Walls
from febed.dem.contact import contact_time

D, RHO, KN = 1e-3, 2500.0, 1000.0
M = RHO * math.pi / 6 * D**3


def pair_dem(law, e, mu, integrator="rk2", rotation=True, stiffness=KN):
    p = DEMParams(contact_model=law, stiffness=stiffness, restitution_pp=e, friction_pp=mu, gravity=0.0,
                  integrator=integrator, rotation=rotation)  # fmt: skip
    return DEM(p)


def collide(dem, pos, vel, factor=50):
    dem.add_particles(np.asarray(pos, float), D, RHO, vel=np.asarray(vel, float))
    dt = contact_time(dem.params.stiffness, dem.params.restitution_pp, M / 2) / factor
    p0 = (dem.particles.mass[:, None] * dem.particles.vel).sum(axis=0)
    dem.advance(int(4 * factor), dt)
    return p0


@pytest.mark.parametrize("law", ["linear", "linear-history"])
@pytest.mark.parametrize("integrator", ["rk2", "verlet"])
def test_momentum_head_on_and_oblique(law, integrator):
    for vel in ([[0.1, 0, 0], [-0.05, 0, 0]], [[0.1, 0.07, -0.02], [-0.03, 0.0, 0.05]]):
        dem = pair_dem(law, 0.8, 0.3, integrator)
        p0 = collide(dem, [[0, 0, 0], [1.0001 * D, 0.2 * D, 0.1 * D]], vel)
        P = dem.particles
        p1 = (P.mass[:, None] * P.vel).sum(axis=0)
        assert np.linalg.norm(p1 - p0) <= 1e-12 * np.linalg.norm(p0)
        assert np.dot(P.vel[1] - P.vel[0], P.pos[1] - P.pos[0]) > 0  # they separated
        if vel[0][1] != 0:
            assert np.linalg.norm(P.omega) > 0  # friction made them spin


@pytest.mark.parametrize("law", ["linear", "linear-history"])
def test_sliding_impact_matches_coulomb_impulse(law):
    """Equal spheres, b at rest, normal along x: gross sliding throughout (vt > 7/2 mu (1 + e) vn).

    A stiff contact (short, so the normal hardly turns while the spheres slide) approximates the impulse theory.
    """
    e, mu, vn, vt = 0.9, 0.1, 0.1, 0.2
    dem = pair_dem(law, e, mu, stiffness=1e5)
    collide(dem, [[0, 0, 0], [D * (1 + 1e-9), 0, 0]], [[vn, vt, 0], [0, 0, 0]], factor=100)
    P = dem.particles
    jn = (1 + e) * (M / 2) * vn  # normal impulse of the restitution law
    jt = mu * jn
    r = D / 2
    inertia = 0.1 * M * D**2
    expect_vt = [vt - jt / M, jt / M]
    expect_w = -r * jt / inertia
    got_vn = P.vel[1, 0] - P.vel[0, 0]
    assert got_vn == pytest.approx(e * vn, rel=0.005)
    for k in range(2):
        assert P.vel[k, 1] == pytest.approx(expect_vt[k], rel=0.02)
        assert P.omega[k, 2] == pytest.approx(expect_w, rel=0.02)


@pytest.mark.parametrize("law", ["linear", "linear-history"])
def test_sliding_wall_impact_matches_coulomb_impulse(law):
    e, mu, vn, vt = 0.9, 0.1, 0.1, 0.2
    p = DEMParams(contact_model=law, stiffness=KN, restitution_pw=e, friction_pw=mu, gravity=0.0)
    dem = DEM(p, walls=Walls(planes=[((0, 0, 0), (0, 0, 1))]))
    dem.add_particles(np.array([[0, 0, D / 2]]), D, RHO, vel=np.array([[vt, 0, -vn]]))
    dt = contact_time(KN, e, M) / 100
    dem.advance(400, dt)
    P = dem.particles
    jt = mu * (1 + e) * M * vn
    assert P.vel[0, 2] == pytest.approx(e * vn, rel=0.005)
    assert P.vel[0, 0] == pytest.approx(vt - jt / M, rel=0.02)
    assert P.omega[0, 1] == pytest.approx((D / 2) * jt / (0.1 * M * D**2), rel=0.02)  # rolls forward: +y


@pytest.mark.parametrize("law", ["linear", "linear-history"])
@pytest.mark.parametrize("integrator", ["rk2", "verlet"])
def test_sliding_sphere_ends_rolling_at_five_sevenths(law, integrator):
    mu, v0, g = 0.3, 0.1, 9.81
    p = DEMParams(contact_model=law, stiffness=KN, restitution_pw=0.5, friction_pw=mu, gravity=g, integrator=integrator)
    dem = DEM(p, walls=Walls(planes=[((0, 0, 0), (0, 0, 1))]))
    dem.add_particles(np.array([[0, 0, D / 2 - M * g / KN]]), D, RHO, vel=np.array([[v0, 0, 0]]))
    t_slip = 2 * v0 / (7 * mu * g)
    dem.advance(int(2 * t_slip / dem.dt))
    vs = []
    for _ in range(200):
        dem.advance(5)
        vs.append(dem.particles.vel[0, 0])
    v_end = np.mean(vs)
    assert v_end == pytest.approx(5 / 7 * v0, rel=0.01)
    rolling = dem.particles.omega[0, 1] * D / 2
    assert rolling == pytest.approx(v_end, rel=0.01)
