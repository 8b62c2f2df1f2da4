"""The Coupler on distributed particles: owned particles located in local cells, nodal sums over ranks.

Particles are distributed and moved by the DEM through the `ParticleExchange`; the serial reference projects the
same particles (gathered) on the same mesh held by one process. Run serially and under `mpirun -n 2`.
"""

from mpi4py import MPI

import numpy as np
import pytest

from febed.coupling.exchange import Coupler
from febed.coupling.mesh_arrays import extract_mesh_arrays
from febed.dem import DEM, DEMParams, Walls
from febed.parallel import ParticleExchange, cell_owners

pytestmark = pytest.mark.mpi
COMM = MPI.COMM_WORLD
LX, LY, LZ = 0.02, 0.02, 0.04
D = 1e-3


def box(comm):
    import dolfinx.mesh as dm

    return dm.create_box(comm, [[0, 0, 0], [LX, LY, LZ]], [4, 4, 8], dm.CellType.hexahedron)


def fields(ma):
    """Smooth nodal gas fields from the node coordinates: u (nd, 3), eps (nd,), grad p (nd, 3)."""
    x = ma.x_dofs
    u = np.stack([np.sin(100 * x[:, 2]), 0.3 * x[:, 0] / LX, 1.0 + np.cos(150 * x[:, 1])], axis=1)
    eps = 0.5 + 0.4 * x[:, 2] / LZ
    gradp = np.stack([x[:, 1] * 10, -x[:, 0] * 20, -9000.0 + 1e5 * x[:, 2]], axis=1)
    return u, eps, gradp


def coupled(ma, pos, vel):
    """Locate, interpolate + drag, project: K per particle and the nodal exchange."""
    c = Coupler(ma, "wen-yu", 1.2, 1.8e-5, filter_passes=1)
    missing = c.locate(pos)
    u, eps, gradp = fields(ma)
    n = pos.shape[0]
    d = np.full(n, D)
    ones = np.ones(n)
    K, f_d, f_p, _ = c.forces(u, eps, gradp, vel, d, ones)
    return missing, K, f_d + f_p, c.project_to_gas(d, ones, K, vel, F_explicit=f_p)


def node_keys(ma, rows):
    """Integer lattice keys of node coordinates (the box nodes sit on a regular lattice)."""
    h = np.array([LX / 4, LY / 4, LZ / 8])
    k = np.rint(ma.x_dofs[rows] / h).astype(np.int64)
    return (k[:, 0] * 100 + k[:, 1]) * 100 + k[:, 2]


def test_projection_and_interpolation_on_2_ranks_equal_serial():
    mesh = box(COMM)
    ma = extract_mesh_arrays(mesh)
    dem = DEM(DEMParams(stiffness=1000.0), walls=Walls.box([0, 0, 0], [LX, LY, LZ]))
    rng = np.random.default_rng(4)
    k = np.arange(1500)
    lattice = (np.stack([k % 15, (k // 15) % 15, k // 225], axis=1) + 0.7) * [1.25 * D, 1.25 * D, 5 * D]
    pos = lattice + rng.uniform(-1e-4, 1e-4, (1500, 3))  # layers through the whole box: on every rank
    dem.add_particles(pos, D, 2500.0, vel=rng.normal(0, 0.1, (1500, 3)))
    dem.attach_exchange(ParticleExchange(ma, cell_owners(mesh)), distribute=True)
    dem.advance(200)  # particles move, collide and migrate
    P = dem.particles
    n = P.n_owned
    assert COMM.allreduce(min(n, 1)) == COMM.size  # every rank has particles
    missing, K, f, nodal = coupled(ma, P.pos[:n].copy(), P.vel[:n].copy())
    assert missing.size == 0  # every owned particle lies in a local cell
    # serial reference: the gathered particles on the whole mesh on one process
    gid = np.concatenate(COMM.allgather(P.gid[:n].copy()))
    assert gid.size == 1500 and np.unique(gid).size == 1500
    o = np.argsort(gid)
    x_all = np.concatenate(COMM.allgather(P.pos[:n].copy()))[o]
    v_all = np.concatenate(COMM.allgather(P.vel[:n].copy()))[o]
    mesh1 = box(MPI.COMM_SELF)  # kept alive: its communicator is freed with it
    ma1 = extract_mesh_arrays(mesh1)
    _, K1, f1, nodal1 = coupled(ma1, x_all, v_all)
    # per particle (interpolation on the rank's local cells + drag law)
    mine = np.searchsorted(gid[o], P.gid[:n])
    assert np.abs(K - K1[mine]).max(initial=0.0) <= 1e-12 * np.abs(K1).max()
    assert np.abs(f - f1[mine]).max(initial=0.0) <= 1e-12 * np.abs(f1).max()
    # per node: owned and ghost nodes hold the serial sums
    serial = dict(zip(node_keys(ma1, np.arange(ma1.num_dofs)).tolist(), range(ma1.num_dofs), strict=True))
    rows = np.array([serial[q] for q in node_keys(ma, np.arange(ma.num_dofs)).tolist()])
    for name in ("alpha", "eps", "K", "Kv", "F"):
        a, b = getattr(nodal, name), getattr(nodal1, name)[rows]
        assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max(), name
    assert nodal.clipped == nodal1.clipped  # summed over ranks already
    assert nodal1.alpha.max() > 0.03  # particles everywhere: the fields are not trivially small


def particle_substeps(dem, coupler, gas, n_sub, dt, comm):
    """The coupled loop's particle half (febed/solver.py `advance_particles`) written for several ranks.

    Per-particle drag state lives in auxiliary arrays, which follow the rows through sorting and migration;
    the number of drag chunks is agreed over the ranks (every `advance` is collective).
    """
    P = dem.particles
    n = P.n_owned
    coupler.reset_cells(P.cell[:n].astype(np.int32))  # arrivals have cell -1: searched afresh
    assert coupler.locate(P.pos[:n]).size == 0
    P.cell[:n] = coupler.cell
    u, eps, gradp = gas
    d = P.diameter[:n]
    K, f_d, f_p, _ = coupler.forces(u, eps, gradp, P.vel[:n], d, np.ones(n))
    P.attach("drag_K", 1)[:n, 0] = K
    P.attach("drag_f", 3)[:n] = f_d + f_p
    P.attach("drag_v0", 3)[:n] = P.vel[:n]
    tau = float(np.min(P.mass[:n] / np.maximum(K, 1e-300))) if n else np.inf
    tau = comm.allreduce(tau, op=MPI.MIN)
    chunks = min(n_sub, max(1, int(np.ceil(dt / (0.1 * tau)))))
    h = dt / n_sub
    done = 0
    for k in range(chunks):
        steps = (n_sub * (k + 1)) // chunks - done
        n = P.n_owned
        f = P.aux("drag_f")[:n] + P.aux("drag_K")[:n] * (P.aux("drag_v0")[:n] - P.vel[:n])
        dem.advance(steps, h, f)
        done += steps
    return chunks


def project(dem, coupler, gas):
    """Locate the owned particles where they are now (walk from `cell`) and project them."""
    P = dem.particles
    n = P.n_owned
    coupler.reset_cells(P.cell[:n].astype(np.int32))
    assert coupler.locate(P.pos[:n]).size == 0
    d, ones = P.diameter[:n], np.ones(n)
    K = coupler.forces(*gas, P.vel[:n], d, ones)[0]
    return coupler.project_to_gas(d, ones, K, P.vel[:n])


def test_coupled_substeps_in_a_frozen_gas_on_2_ranks_match_serial():
    mesh = box(COMM)
    ma = extract_mesh_arrays(mesh)
    mesh1 = box(MPI.COMM_SELF)
    ma1 = extract_mesh_arrays(mesh1)

    def make():
        dem = DEM(DEMParams(stiffness=1000.0, restitution_pp=0.8), walls=Walls.box([0, 0, 0], [LX, LY, LZ]))
        rng = np.random.default_rng(9)
        k = np.arange(800)
        lattice = (np.stack([k % 10, (k // 10) % 10, k // 100], axis=1) + 0.8) * [1.8 * D, 1.8 * D, 4.5 * D]
        dem.add_particles(lattice + rng.uniform(-2e-4, 2e-4, (800, 3)), D, 2500.0, vel=rng.normal(0, 0.05, (800, 3)))
        return dem

    ref, par = make(), make()
    par.attach_exchange(ParticleExchange(ma, cell_owners(mesh)), distribute=True)
    c, c1 = Coupler(ma, "wen-yu", 1.2, 0.5), Coupler(ma1, "wen-yu", 1.2, 0.5)  # tau_p ~ 0.3 ms
    gas, gas1 = fields(ma), fields(ma1)
    for _ in range(4):  # gas steps of 20 DEM sub-steps
        chunks = particle_substeps(par, c, gas, 20, 20 * ref.dt, COMM)
        assert particle_substeps(ref, c1, gas1, 20, 20 * ref.dt, MPI.COMM_SELF) == chunks > 1
    P = par.particles
    n = P.n_owned
    gid = np.concatenate(COMM.allgather(P.gid[:n].copy()))
    x = np.concatenate(COMM.allgather(P.pos[:n].copy()))[np.argsort(gid)]
    assert np.array_equal(np.sort(gid), np.arange(800))
    xr = ref.particles.pos[np.argsort(ref.particles.gid)]
    assert np.abs(x - xr).max() <= 1e-9 * LZ
    assert np.abs(xr - make().particles.pos).max() > 0.1 * D  # the particles moved
    a, b = project(par, c, gas), project(ref, c1, gas1)
    serial = dict(zip(node_keys(ma1, np.arange(ma1.num_dofs)).tolist(), range(ma1.num_dofs), strict=True))
    rows = np.array([serial[q] for q in node_keys(ma, np.arange(ma.num_dofs)).tolist()])
    assert np.abs(a.alpha - b.alpha[rows]).max() <= 1e-9 * b.alpha.max()
    assert np.abs(a.K - b.K[rows]).max() <= 1e-9 * b.K.max()
