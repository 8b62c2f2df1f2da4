"""Coupling on the particles' own ranks (`febed.coupling.owners`): particles in work boxes, the mesh in blocks.

Each rank locates its particles on the whole mesh, gathers the gas values of their cells' nodes from the
nodes' owners and sends its nodal sums back to them. Against the same particles coupled serially on the
whole mesh: per-particle forces and every nodal field to round-off. Run serially and under mpirun -n 2 (and
3, 4 in `make test-all`).
"""

from mpi4py import MPI

import numpy as np
import pytest

from febed.coupling.exchange import Coupler
from febed.coupling.mesh_arrays import extract_mesh_arrays
from febed.coupling.owners import NodeOwners, OwnerCoupler, dof_inputs
from febed.dem import DEM, DEMParams, Walls
from febed.meshing import build_msh, load_msh
from febed.parallel import BoxExchange

pytestmark = pytest.mark.mpi
COMM = MPI.COMM_WORLD
LX, LY, LZ = 0.02, 0.02, 0.04
D = 1e-3
LAW = dict(drag="wen-yu", rho_g=1.2, mu_g=1.8e-5, filter_passes=1)


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    """The box mesh cut in blocks over every rank, the same file read by this rank alone, and the couplers."""
    path = None
    if COMM.rank == 0:
        path = build_msh("box", tmp_path_factory.mktemp("owners") / "box.msh", cell="hexahedron", size=0.005,
                         extent=(LX, LY, LZ))  # fmt: skip
    path = COMM.bcast(path, root=0)
    md = load_msh(path, COMM, cut="blocks")
    whole = load_msh(path, MPI.COMM_SELF)
    import dolfinx.fem

    Q = dolfinx.fem.FunctionSpace(md.mesh, ("Lagrange", 1))
    ma = extract_mesh_arrays(md.mesh, Q)
    return md, whole, Q, ma


def fields(x):
    """Smooth nodal gas fields of node coordinates x: u (nd, 3), eps (nd,), grad p (nd, 3)."""
    u = np.stack([np.sin(100 * x[:, 2]), 0.3 * x[:, 0] / LX, 1.0 + np.cos(150 * x[:, 1])], axis=1)
    eps = 0.5 + 0.4 * x[:, 2] / LZ
    gradp = np.stack([x[:, 1] * 10, -x[:, 0] * 20, -9000.0 + 1e5 * x[:, 2]], axis=1)
    return u, eps, gradp


def test_node_owners_gather_every_node_and_return_every_sum(meshes):
    md, whole, Q, ma = meshes
    import dolfinx.fem

    wQ = dolfinx.fem.FunctionSpace(whole.mesh, ("Lagrange", 1))
    wx = wQ.tabulate_dof_coordinates()
    nodes = NodeOwners(dof_inputs(whole.mesh, wQ), dof_inputs(md.mesh, Q), ma.num_owned_dofs, COMM)
    every = np.arange(wx.shape[0])
    got = [np.full((wx.shape[0], 3), np.nan), np.full(wx.shape[0], np.nan)]
    nodes.gather(every, [ma.x_dofs, ma.x_dofs[:, 0].copy()], got)
    # each node from its owner (a node's tabulated coordinates may differ in the last bit between partitions)
    assert np.abs(got[0] - wx).max() <= 1e-14 and np.array_equal(got[1], got[0][:, 0])
    # every rank adds rank + 1 at a different subset; the owners hold the sums, the ghosts zero
    rng = np.random.default_rng(7)
    picks = [np.flatnonzero(rng.random(wx.shape[0]) < 0.6) for _ in range(COMM.size)]
    sums = np.zeros((wx.shape[0], 2))
    for r, p in enumerate(picks):
        sums[p] += [r + 1.0, 1.0]
    mine = picks[COMM.rank]
    contrib = np.zeros((wx.shape[0], 2))
    contrib[mine] = [COMM.rank + 1.0, 1.0]
    out = np.full((ma.num_dofs, 2), np.nan)
    nodes.add_to_owners(mine, contrib, out)
    n = ma.num_owned_dofs
    owned_whole = np.flatnonzero((nodes.local >= 0) & (nodes.local < n))
    assert np.array_equal(out[nodes.local[owned_whole]], sums[owned_whole])
    assert not out[n:].any()
    assert COMM.allreduce(owned_whole.size) == wx.shape[0]  # each node owned once


def test_particles_in_work_boxes_couple_as_serially(meshes):
    md, whole, Q, ma = meshes
    dem = DEM(DEMParams(stiffness=1000.0), walls=Walls.box([0, 0, 0], [LX, LY, LZ]))
    rng = np.random.default_rng(4)
    k = np.arange(1500)
    lattice = (np.stack([k % 15, (k // 15) % 15, k // 225], axis=1) + 0.7) * [1.25 * D, 1.25 * D, 4 * D]
    dem.add_particles(lattice + rng.uniform(-1e-4, 1e-4, (1500, 3)), D, 2500.0, vel=rng.normal(0, 0.1, (1500, 3)))
    dem.attach_exchange(BoxExchange(COMM, dim=3), distribute=True)
    dem.advance(200)  # particles move, collide and migrate between the boxes
    P = dem.particles
    n = P.n_owned
    c = OwnerCoupler.build(ma, md.mesh, Q, whole.mesh, 1.0, **LAW)
    assert c.locate(P.pos[:n].copy()).size == 0  # the whole mesh holds every particle
    vel, d, ones = P.vel[:n].copy(), np.full(n, D), np.ones(n)
    K, f_d, f_p, eps_p = c.forces(*fields(ma.x_dofs), vel, d, ones)
    nodal = c.project_to_gas(d, ones, K, vel, F_explicit=f_p)
    # some particles' cells are held by other ranks (the boxes do not follow the mesh's blocks)
    far = int(np.count_nonzero(c.nodes.local[c.touched()] < 0))
    assert COMM.size == 1 or COMM.allreduce(far) > 0
    # the serial reference: every particle on one process
    gid = np.concatenate(COMM.allgather(P.gid[:n].copy()))
    assert np.array_equal(np.sort(gid), np.arange(1500))  # each particle once
    o = np.argsort(gid)
    x_all = np.concatenate(COMM.allgather(P.pos[:n].copy()))[o]
    v_all = np.concatenate(COMM.allgather(vel))[o]
    ma1 = extract_mesh_arrays(whole.mesh)
    c1 = Coupler(ma1, **LAW)
    assert c1.locate(x_all).size == 0
    one = np.ones(1500)
    K1, fd1, fp1, eps1 = c1.forces(*fields(ma1.x_dofs), v_all, np.full(1500, D), one)
    nodal1 = c1.project_to_gas(np.full(1500, D), one, K1, v_all, F_explicit=fp1)
    mine = np.searchsorted(gid[o], P.gid[:n])
    for a, b in ((K, K1), (f_d, fd1), (f_p, fp1), (eps_p, eps1)):
        assert np.abs(a - b[mine]).max(initial=0.0) <= 1e-12 * np.abs(b).max()
    rows = match(ma1.x_dofs, ma.x_dofs)
    for name in ("alpha", "eps", "K", "Kv", "F"):  # owned and ghost nodes
        a, b = getattr(nodal, name), getattr(nodal1, name)[rows]
        assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max(), name
    assert nodal.clipped == nodal1.clipped
    assert nodal1.alpha.max() > 0.03  # particles everywhere: the fields are not trivially small
    assert np.allclose(c.gas_at_particles(*fields(ma.x_dofs))[1], eps_p, rtol=0, atol=1e-14)


def match(x_ref, x):
    """Row of x_ref at each row of x (the same nodes, coordinates rounded to 0.1 um)."""
    key = {tuple(r): i for i, r in enumerate(np.round(x_ref * 1e7).astype(np.int64).tolist())}
    return np.array([key[tuple(r)] for r in np.round(x * 1e7).astype(np.int64).tolist()])
