"""Interpolation to particles is exact for linear fields (seed 001 eq 28) on all four cell types."""

import numpy as np
import pytest
from _coupling_meshes import ALL_MESHES, mesh_and_arrays, random_points

from febed.coupling.interpolate import gradient_at_particles, interpolate
from febed.coupling.locate import locate
from febed.coupling.weights import compute_weights

A = np.array([[1.5, -2.0, 0.7], [0.3, 4.0, -1.1], [-0.8, 0.2, 2.5]])
B = np.array([0.1, -0.4, 2.0])


def _located(name, n=600):
    _, ma = mesh_and_arrays(name)
    pts = random_points(ma, n, seed=5)
    cell, ref, _, _, _ = locate(ma, pts, np.full(n, -1, np.int32))
    keep = cell >= 0
    return ma, pts[keep], cell[keep], ref[keep]


@pytest.mark.mpi
@pytest.mark.parametrize("name", ALL_MESHES + ("tri-distorted", "tet-distorted", "quad-affine", "hex-affine"))
def test_linear_fields_exact(name):
    ma, pts, cell, ref = _located(name)
    g = ma.gdim
    w = compute_weights(ma, ref, cell)
    assert np.max(np.abs(w.sum(axis=1) - 1.0)) < 1e-14  # seed 001 eq 28
    assert w.min() > -1e-9
    # vector field u (nd, gdim), scalar field ε (nd,)
    u_nodes = ma.x_dofs[:, :g] @ A[:g, :g].T + B[:g]
    u_p = interpolate(ma, cell, w, u_nodes)
    assert u_p.shape == (len(cell), g)
    assert np.max(np.abs(u_p - (pts[:, :g] @ A[:g, :g].T + B[:g]))) < 1e-12
    eps_nodes = 0.4 + 2.0 * ma.x_dofs[:, 0] - 3.0 * ma.x_dofs[:, 1] + ma.x_dofs[:, 2]
    eps_p = interpolate(ma, cell, w, eps_nodes)
    assert eps_p.shape == (len(cell),)
    assert np.max(np.abs(eps_p - (0.4 + 2.0 * pts[:, 0] - 3.0 * pts[:, 1] + pts[:, 2]))) < 1e-13
    # gradient of a linear pressure, cellwise, on any cell shape
    p_nodes = ma.x_dofs @ np.array([-9.81e3, 250.0, -40.0]) + 1e5
    gp = gradient_at_particles(ma, cell, ref, p_nodes)
    expect = np.array([-9.81e3, 250.0, -40.0])
    expect[g:] = 0.0
    assert np.max(np.abs(gp - expect)) < 1e-8 * 9.81e3
