"""Contact-law details: static friction of the history law, sliding on an incline, stiffness from E and sigma,
external forces, history kept across insertion, input errors."""

import math

import numpy as np
import pytest

from febed.dem import DEM, DEMParams, Walls
from febed.dem.contact import contact_time, get_law, stiffness_from_material
from febed.schema import CONTACT_LAWS, INTEGRATORS

D, RHO, KN, G = 1e-3, 2500.0, 1000.0, 9.81
M = RHO * math.pi / 6 * D**3


def on_incline(law, mu, angle_deg, t_end=0.05):
    """A non-rotating sphere released at rest on a plane tilted by `angle` about y; returns (displacement, velocity)."""
    a = math.radians(angle_deg)
    normal = (math.sin(a), 0.0, math.cos(a))  # plane through 0; downhill is +x along the plane
    p = DEMParams(contact_model=law, stiffness=KN, friction_pw=mu, restitution_pw=0.5, rotation=False, gravity=G)
    dem = DEM(p, walls=Walls(planes=[((0, 0, 0), normal)]))
    rest = D / 2 - M * G * math.cos(a) / KN
    x0 = np.array(normal) * rest
    dem.add_particles(x0[None, :], D, RHO)
    dem.advance(int(t_end / dem.dt))
    tang = np.array([math.cos(a), 0.0, -math.sin(a)])
    return float((dem.particles.pos[0] - x0) @ tang), float(dem.particles.vel[0] @ tang), dem


def test_history_law_holds_a_block_below_the_friction_angle():
    disp, vel, _ = on_incline("linear-history", mu=0.5, angle_deg=20)  # tan 20 deg = 0.36 < 0.5
    assert abs(disp) < 1e-3 * D  # only the tangential spring's elastic give
    assert abs(vel) < 1e-4


@pytest.mark.parametrize("law", ["linear", "linear-history"])
def test_sliding_on_incline_accelerates_at_g_sin_minus_mu_cos(law):
    mu, ang = 0.2, 30.0
    t = 0.05
    _, vel, dem = on_incline(law, mu, ang, t_end=t)
    a = G * (math.sin(math.radians(ang)) - mu * math.cos(math.radians(ang)))
    assert vel == pytest.approx(a * dem.time, rel=0.01)


def test_stiffness_from_material_is_seed000_eqs_10_to_12():
    E, s, r, dlt = 1e7, 0.3, 0.5e-3, 5e-6
    kn, kt = stiffness_from_material(E, s, r, dlt)
    assert kn == pytest.approx(math.sqrt(2 * r) * E / (3 * (1 - s**2)) * math.sqrt(dlt), rel=1e-14)
    assert kt == pytest.approx(2 * math.sqrt(2 * r) * (E / (2 * (1 + s))) / (2 - s) * math.sqrt(dlt), rel=1e-14)
    # Hertz: the secant stiffness at the overlap gives the Hertz force there
    hertz = (4 / 3) * (E / (2 * (1 - s**2))) * math.sqrt(r / 2) * dlt**1.5
    assert kn * dlt == pytest.approx(hertz, rel=1e-12)
    knw, _ = stiffness_from_material(E, s, r, dlt, wall_young=E, wall_poisson=s)
    assert knw == pytest.approx(4 * math.sqrt(r) / 3 / (2 * (1 - s**2) / E) * math.sqrt(dlt), rel=1e-14)
    with pytest.raises(ValueError, match="poisson"):
        stiffness_from_material(E, 0.7, r, dlt)


@pytest.mark.parametrize("integrator", ["rk2", "verlet"])
def test_external_force_and_gravity_are_integrated_exactly(integrator):
    dem = DEM(DEMParams(integrator=integrator, gravity=G))
    dem.add_particles(np.array([[0.0, 0, 0], [0.01, 0, 0]]), D, RHO)
    f = np.array([[1e-5, 0, 0], [0, -2e-5, 3e-5]])
    dem.advance(100, 1e-5, f_ext=f)
    t = dem.time
    acc = f / M + np.array([0, 0, -G])
    assert np.allclose(dem.particles.vel, acc * t, rtol=1e-12, atol=1e-15)
    assert np.allclose(dem.particles.pos - [[0, 0, 0], [0.01, 0, 0]], 0.5 * acc * t**2, rtol=1e-9, atol=1e-15)
    with pytest.raises(ValueError, match="f_ext"):
        dem.advance(1, 1e-5, f_ext=np.zeros((3, 3)))


def test_history_survives_insertion_and_removal():
    p = DEMParams(contact_model="linear-history", friction_pp=0.5, gravity=G, rotation=False)
    dem = DEM(p, walls=Walls.box([0.001, 0.0015, 0], [0.003, 0.0025, 0.02]))
    x = np.array([[0.0015, 0.002, 0.0005], [0.0025, 0.002, 0.0005], [0.002, 0.002, 0.0005 + 0.00087]])
    dem.add_particles(x, D, RHO)
    dem.advance(2000)

    def table():
        pl = dem.pairs
        g = dem.particles.gid
        i = np.repeat(np.arange(pl.n), np.diff(pl.start))
        out = {}
        for k, (a, b) in enumerate(zip(i, pl.nbr[: pl.size], strict=True)):
            s = 1.0 if g[a] < g[b] else -1.0  # canonical: displacement of the smaller gid
            out[(min(g[a], g[b]), max(g[a], g[b]))] = s * pl.hist[k]
        return out

    before = table()
    assert np.any(before[(0, 2)] != 0)
    dem.add_particles(np.array([[0.001, 0.001, 0.015], [0.003, 0.003, 0.015]]), D, RHO)
    dem.remove_particles(dem.particles.gid == 4)
    dem.rebuild()
    after = table()
    assert np.array_equal(after[(0, 2)], before[(0, 2)]) and np.array_equal(after[(1, 2)], before[(1, 2)])


def test_registries_and_bad_input():
    assert {"linear", "linear-history"} <= set(CONTACT_LAWS.names())
    assert {"rk2", "verlet"} <= set(INTEGRATORS.names())
    with pytest.raises(ValueError, match=r"contact_model = 'hertz' \(contact.model\): expected one of 'linear'"):
        DEM(DEMParams(contact_model="hertz"))
    with pytest.raises(ValueError, match="integrator"):
        DEM(DEMParams(integrator="euler"))
    with pytest.raises(ValueError, match="restitution_pp"):
        DEM(DEMParams(restitution_pp=0.0))
    with pytest.raises(ValueError, match="dim"):
        DEM(DEMParams(dim=1))
    law = get_law("linear")
    assert contact_time(KN, 1.0, M / 2) == pytest.approx(math.pi * math.sqrt(M / 2 / KN), rel=1e-14)
    dem = DEM(DEMParams(contact_model="linear", stiffness=KN, restitution_pp=0.9, restitution_pw=0.9))
    dem.add_particles(np.zeros((1, 3)), D, RHO)
    assert dem.critical_time() == pytest.approx(contact_time(KN, 0.9, M / 2), rel=1e-12)
    assert dem.dt == pytest.approx(dem.critical_time() / 6)
    assert law.params(KN, 0.9, 0.3).friction == 0.3


@pytest.mark.parametrize("integrator", ["rk2", "verlet"])
def test_regularised_coulomb_stops_but_never_reverses_slip(integrator):
    """`linear`: a slow slide under strong friction decays (by half per step: the cap m |u_t| / dt is applied over
    dt from the predicted/midpoint slip); the slip never changes sign."""
    p = DEMParams(contact_model="linear", stiffness=KN, friction_pw=1.0, restitution_pw=0.5, rotation=False, gravity=G,
                  integrator=integrator)  # fmt: skip
    dem = DEM(p, walls=Walls(planes=[((0, 0, 0), (0, 0, 1))]))
    dem.add_particles(np.array([[0, 0, D / 2 - M * G / KN]]), D, RHO, vel=np.array([[1e-5, 0, 0]]))
    vs = []
    for _ in range(20):
        dem.advance(1)
        vs.append(dem.particles.vel[0, 0])
    assert min(vs) >= 0.0
    assert vs[-1] < 1e-5 * 2.0**-15
