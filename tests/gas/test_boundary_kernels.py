"""The compiled boundary-condition kernels of the gas step against their NumPy forms on random data.

`febed.gas.kernels` imposes the no-slip, inlet and slip-wall velocities, adds the walls' implicit shear
(partial-slip and porous wall-law nodes) and the outlet's backflow coefficient row by row. Each must give what
the array expression it stands for gives, to the bit when the sums over the components run in order (NumPy's
einsum adds three components as (0 + 2) + 1, so it agrees to round-off only).
"""

import numpy as np
import pytest

from febed.gas import kernels
from febed.gas.boundary import porous_slip_inverse


def _rows(rng, n, m):
    return np.sort(rng.choice(n, m, replace=False)).astype(np.int32)


def _dot(a, b):
    """Σ_d a[..., d] b[..., d], the components added in order."""
    s = a[..., 0] * b[..., 0]
    for d in range(1, a.shape[-1]):
        s = s + a[..., d] * b[..., d]
    return s


@pytest.mark.parametrize("gdim", [2, 3])
def test_velocity_rows(gdim):
    rng = np.random.default_rng(gdim)
    n = 400
    q = rng.normal(size=(n, gdim))
    noslip, inlet, slip = _rows(rng, n, 50), _rows(rng, n, 30), _rows(rng, n, 80)
    w, normal = rng.random(inlet.size), rng.normal(size=gdim)
    proj = rng.normal(size=(slip.size, gdim, gdim))

    other = np.union1d(inlet[:10], _rows(rng, n, 20))  # a second inlet sharing ten of the first's rows
    w2, normal2 = rng.random(other.size), rng.normal(size=gdim)
    ref = q.copy()
    ref[noslip] = 0.0
    ref[np.union1d(inlet, other)] = 0.0
    ref[inlet] += 1.7 * w[:, None] * normal
    ref[other] += 0.3 * w2[:, None] * normal2
    out = q.copy()
    kernels.zero_rows(out, noslip)
    kernels.zero_rows(out, np.union1d(inlet, other))
    kernels.add_rows(out, inlet, 1.7, w, normal)
    kernels.add_rows(out, other, 0.3, w2, normal2)
    assert np.array_equal(out, ref)

    via_einsum = ref.copy()
    via_einsum[slip] = np.einsum("nij,nj->ni", proj, ref[slip])
    ref[slip] = _dot(proj, ref[slip][:, None, :])
    kernels.project_rows(out, slip, proj)
    assert np.array_equal(out, ref)
    np.testing.assert_allclose(out, via_einsum, rtol=0, atol=1e-14 * np.abs(ref).max())


def test_divide_rows():
    rng = np.random.default_rng(1)
    q, eps = rng.normal(size=(300, 3)), rng.uniform(0.4, 1.0, 300)
    u = np.empty_like(q)
    kernels.divide_rows(q, eps, u)
    assert np.array_equal(u, q / eps[:, None])


def test_wall_friction_is_the_porous_wall_law_node_by_node():
    rng = np.random.default_rng(2)
    n = 500
    K = rng.uniform(0.0, 5e4, n)
    K[:40] = 0.0  # clear gas: the law's no-slip limit
    eps_mu = rng.uniform(0.4, 1.0, n) * 1.8e-5
    volume = rng.uniform(1e-9, 2e-9, n)
    friction, law = _rows(rng, n, 60), _rows(rng, n, 120)
    friction_area, law_area = rng.uniform(0.1, 1.0, friction.size), rng.uniform(1e-6, 2e-6, law.size)
    law_h = rng.uniform(5e-4, 2e-3, law.size)

    ref = K.copy()
    ref[friction] += eps_mu[friction] * friction_area / volume[friction]
    ref[law] += eps_mu[law] * law_area * porous_slip_inverse(ref[law], eps_mu[law], law_h) / volume[law]
    out = K.copy()
    kernels.add_wall_friction(out, eps_mu, volume, friction, friction_area, law, law_area, law_h)
    assert np.array_equal(out, ref)


def test_backflow_coefficients():
    rng = np.random.default_rng(3)
    n = 200
    q, bnormal, mass = rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.uniform(1e-9, 2e-9, n)
    rows = _rows(rng, n, 40)
    c = np.empty(rows.size)
    flux = _dot(bnormal[rows], q[rows])
    assert kernels.backflow_coefficients(rows, bnormal, q, mass, 0.6, c)
    assert np.array_equal(c, 0.6 * np.maximum(-flux, 0.0) / mass[rows])
    outflow = rows[flux > 0]  # every row leaving: no coefficient, and the kernel says so
    assert not kernels.backflow_coefficients(outflow, bnormal, q, mass, 0.6, np.empty(outflow.size))
