"""Projection + conservative neighbour filter (seed 001 eqs 29-34): conservation, third law, eqs 32-33."""

from mpi4py import MPI

import dolfinx.la
import numpy as np
import pytest
import ufl
from _coupling_meshes import ALL_MESHES, mesh_and_arrays, random_points
from dolfinx import fem
from dolfinx import mesh as dmesh

from febed.coupling.interpolate import interpolate
from febed.coupling.locate import locate
from febed.coupling.mesh_arrays import extract_mesh_arrays
from febed.coupling.projection import (
    neighbour_filter,
    neighbour_filter_transpose,
    per_volume,
    project,
    solid_fraction,
)
from febed.coupling.weights import compute_weights


def _my_particles(ma, n, seed):
    """The same n random particles on every rank; each rank keeps those in its owned cells (-1 elsewhere)."""
    pts = random_points(ma, n, seed=seed)
    cell, ref, _, _, _ = locate(ma, pts, np.full(n, -1, np.int32))
    cell[cell >= ma.num_owned_cells] = -1
    w = compute_weights(ma, ref, cell)
    return pts, cell, w, cell >= 0


def _gsum(comm, a):
    out = np.zeros_like(np.atleast_1d(np.asarray(a, dtype=float)))
    comm.Allreduce(np.atleast_1d(np.asarray(a, dtype=float)), out, op=MPI.SUM)
    return out


@pytest.mark.mpi
@pytest.mark.parametrize("name", ALL_MESHES)
@pytest.mark.parametrize("passes", [0, 1, 2])
def test_the_filters_transpose_is_its_adjoint_and_keeps_constants(name, passes):
    """Σ_i (T A)_i Φ_i = Σ_j A_j (Tᵀ Φ)_j over owned dofs for random sums A and fields Φ (k = 3 columns), and
    Tᵀ keeps a constant field: what the nodal pressure-gradient reaction's exact balance rests on."""
    _, ma = mesh_and_arrays(name)
    nd = ma.num_dofs
    rng = np.random.default_rng(11)
    _, cell, w, _ = _my_particles(ma, 500, seed=3)
    A = project(ma, cell, w, rng.uniform(0.5, 1.5, (500, 3)))  # extensive sums, consistent on ghosts
    x = ma.x_dofs[:, :3]
    phi = np.cos(np.array([40.0, 70.0, 110.0]) * x + x[:, ::-1])  # a smooth field, the same on every rank
    lhs = ma.owned_sum(neighbour_filter(ma, A, passes) * phi)
    rhs = ma.owned_sum(A * neighbour_filter_transpose(ma, phi, passes))
    assert np.max(np.abs(lhs - rhs)) < 1e-12 * np.max(np.abs(lhs)), (lhs, rhs)
    vol = ma.node_volume[:, None]  # Tᵀ is the filter's intensive form (seed 001 eq 31): T(Φ ΔV)/ΔV
    assert np.allclose(neighbour_filter_transpose(ma, phi, passes), neighbour_filter(ma, phi * vol, passes) / vol,
                       rtol=0, atol=1e-12)  # fmt: skip
    ones = neighbour_filter_transpose(ma, np.full((nd, 2), 2.5), passes)
    assert np.max(np.abs(ones - 2.5)) < 1e-13
    if passes:  # it averages: a non-constant field changes
        assert ma.comm.allreduce(np.max(np.abs(neighbour_filter_transpose(ma, phi, passes) - phi)), op=MPI.MAX) > 1e-3


@pytest.mark.mpi
@pytest.mark.parametrize("name", ["tet-unstructured", "tri-unstructured", "hex", "quad"])
def test_node_volumes_are_lumped_masses(name):
    m, ma = mesh_and_arrays(name)
    Q = fem.FunctionSpace(m, ("Lagrange", 1))
    b = fem.assemble_vector(fem.form(ufl.TestFunction(Q) * ufl.dx))
    b.scatter_reverse(dolfinx.la.ScatterMode.add)
    b.scatter_forward()
    scale = ma.depth if ma.gdim == 2 else 1.0
    assert np.max(np.abs(b.array * scale - ma.node_volume)) < 1e-12 * ma.node_volume.max()
    assert ma.node_volume.min() > 0.0  # ghosts hold the full value too
    total = _gsum(ma.comm, ma.cell_volume[: ma.num_owned_cells].sum())[0]
    assert abs(ma.owned_sum(ma.node_volume) - total) < 1e-13 * total
    assert np.max(np.abs(ma.cell_node_share.sum(axis=1) - ma.cell_volume)) < 1e-13 * ma.cell_volume.max()


@pytest.mark.mpi
@pytest.mark.parametrize("name", ["tet-unstructured", "tri-unstructured"])
@pytest.mark.parametrize("passes", [0, 1, 3])
def test_projection_conserves_solid_volume(name, passes):
    _, ma = mesh_and_arrays(name)
    n = 3000
    _, cell, w, mine = _my_particles(ma, n, seed=7)
    rng = np.random.default_rng(8)
    d_orig = rng.uniform(0.5e-3, 1.5e-3, n)
    n_orig = rng.integers(1, 9, n).astype(float)
    volume = n_orig * np.pi * d_orig**3 / 6.0  # represented solid volume
    total = _gsum(ma.comm, volume[mine].sum())[0]
    assert _gsum(ma.comm, mine.sum())[0] == n
    nodal = project(ma, cell, w, volume)
    filtered = neighbour_filter(ma, nodal, passes)
    assert abs(ma.owned_sum(filtered) - total) < 1e-12 * total
    # and through the solid fraction: Σ α_i ΔV_i is the particle volume (seed 001 eq 34)
    alpha, eps, clipped = solid_fraction(ma, filtered, floor=0.0)
    assert abs(ma.owned_sum(alpha * ma.node_volume) - total) < 1e-12 * total
    assert clipped == 0 and np.allclose(eps, 1.0 - alpha)
    if passes > 0:  # the filter smooths: the largest solid fraction drops
        peak0 = ma.comm.allreduce((nodal / ma.node_volume).max(), op=MPI.MAX)
        assert ma.comm.allreduce(alpha.max(), op=MPI.MAX) < peak0


@pytest.mark.mpi
@pytest.mark.parametrize("passes", [0, 1, 3])
def test_momentum_exchange_third_law(passes):
    """Gas receives exactly minus what the particles receive (explicit forces filtered, implicit drag raw)."""
    _, ma = mesh_and_arrays("tet-unstructured")
    n = 2000
    pts, cell, w, mine = _my_particles(ma, n, seed=11)
    rng = np.random.default_rng(12)
    K = rng.uniform(1e-6, 1e-4, n)  # kg/s
    v = rng.normal(0.0, 0.3, (n, 3))  # particle velocity
    u_nodes = rng.normal(0.5, 0.2, (ma.num_dofs, 3))
    ma.update_ghosts(u_nodes)  # a consistent gas field
    u_p = interpolate(ma, cell, w, u_nodes)
    f_drag = K[:, None] * (u_p - v)
    f_drag[~mine] = 0.0
    particles_total = _gsum(ma.comm, f_drag.sum(axis=0))
    scale = np.abs(particles_total).max()
    # explicit force projection (seed 001 eq 29), conserved through any number of filter passes
    gas_explicit = neighbour_filter(ma, project(ma, cell, w, -f_drag), passes)
    assert np.max(np.abs(ma.owned_sum(gas_explicit) + particles_total)) < 1e-12 * scale
    # implicit form -K_i u_i + (K v)_i with the same u the particles saw (unfiltered: exact third law)
    K_i = project(ma, cell, w, K)
    Kv_i = project(ma, cell, w, K[:, None] * v)
    gas_implicit = -K_i[:, None] * u_nodes + Kv_i
    assert np.max(np.abs(ma.owned_sum(gas_implicit) + particles_total)) < 1e-12 * scale
    # filtered K and K v keep their totals (the exchange is exact for a uniform gas velocity)
    K_f = neighbour_filter(ma, K_i, passes)
    assert abs(ma.owned_sum(K_f) - _gsum(ma.comm, K[mine].sum())[0]) < 1e-12 * K.sum()
    assert per_volume(ma, K_f).shape == (ma.num_dofs,)


@pytest.mark.mpi
def test_void_fraction_floor_counts_clipped_nodes():
    _, ma = mesh_and_arrays("tri-unstructured")
    alpha_target = np.linspace(0.0, 0.9, ma.num_dofs)
    _, eps, clipped = solid_fraction(ma, alpha_target * ma.node_volume, floor=0.35)
    expected = np.count_nonzero(1.0 - alpha_target[: ma.num_owned_dofs] < 0.35)
    assert clipped == ma.comm.allreduce(int(expected))
    assert eps.min() == pytest.approx(0.35)
    with pytest.raises(ValueError, match="floor"):
        solid_fraction(ma, alpha_target * ma.node_volume, floor=1.5)


@pytest.mark.mpi
@pytest.mark.parametrize("name", ["tet-unstructured", "hex"])
def test_filter_preserves_uniform_fields(name):
    _, ma = mesh_and_arrays(name)
    out = neighbour_filter(ma, 0.37 * ma.node_volume, 2) / ma.node_volume
    assert np.max(np.abs(out - 0.37)) < 1e-14


def _neighbour_offsets(ma, m, i):
    """Integer lattice offsets (in cells) of the nodes sharing a cell with node i, with their dofs."""
    h = np.array([1.0 / 6.0] * 3)
    cells = np.nonzero(np.any(ma.cell_dofs == i, axis=1))[0]
    dofs = np.unique(ma.cell_dofs[cells])
    off = np.rint((ma.x_dofs[dofs] - ma.x_dofs[i]) / h).astype(int)
    return dofs, off


def test_filter_reduces_to_eqs_32_33_on_uniform_grids():
    """Interior nodes of uniform grids: eq 32 (2D triangles, 6 neighbours) and eq 33 (3D hexahedra)."""
    comm = MPI.COMM_SELF
    rng = np.random.default_rng(3)
    # eq 32: Φ̂ = Φ/3 + 1/9 Σ_{6 neighbours} Φ
    m2 = dmesh.create_unit_square(comm, 6, 6, dmesh.CellType.triangle)
    ma2 = extract_mesh_arrays(m2, depth=1.0)
    phi = rng.random(ma2.num_dofs)
    hat = neighbour_filter(ma2, phi * ma2.node_volume, 1) / ma2.node_volume
    interior = np.nonzero(np.all((ma2.x_dofs[:, :2] > 0.01) & (ma2.x_dofs[:, :2] < 0.99), axis=1))[0]
    for i in interior:
        dofs, _ = _neighbour_offsets(ma2, m2, i)
        nb = dofs[dofs != i]
        assert len(nb) == 6
        assert abs(hat[i] - (phi[i] / 3.0 + phi[nb].sum() / 9.0)) < 1e-14
    # eq 33: Φ̂ = Φ/8 + (4 Σ_RN + 2 Σ_BN + Σ_GN)/64, face / edge / corner neighbours
    m3 = dmesh.create_unit_cube(comm, 6, 6, 6, dmesh.CellType.hexahedron)
    ma3 = extract_mesh_arrays(m3)
    phi = rng.random(ma3.num_dofs)
    hat = neighbour_filter(ma3, phi * ma3.node_volume, 1) / ma3.node_volume
    interior = np.nonzero(np.all((ma3.x_dofs > 0.01) & (ma3.x_dofs < 0.99), axis=1))[0]
    for i in interior[::7]:
        dofs, off = _neighbour_offsets(ma3, m3, i)
        kind = np.abs(off).sum(axis=1)  # 0 self, 1 face (RN), 2 edge (BN), 3 corner (GN)
        assert np.array_equal(np.bincount(kind), [1, 6, 12, 8])
        expect = phi[i] / 8.0 + (4 * phi[dofs[kind == 1]].sum() + 2 * phi[dofs[kind == 2]].sum()) / 64.0
        expect += phi[dofs[kind == 3]].sum() / 64.0
        assert abs(hat[i] - expect) < 1e-14


def test_bad_input_is_rejected():
    _, ma = mesh_and_arrays("quad")
    with pytest.raises(ValueError, match="passes"):
        neighbour_filter(ma, ma.node_volume, -1)
    with pytest.raises(ValueError, match="values"):
        project(ma, np.zeros(3, np.int32), np.zeros((3, 4)), np.zeros(4))
    with pytest.raises(ValueError, match="x"):
        locate(ma, np.zeros((3, 2)), np.zeros(3, np.int32))


@pytest.mark.mpi
@pytest.mark.parametrize("name", ["hex", "tet-distorted"])
def test_partitioned_result_equals_serial(name):
    """Projection + 3 filter passes on the distributed mesh give the serial nodal values at every node."""
    m, ma = mesh_and_arrays(name)
    comm = ma.comm
    n = 1500
    pts, cell, w, mine = _my_particles(ma, n, seed=31)
    vol = np.random.default_rng(32).uniform(1e-10, 1e-9, n)
    alpha = neighbour_filter(ma, project(ma, cell, w, vol), 3) / ma.node_volume
    owned = slice(0, ma.num_owned_dofs)
    xs = comm.gather(ma.x_dofs[owned], root=0)
    vals = comm.gather(alpha[owned], root=0)
    if comm.rank == 0:
        from _coupling_meshes import _distorted

        ms = _distorted({"hex": "hexahedron", "tet-distorted": "tetrahedron"}[name], MPI.COMM_SELF)
        mas = extract_mesh_arrays(ms)
        cs, rs, _, _, _ = locate(mas, pts, np.full(n, -1, np.int32))
        ws = compute_weights(mas, rs, cs)
        ref = neighbour_filter(mas, project(mas, cs, ws, vol), 3) / mas.node_volume
        xs, vals = np.concatenate(xs), np.concatenate(vals)
        assert len(vals) == mas.num_dofs
        key = lambda x: np.lexsort(np.round(x / 1e-9).T)  # noqa: E731
        assert np.allclose(xs[key(xs)], mas.x_dofs[key(mas.x_dofs)], atol=1e-12, rtol=0)
        assert np.max(np.abs(vals[key(xs)] - ref[key(mas.x_dofs)])) < 1e-12 * ref.max()
