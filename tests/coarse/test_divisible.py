"""Divisible originals in PCPM (`coarse_grain.min_group` < 1, seed 000 sec 4): crush sizes in pieces of
`min_group`, originals crushed into pieces with the count conserved exactly and momentum to round-off, a piece's
drag equal to that of one sphere of its own diameter, and the bad values refused."""

import math
from pathlib import Path

import numpy as np
import pytest

from febed.case import CaseError, load_case
from febed.coarse.pcpm import NO_CRUSH, GroupDynamics
from febed.coarse.setup import closure_sizes
from febed.coarse.tm import use_group_contacts
from febed.coupling.drag import drag_forces
from febed.dem import DEM, DEMParams, Walls
from febed.dem.insertion import random_positions
from febed.dem.particles import Particles
from febed.io.particles import ParticleWriter, read_vtp

DO, RHO = 1e-3, 2500.0
WANG2D = Path(__file__).parents[2] / "demos" / "wang2d" / "wang2d.toml"


def test_crush_sizes_in_pieces_of_an_eighth():
    gd = GroupDynamics(DO, RHO, 1.2, 1.8e-5, 0.45, min_group=0.125)
    # one original (8 pieces of d_O/2) at d_cl = 0.6 d_O: children of floor((0.6/0.5)^3) = 1 piece, and
    # floor(1/0.36) = 2 of them (eq 41), the remainder 6 pieces (eq 42)
    assert gd.crush_sizes(1.0, DO, 0.6 * DO) == (0.125, 2, 0.75)
    # a group of 8 at d_cl = d_O: children of 8 pieces (one original), 4 of them, remainder 4 originals
    assert gd.crush_sizes(8.0, 2 * DO, DO) == (1.0, 4, 4.0)
    # the smallest piece never crushes; whole originals do not crush unless divisible
    assert gd.crush_sizes(0.125, 0.5 * DO, 0.1 * DO)[1] == 0
    assert GroupDynamics(DO, RHO, 1.2, 1.8e-5, 0.45).crush_sizes(1.0, DO, 0.6 * DO)[1] == 0


@pytest.mark.parametrize("bad", [0.3, 0.0, 2.0, 1 / 128])
def test_min_group_must_be_a_power_of_two_fraction(bad):
    with pytest.raises(ValueError, match="min_group"):
        GroupDynamics(DO, RHO, 1.2, 1.8e-5, 0.45, min_group=bad)


def test_case_refuses_a_min_group_that_is_not_a_power_of_two_fraction(tmp_path):
    case = tmp_path / "c.toml"
    case.write_text(f'extends = "{WANG2D}"\n[coarse_grain]\nmodel = "pcpm"\nmin_group = 0.3\n'
                    '[contact]\nmodel = "linear"\n')  # fmt: skip
    with pytest.raises(CaseError, match=r"min_group = 0\.3.*0\.125"):
        load_case(case)


def test_originals_crush_into_pieces_conserving_count_and_momentum():
    rng = np.random.default_rng(5)
    lo, hi = np.zeros(3), np.full(3, 0.02)
    dem = DEM(DEMParams(gravity=0.0, stiffness=800.0, contact_model="linear"), walls=Walls.box(lo, hi))
    pos = random_positions(200, lo, hi, 1.6 * DO, seed=4)
    vel = np.array([0.3, -0.2, 0.1]) + 0.05 * rng.normal(size=(200, 3))
    dem.add_particles(pos, DO, RHO, vel=vel, n_orig=1.0)
    gd = GroupDynamics(DO, RHO, 1.2, 1.8e-5, 0.45, min_group=0.125, overlap_tolerance=0.3, merge=False,
                       measure_energy=False, conserve_energy=False, seed=2)  # fmt: skip
    P = dem.particles
    p0 = (P.mass[: P.n_owned, None] * P.vel[: P.n_owned]).sum(axis=0)
    crushed = 0
    for _ in range(5):
        n = P.n_owned
        s = gd.apply(dem, np.where(rng.random(n) < 0.3, 0.55 * P.diameter[:n], NO_CRUSH))
        crushed += s.crushed
        assert s.originals == 200.0  # exact: every count is a multiple of 1/8
    n = P.n_owned
    no = P.n_orig[:n]
    assert crushed > 50 and no.min() == 0.125 and np.all(no * 8 == np.round(no * 8))
    assert np.allclose(P.diameter[:n], DO * np.cbrt(no), rtol=1e-15, atol=0)
    assert np.allclose(P.mass[:n], RHO * math.pi / 6 * DO**3 * no, rtol=1e-14, atol=0)
    p1 = (P.mass[:n, None] * P.vel[:n]).sum(axis=0)
    assert np.linalg.norm(p1 - p0) <= 1e-13 * np.linalg.norm(p0)
    # pieces move: the DEM steps them at a contact time of the lightest pair present (k_n l^2, l^3 = 1/8)
    dem.advance(20, dem.dt)
    assert np.isfinite(P.pos[: P.n_owned]).all()


def test_a_piece_has_the_drag_of_its_own_sphere_and_a_group_n_times_an_original():
    d = np.array([0.5 * DO, DO, 2 * DO])
    n = np.array([0.125, 1.0, 8.0])
    d_c, count = closure_sizes(d, n)
    assert d_c.tolist() == pytest.approx([0.5 * DO, DO, DO], rel=1e-15)
    assert count.tolist() == [1.0, 1.0, 8.0]
    assert (count * d_c**3).tolist() == pytest.approx((n * DO**3).tolist(), rel=1e-14)  # solid volume n V_O
    eps, u, v = np.full(3, 0.6), np.tile([0.0, 0.0, 1.0], (3, 1)), np.zeros((3, 3))
    K, _ = drag_forces("gidaspow-blend", eps, u, v, d_c, count, 1.2, 1.8e-5)
    K_one, _ = drag_forces("gidaspow-blend", eps[:1], u[:1], v[:1], d[:1], np.ones(1), 1.2, 1.8e-5)
    K_orig, _ = drag_forces("gidaspow-blend", eps[:1], u[:1], v[:1], np.array([DO]), np.ones(1), 1.2, 1.8e-5)
    assert K[0] == K_one[0]  # the piece: one sphere of d_O/2
    assert K[2] == pytest.approx(8 * K_orig[0], rel=1e-14)  # the group: 8 originals
    assert K[0] / (0.125 * K_orig[0]) > 2.0  # per unit mass a piece is dragged harder than an original
    # whole originals only: the inputs themselves
    d1, n1 = d[1:2], n[1:2]
    assert closure_sizes(d1, n1)[0] is d1 and closure_sizes(d1, n1)[1] is n1


def test_contact_time_of_pieces_follows_the_group_scaling():
    def contact_time(n):
        dem = DEM(DEMParams(gravity=0.0, stiffness=800.0, contact_model="linear", rotation=False))
        dem.add_particles(np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]]), DO * n ** (1 / 3), RHO, n_orig=n)
        use_group_contacts(dem, DO, RHO)
        return dem.critical_time(), dem.pp.ce

    t_orig, ce = contact_time(1.0)
    t_piece, _ = contact_time(0.125)
    # k_n l^2, c_e sqrt(l) with l^3 = 1/8 (the pair's mass over an original pair's): T_C ~ sqrt(m / k) ~ sqrt(l)
    ratio = math.sqrt(0.5) * math.sqrt((1 - ce**2) / (1 - ce**2 * 0.5))
    assert t_piece / t_orig == pytest.approx(ratio, rel=1e-12)


def test_fractional_counts_survive_output_and_reload(tmp_path):
    P = Particles()
    P.add(np.zeros((3, 3)) + np.arange(3)[:, None] * 1e-3, DO * np.cbrt([0.125, 0.75, 8.0]), RHO,
          n_orig=np.array([0.125, 0.75, 8.0]))  # fmt: skip
    assert Particles.from_dict(P.to_dict()).n_orig[:3].tolist() == [0.125, 0.75, 8.0]
    path = ParticleWriter(tmp_path).write(0.0, P)
    assert read_vtp(path)["n_orig"].tolist() == [0.125, 0.75, 8.0]
