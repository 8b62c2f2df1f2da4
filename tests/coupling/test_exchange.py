"""The coupling steps of one gas step: Newton's third law through `Coupler` (0 filter passes: exact)."""

import numpy as np
import pytest
from _coupling_meshes import mesh_and_arrays, random_points

from febed.coupling.drag import RECORD_COLUMNS, RECORD_FORCE, RECORD_FP, RECORD_K, RECORD_SET, RECORD_VEL
from febed.coupling.exchange import Coupler, solid_volume
from febed.coupling.projection import neighbour_filter, per_volume, project, solid_fraction


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

    # the solver's path: the same kernel writing each particle's record, and the shortest relaxation time
    record = np.zeros((n, RECORD_COLUMNS))
    mass = rng.uniform(1e-6, 2e-6, n)
    drag = np.empty((n, 3))
    tau = cp.forces_into(u_nodes, eps_nodes, gradp_nodes, v, d_orig, n_orig, record, mass, drag)
    assert np.array_equal(record[:, RECORD_K], K2) and np.array_equal(record[:, RECORD_FORCE], F_d2 + F_p2)
    assert np.array_equal(record[:, RECORD_VEL], v) and np.array_equal(record[:, RECORD_FP], F_p2)
    assert np.all(record[:, RECORD_SET] == 1.0) and np.array_equal(drag, F_d2)
    columns = [RECORD_K, *range(11)[RECORD_FORCE], *range(11)[RECORD_VEL], *range(11)[RECORD_FP], RECORD_SET]
    assert sorted(columns) == list(range(RECORD_COLUMNS))  # the names cover every column once
    assert tau == np.min(mass / np.maximum(K2, 1e-300))
    with pytest.raises(ValueError, match="record"):
        cp.forces_into(u_nodes, eps_nodes, gradp_nodes, v, d_orig, n_orig, record[:, :10], mass)


@pytest.mark.mpi
@pytest.mark.parametrize("name", ["quad", "tet-unstructured"])
@pytest.mark.parametrize("passes", [0, 2])
def test_project_to_gas_equals_the_step_by_step_functions(name, passes):
    """project_to_gas (kernels on reused arrays) gives bit for bit what project, the filter and the division give."""
    _, ma = mesh_and_arrays(name)
    g = ma.gdim
    n = 400
    x = random_points(ma, n, seed=31)
    rng = np.random.default_rng(32)
    floor = 0.9  # clips some nodes
    cp = Coupler(ma, "wen-yu", rho_g=1.2, mu_g=1.8e-5, filter_passes=passes, void_floor=floor)
    cp.locate(x)
    d_orig = rng.uniform(2e-3, 4e-3, n)
    n_orig = rng.integers(1, 4, n)
    K = rng.uniform(1e-5, 2e-5, n)
    v = rng.normal(0.0, 0.2, (n, 3))
    F = rng.normal(0.0, 1e-4, (n, 3))
    owned = (cp.cell >= 0) & (cp.cell < ma.num_owned_cells)
    cell = np.where(owned, cp.cell, -1).astype(np.int32)
    for F_explicit in (F, None):
        for counts in (n_orig, n_orig.astype(float)):
            ex = cp.project_to_gas(d_orig, counts, K, v, F_explicit=F_explicit, owned=owned)
            cols = [solid_volume(d_orig, counts.astype(float)), K, *(K * v[:, a] for a in range(g))]
            cols += [-F_explicit[:, a] for a in range(g)] if F_explicit is not None else []
            nodal = neighbour_filter(ma, project(ma, cell, cp.w, np.stack(cols, axis=1)), passes)
            alpha, eps, clipped = solid_fraction(ma, np.ascontiguousarray(nodal[:, 0]), floor)
            dens = per_volume(ma, nodal)
            assert clipped > 0 and ex.clipped == clipped
            assert np.array_equal(ex.alpha, alpha) and np.array_equal(ex.eps, eps)
            assert np.array_equal(ex.K, dens[:, 1]) and np.array_equal(ex.Kv, dens[:, 2 : 2 + g])
            assert np.array_equal(ex.F, dens[:, 2 + g :] if F_explicit is not None else np.zeros((ma.num_dofs, g)))
