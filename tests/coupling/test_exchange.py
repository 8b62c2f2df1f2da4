"""The coupling steps of one gas step: Newton's third law through `Coupler` (0 filter passes: exact)."""

import numpy as np
import pytest
from _coupling_meshes import mesh_and_arrays, random_points

from febed.coupling.exchange import Coupler, solid_volume


@pytest.mark.mpi
@pytest.mark.parametrize("name", ["quad", "tet-unstructured"])
def test_coupler_third_law(name):
    _, ma = mesh_and_arrays(name)
    g = ma.gdim
    n = 500
    x = random_points(ma, n, seed=21)
    rng = np.random.default_rng(22)
    cp = Coupler(ma, "gidaspow-blend", rho_g=1.28, mu_g=1.7e-5, filter_passes=0, void_floor=0.0)
    missing = cp.locate(x)
    owned = (cp.cell >= 0) & (cp.cell < ma.num_owned_cells)
    if not ma.parallel:
        assert owned.sum() == n - missing.size > 0.8 * n
    u_nodes = rng.normal(0.5, 0.3, (ma.num_dofs, g))
    gradp_nodes = rng.normal(0.0, 1e3, (ma.num_dofs, g))
    ma.update_ghosts(u_nodes)
    ma.update_ghosts(gradp_nodes)
    eps_nodes = np.full(ma.num_dofs, 0.8)
    u_p, eps_p, gp_p = cp.gas_at_particles(u_nodes, eps_nodes, gradp_nodes)
    v = rng.normal(0.0, 0.2, (n, 3))
    v[:, g:] = 0.0
    d_orig = np.full(n, 1e-3)
    n_orig = rng.integers(1, 5, n).astype(float)
    K, F_d, F_p = cp.particle_forces(u_p, eps_p, gp_p, v, d_orig, n_orig)
    ex = cp.project_to_gas(d_orig, n_orig, K, v, F_explicit=F_p, owned=owned)
    dv = ma.node_volume[:, None]
    gas = (-ex.K[:, None] * u_nodes + ex.Kv + ex.F) * dv  # what the gas receives at each node (N)
    particles = np.zeros(g)
    ma.comm.Allreduce((F_d + F_p)[owned, :g].sum(axis=0), particles)
    assert np.max(np.abs(ma.owned_sum(gas) + particles)) < 1e-12 * np.abs(particles).max()
    vol = np.zeros(1)
    ma.comm.Allreduce(np.array([solid_volume(d_orig, n_orig)[owned].sum()]), vol)
    assert abs(ma.owned_sum(ex.alpha * ma.node_volume) - vol[0]) < 1e-12 * vol[0]

    # the fused per-sub-step kernel gives the same forces
    K2, F_d2, F_p2, eps2 = cp.forces(u_nodes, eps_nodes, gradp_nodes, v, d_orig, n_orig)
    found = cp.cell >= 0
    assert np.allclose(K2[found], K[found], rtol=1e-13, atol=0) and np.all(K2[~found] == 0.0)
    assert np.allclose(F_d2, F_d, rtol=1e-12, atol=1e-14 * np.abs(F_d).max())
    assert np.allclose(F_p2, F_p, rtol=1e-12, atol=1e-14 * np.abs(F_p).max())
    assert np.allclose(eps2, eps_p, rtol=1e-14, atol=0)
