"""Drag closures against values computed here from the written formulas (plain Python floats)."""

import math

import numpy as np
import pytest

from febed.coupling.drag import drag_forces, emms_heterogeneity, get_drag_law, pressure_gradient_kernel
from febed.schema import DRAG_LAWS

RHO_G, MU_G, RHO_P = 1.28, 1.7e-5, 1150.0
# (eps, slip m/s, d m): dense/slow, intermediate, dilute, and one above Re = 1000
STATES = [(0.42, 0.3, 1.5e-3), (0.62, 1.1, 1.0e-3), (0.93, 0.05, 5.0e-4), (0.97, 25.0, 3.0e-3)]


def k_from_tau(cd, re, d):
    """K = m_p / τ_p with τ_p = 4 ρ_p d² / (3 μ C_D Re_p) (seed 001 eqs 20-21)."""
    m_p = RHO_P * math.pi * d**3 / 6.0
    tau = 4.0 * RHO_P * d**2 / (3.0 * MU_G * cd * re)
    return m_p / tau


def cd_wen_yu(eps, re):
    return (24.0 / re * (1.0 + 0.15 * re**0.687) if re < 1000.0 else 0.44) * eps**-2.7  # seed 001 eq 24


def cd_ergun(eps, re):
    return (200.0 * (1.0 - eps) / re + 7.0 / 3.0) / eps  # seed 001 eq 25


def hand_wen_yu(eps, slip, d):
    re = eps * RHO_G * slip * d / MU_G
    return k_from_tau(cd_wen_yu(eps, re), re, d)


def hand_ergun(eps, slip, d):
    re = eps * RHO_G * slip * d / MU_G
    return k_from_tau(cd_ergun(eps, re), re, d)


def hand_gidaspow(eps, slip, d):
    re = eps * RHO_G * slip * d / MU_G
    phi = math.atan(150.0 * 1.75 * (0.2 - (1.0 - eps))) / math.pi + 0.5  # eq 22
    return k_from_tau(phi * cd_wen_yu(eps, re) + (1.0 - phi) * cd_ergun(eps, re), re, d)  # eq 23


def hand_schiller_naumann(eps, slip, d):
    re = RHO_G * slip * d / MU_G
    cd = 24.0 / re * (1.0 + 0.15 * re**0.687) if re < 1000.0 else 0.44
    return 0.5 * cd * RHO_G * math.pi * d**2 / 4.0 * slip  # |F| = C_D ρ A |w|² / 2 = K |w|


def hand_stokes(eps, slip, d):
    return 3.0 * math.pi * MU_G * d  # F = 3 π μ d w


def table1(eps, re):
    """H_d of seed 000 Table 1 (with the two sign readings documented in febed.coupling.drag)."""
    e = min(max(eps, 0.4), 1.0)
    if 0.4 <= e < 0.46:
        a, b, c = 0.8526 - 0.5846 / (1 + (e / 0.4325) ** 22.6279), 0.0, 0.0
    elif 0.46 <= e < 0.545:
        a = 0.0320 + 0.7399 / (1 + (e / 0.4912) ** 54.4265)
        b = 0.00225 + 0.02404 / (1 + 10 ** (53.8948 * (0.5257 - e))) + 0.1731 / (1 + 10 ** (66.3224 * (e - 0.3987)))
        c = 0.1705 - 0.1731 / (1 + (e / 0.5020) ** 37.7091)
    elif 0.545 <= e < 0.99:
        a = (2124.956 - 2142.3 * e) ** -0.4896
        b = (0.8223 - 0.1293 * e) ** 13.0310
        c = (e - 1.0013) / (-0.06633 + 9.1391 * (e - 1.0013) + 6.9231 * (e - 1.0013) ** 2)
    elif 0.99 <= e < 0.9997:
        a = 0.4243 + 0.8800 / (1 + math.exp(-(e - 0.9942) / 0.00218)) * (
            1 - 1 / (1 + math.exp(-(e - 0.9989) / 0.00003))
        )
        b = 0.01661 + 0.2436 * math.exp(-0.5 * ((e - 0.9985) / 0.00191) ** 2)
        c = 0.0825 - 0.0574 * math.exp(-0.5 * ((e - 0.9979) / 0.00703) ** 2)
    else:
        a, b, c = 1.0, 0.0, 0.0
    return a * (re + b) ** c


def hand_emms(eps, slip, d):
    """K = V β / (1 - ε) from seed 000 eqs 2-5."""
    re = eps * RHO_G * slip * d / MU_G  # eq 5
    cd = 24.0 * (1.0 + 0.15 * re**0.687) / re if re <= 1000.0 else 0.44  # eq 4
    beta = 0.75 * eps * (1.0 - eps) * RHO_G * slip / d * eps**-2.65 * cd * table1(eps, re)  # eq 3
    return math.pi * d**3 / 6.0 * beta / (1.0 - eps)  # eq 2


HAND = {
    "wen-yu": hand_wen_yu,
    "ergun": hand_ergun,
    "gidaspow-blend": hand_gidaspow,
    "schiller-naumann": hand_schiller_naumann,
    "stokes": hand_stokes,
    "emms": hand_emms,
}


def test_every_law_is_registered():
    assert sorted(HAND) == DRAG_LAWS.names()
    with pytest.raises(ValueError, match="gidaspow-blend"):
        get_drag_law("gidaspow")


@pytest.mark.parametrize("name", sorted(HAND))
def test_law_matches_hand_values(name):
    law = get_drag_law(name)
    for eps, slip, d in STATES:
        expect = HAND[name](eps, slip, d)
        assert law(eps, slip, d, RHO_G, MU_G) == pytest.approx(expect, rel=1e-12), (eps, slip, d)
    # finite at zero slip (K is used implicitly)
    assert math.isfinite(law(0.6, 0.0, 1e-3, RHO_G, MU_G))


def test_gidaspow_blend_switches_between_ergun_and_wen_yu():
    law, er, wy = (get_drag_law(n) for n in ("gidaspow-blend", "ergun", "wen-yu"))
    assert law(0.45, 0.5, 1e-3, RHO_G, MU_G) == pytest.approx(er(0.45, 0.5, 1e-3, RHO_G, MU_G), rel=0.01)
    assert law(0.95, 0.5, 1e-3, RHO_G, MU_G) == pytest.approx(wy(0.95, 0.5, 1e-3, RHO_G, MU_G), rel=0.01)


@pytest.mark.parametrize("eps", [0.41, 0.45, 0.47, 0.5, 0.53, 0.55, 0.7, 0.9, 0.985, 0.991, 0.995, 0.9993, 0.9998, 1.0])
def test_emms_heterogeneity_matches_table_1(eps):
    for re in (0.5, 20.0, 300.0):
        assert emms_heterogeneity(eps, re) == pytest.approx(table1(eps, re), rel=1e-12)


def test_emms_heterogeneity_clamps_and_joins_ranges():
    for re in (1.0, 50.0):
        assert emms_heterogeneity(0.2, re) == emms_heterogeneity(0.4, re)  # ε clamped into [0.4, 1]
        assert emms_heterogeneity(1.2, re) == 1.0
        # the readings of the two signs make H_d positive and continuous (within 4 %) at 0.46 and 0.545
        for e0 in (0.46, 0.545):
            lo, hi = emms_heterogeneity(e0 - 1e-9, re), emms_heterogeneity(e0, re)
            assert abs(hi - lo) < 0.04 * hi
    e = np.linspace(0.4, 1.0, 2001)
    assert all(0.0 < emms_heterogeneity(x, 10.0) < 1.5 for x in e)  # positive, no pole
    # a value worked out by hand: ε = 0.545, Re = 10 -> a = 0.0347, b = 0.0243, c = 0.1633, H_d = 0.0506
    assert emms_heterogeneity(0.545, 10.0) == pytest.approx(0.0506, rel=0.005)


def test_batched_kernel_coarse_grain_and_force():
    n = 4
    eps = np.array([s[0] for s in STATES])
    d = np.array([s[2] for s in STATES])
    u = np.zeros((n, 3))
    u[:, 2] = [s[1] for s in STATES]
    v = np.zeros((n, 3))
    v[:, 0] = 0.0  # slip along z only
    n_orig = np.array([1.0, 8.0, 27.0, 2.0])
    for name in ("gidaspow-blend", "emms"):
        K, F = drag_forces(name, eps, u, v, d, n_orig, RHO_G, MU_G)
        for p in range(n):
            k1 = HAND[name](eps[p], u[p, 2], d[p])
            assert K[p] == pytest.approx(n_orig[p] * k1, rel=1e-12)
            assert F[p, 2] == pytest.approx(n_orig[p] * k1 * u[p, 2], rel=1e-12)
            assert F[p, 0] == 0.0 and F[p, 1] == 0.0
    with pytest.raises(ValueError, match="n_orig"):
        drag_forces("stokes", eps, u, v, d, n_orig[:2], RHO_G, MU_G)


def test_pressure_gradient_force():
    vol = np.array([1e-9, 2e-9])
    grad = np.array([[0.0, -1.2e4], [30.0, 5.0]])  # 2D gradient (Pa/m)
    F = np.empty((2, 3))
    pressure_gradient_kernel(vol, grad, F)
    assert np.allclose(F, [[0.0, 1.2e-5, 0.0], [-6e-8, -1e-8, 0.0]], rtol=1e-14, atol=0)


def test_terminal_velocity():
    from febed.coupling.drag import terminal_velocity

    d, rho_p = 1e-4, 2500.0
    stokes = (rho_p - RHO_G) * 9.81 * d**2 / (18.0 * MU_G)
    assert terminal_velocity("stokes", d, rho_p, RHO_G, MU_G) == pytest.approx(stokes, rel=1e-10)
    # Schiller-Naumann at 1.5 mm (Re ~ 500): C_D(Re_t) ρ_g v_t² π d²/8 = (ρ_p - ρ_g) g π d³/6 by hand
    d = 1.5e-3
    vt = terminal_velocity("schiller-naumann", d, 1150.0, RHO_G, MU_G)
    re = RHO_G * vt * d / MU_G
    cd = 24.0 / re * (1.0 + 0.15 * re**0.687)
    drag = 0.5 * cd * RHO_G * vt**2 * math.pi * d**2 / 4.0
    weight = (1150.0 - RHO_G) * 9.81 * math.pi * d**3 / 6.0
    assert drag == pytest.approx(weight, rel=1e-9)
    assert 100.0 < re < 1000.0
