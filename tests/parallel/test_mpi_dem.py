"""Distributed particles against the serial DEM (run serially and under `mpirun -n K`, any K).

The mesh is a box split into slabs across z (`slab_partitioner`): on 2 ranks the partition boundary is the plane
z = H/2, so the cases below put contacts and crossings exactly there; on more ranks there are more boundaries,
not all of them planes (a slab is a block of cell indices). The serial reference is the same DEM without an
exchange (the compiled multi-step loop), run on every rank. `test_many_ranks.py` cuts the box into blocks
meeting at corners. The tests marked with `kind` also run with the particles owned by work-balanced boxes
(`BoxExchange`, cut again at every rebuild) instead of the mesh slabs.
"""

from mpi4py import MPI

import numpy as np
import pytest

from febed.dem import DEM, DEMParams, Walls
from febed.parallel import BoxExchange, ParticleExchange, slab_partitioner

pytestmark = pytest.mark.mpi
COMM = MPI.COMM_WORLD
D, RHO = 1e-3, 2500.0


def box_exchange(lo, hi, cells, kind="cells"):
    """An exchange over a hexahedral box mesh cut into z slabs (one per rank), or by boxes of the particles' work."""
    import dolfinx.mesh as dm

    if kind == "work":
        return BoxExchange(COMM)

    mesh = dm.create_box(COMM, [lo, hi], cells, dm.CellType.hexahedron, dm.GhostMode.shared_facet, slab_partitioner())
    return ParticleExchange.from_mesh(mesh)


def gathered(dem):
    """gid, pos, vel, omega of every rank's owned particles, sorted by gid."""
    P = dem.particles
    n = P.n_owned
    parts = COMM.allgather((P.gid[:n].copy(), P.pos[:n].copy(), P.vel[:n].copy(), P.omega[:n].copy()))
    gid = np.concatenate([p[0] for p in parts])
    o = np.argsort(gid)
    return gid[o], *(np.concatenate([p[k] for p in parts])[o] for k in (1, 2, 3))


@pytest.mark.parametrize("kind", ["cells", "work"])
@pytest.mark.parametrize("integrator", ["rk2", "verlet"])
def test_two_particles_colliding_across_the_partition_follow_the_serial_trajectory(integrator, kind):
    L = 0.01  # box L x L x 2L: the partition plane is z = L on 2 ranks (work: between the two particles)
    ex = box_exchange([0, 0, 0], [L, L, 2 * L], [2, 2, 4], kind)

    def make():
        p = DEMParams(contact_model="linear-history", stiffness=1000.0, restitution_pp=0.7, friction_pp=0.3,
                      integrator=integrator)  # fmt: skip
        dem = DEM(p)
        pos = [[L / 2, L / 2, L - 0.6 * D], [L / 2 + 0.3 * D, L / 2 - 0.1 * D, L + 0.6 * D]]
        vel = [[0.0, 0.05, 0.3], [0.02, 0.0, -0.3]]  # oblique impact with spin: sliding, history, rotation
        dem.add_particles(np.array(pos), D, RHO, vel=np.array(vel), omega=np.array([[0, 0, 50.0], [10.0, 0, 0]]))
        return dem

    ref, par = make(), make()
    par.attach_exchange(ex, distribute=True)
    if COMM.size > 1:
        assert COMM.allreduce(par.particles.n_owned, op=MPI.MAX) == 1  # on two ranks, one on each side
    z0 = ref.particles.pos[:, 2].copy()
    for _ in range(30):
        ref.advance(20, ref.dt)
        par.advance(20, ref.dt)
    gid, x, v, w = gathered(par)
    assert np.array_equal(gid, [0, 1])
    assert np.all(np.diff(ref.particles.pos[:, 2]) > 0) and ref.particles.vel[0, 2] < 0 < ref.particles.vel[1, 2]
    assert ref.particles.pos[0, 2] < z0[0] and ref.particles.pos[1, 2] > z0[1]  # they bounced off each other
    print(f"two particles {integrator}: deviation {np.abs(x - ref.particles.pos).max() / L:.1e} L")
    assert np.abs(x - ref.particles.pos).max() <= 1e-12 * L
    assert np.abs(v - ref.particles.vel).max() <= 1e-12 * 0.3
    assert np.abs(w - ref.particles.omega).max() <= 1e-12 * 50.0


def settling(integrator, rotation=True):
    """2,000 spheres on a jittered lattice with random velocities in a walled box, 2 (x) by 2 (z) mesh slabs."""
    W, H = 14 * D, 14 * D  # the bed fills the box: the partition plane z = H/2 cuts it in the middle
    p = DEMParams(contact_model="linear-history", stiffness=1000.0, restitution_pp=0.5, restitution_pw=0.5,
                  friction_pp=0.3, friction_pw=0.3, integrator=integrator, rotation=rotation)  # fmt: skip
    dem = DEM(p, walls=Walls.box([0, 0, 0], [W, W, H]))
    rng = np.random.default_rng(5)
    k = np.arange(2000)
    idx = np.stack([k % 13, (k // 13) % 13, k // 169], axis=1)
    pos = (idx + 0.5) * (1.05 * D) + 0.3 * D + rng.uniform(-0.02, 0.02, (2000, 3)) * D
    dem.add_particles(pos, D, RHO, vel=rng.normal(0, 0.05, (2000, 3)))
    return dem, (W, H)


@pytest.mark.parametrize(
    "integrator,rotation,kind",
    [("rk2", True, "cells"), ("verlet", True, "cells"), ("verlet", False, "cells"), ("rk2", True, "work")],
)
def test_2000_spheres_settling_on_2_ranks_match_serial(integrator, rotation, kind):
    """Without rotation the ghost updates leave omega out (6 numbers per ghost, not 9): same check."""
    ref, (W, H) = settling(integrator, rotation)
    par, _ = settling(integrator, rotation)
    ex = box_exchange([0, 0, 0], [W, W, H], [3, 3, 4], kind)
    par.attach_exchange(ex, distribute=True)
    dt = ref.dt
    ref.advance(500, dt)
    for _ in range(5):
        par.advance(100, dt)
    gid, x, v, _ = gathered(par)
    assert gid.size == 2000 and np.array_equal(gid, np.arange(2000))  # none lost, none duplicated
    o = np.argsort(ref.particles.gid)  # the serial rows are sorted by linked cell
    rel = np.abs(x - ref.particles.pos[o]).max() / np.abs(ref.particles.pos).max()
    print(f"settling {integrator}: max position deviation {rel:.1e} relative, {COMM.allreduce(ex.migrated)} migrations")
    assert rel <= 1e-9, rel
    assert np.abs(v - ref.particles.vel[o]).max() <= 1e-7 * np.abs(ref.particles.vel).max()
    if COMM.size > 1:
        assert COMM.allreduce(par.particles.n_ghost) > 100  # contacts really crossed the partition
        assert ex.migrated + COMM.allreduce(ex.migrated) > 0  # and particles changed rank
    assert ref.max_overlap > 0.001 and abs(COMM.allreduce(par.max_overlap, op=MPI.MAX) - ref.max_overlap) < 1e-9


@pytest.mark.parametrize("kind", ["cells", "work"])
def test_migration_stress_none_lost_or_duplicated_momentum_conserved(kind):
    """A colliding cloud shaken up and down through the partition plane by a square-wave force, 3 periods.

    With work-balanced boxes the cut moves with the cloud at every rebuild: the particles change rank where
    the cloud's collisions stir it across the cut, not where it crosses the plane z = L.
    """
    L = 0.012
    ex = box_exchange([0, 0, 0], [L, L, 2 * L], [3, 3, 6], kind)
    p = DEMParams(
        contact_model="linear-history", stiffness=200.0, restitution_pp=0.8, friction_pp=0.3, gravity=0.0, skin=0.5
    )
    dem = DEM(p)
    rng = np.random.default_rng(2)
    centre = np.array([L / 2, L / 2, L])
    k = np.arange(216)
    pos = centre + (np.stack([k % 6, (k // 6) % 6, k // 36], axis=1) - 2.5) * 1.1 * D
    acc, period, chunk = 700.0, 0.015, 20  # amplitude acc period^2 / 32 = 5 mm about the plane, peak speed 2.6 m/s
    vel = rng.normal(0, 0.05, (216, 3))  # a granular gas: collisions, sliding, history across the plane
    vel[:, 2] -= acc * period / 4
    dem.add_particles(pos, D, RHO, vel=vel)
    dem.attach_exchange(ex, distribute=True)
    m = RHO * np.pi / 6 * D**3
    P = dem.particles
    assert np.all(P.mass[: P.n_owned] == m)  # a rank may hold none of the cloud (3 ranks or more)
    dt = dem.dt
    impulse = np.zeros(3)
    crossings = changes = 0
    below = holder = None
    for c in range(int(3 * period / (chunk * dt))):
        n = P.n_owned
        f = np.zeros((n, 3))
        f[:, :2] = -m * 2000.0 * (P.pos[:n, :2] - centre[:2])  # a weak lateral spring keeps the cloud in the box
        f[:, 2] = m * acc * (1.0 if (c * chunk * dt) % period < 0.5 * period else -1.0)
        impulse += COMM.allreduce(f.sum(axis=0)) * chunk * dt
        dem.advance(chunk, dt, f)
        n = P.n_owned
        gids = np.concatenate(COMM.allgather(P.gid[:n].copy()))
        assert gids.size == 216 and np.unique(gids).size == 216, "particles lost or duplicated"
        order = np.argsort(gids)
        now = np.concatenate(COMM.allgather(P.pos[:n, 2] < L))[order]
        rank_now = np.concatenate(COMM.allgather(np.full(n, COMM.rank)))[order]
        crossings += int(np.sum(now != below)) if below is not None else 0
        changes += int(np.sum(rank_now != holder)) if holder is not None else 0
        below, holder = now, rank_now
    mom = COMM.allreduce((P.mass[: P.n_owned, None] * P.vel[: P.n_owned]).sum(axis=0))
    err = np.abs(mom - (m * vel.sum(axis=0) + impulse)).max() / (216 * m * 2.6)
    moved = COMM.allreduce(ex.migrated)
    print(f"migration stress: {crossings} crossings, {changes} changes of rank, {moved} migrations, "
          f"momentum error {err:.1e}")  # fmt: skip
    assert err <= 1e-12
    assert crossings > 600, crossings  # the particles crossed the mid-plane 3 times each on average
    assert moved >= changes  # each change of rank between two chunks took at least one migration
    if COMM.size > 1 and kind == "cells":
        assert changes > 200, changes  # the partition planes (z = L on 2 ranks, 2L/3 and 4L/3 on 3) were crossed
    if COMM.size == 2 and kind == "cells":
        assert moved > 0.5 * crossings  # crossings are migrations (counted at rebuilds)
    if COMM.size > 1 and kind == "work":
        assert changes > 20, changes  # particles did change rank


@pytest.mark.parametrize("kind", ["cells", "work"])
def test_checkpoint_of_a_distributed_run_restarts_on_any_rank_count(kind):
    from febed.parallel.state import gather_state

    par, (W, H) = settling("rk2")
    ex = box_exchange([0, 0, 0], [W, W, H], [3, 3, 4], kind)
    par.attach_exchange(ex, distribute=True)
    dt = par.dt
    par.advance(300, dt)
    state = COMM.bcast(gather_state(par), root=0)
    assert state["p_gid"].size == 2000 and np.array_equal(state["p_gid"], np.arange(2000))
    assert state["saved_keys"].size > 20  # sliding contacts: the history matters
    serial, _ = settling("rk2")  # a fresh DEM (same parameters and walls) on this rank alone
    serial.set_state(state)
    again, _ = settling("rk2")  # and one distributed afresh
    again.set_state(state)
    again.attach_exchange(ex, distribute=True)
    for dem in (par, serial, again):
        dem.advance(300, dt)
    gid, x, _, _ = gathered(par)
    gid2, x2, _, _ = gathered(again)
    o = np.argsort(serial.particles.gid)
    assert np.array_equal(gid, serial.particles.gid[o]) and np.array_equal(gid, gid2)
    scale = np.abs(x).max()
    assert np.abs(x - serial.particles.pos[o]).max() <= 1e-9 * scale
    assert np.abs(x - x2).max() <= 1e-9 * scale
    assert serial.time == par.time and serial.steps == par.steps == 600


def test_2d_bed_on_2_ranks_matches_serial():
    """Spheres moving in the x-y plane (2D mode) on a quadrilateral mesh cut into slabs (at x = W/2 on 2 ranks)."""
    import dolfinx.mesh as dm

    W, H = 20 * D, 20 * D
    mesh = dm.create_rectangle(COMM, [[0, 0], [W, H]], [4, 4], dm.CellType.quadrilateral, dm.GhostMode.shared_facet,
                               slab_partitioner())  # fmt: skip
    ex = ParticleExchange.from_mesh(mesh)

    def make():
        p = DEMParams(dim=2, contact_model="linear-history", stiffness=1000.0, restitution_pp=0.6, friction_pp=0.3)
        dem = DEM(p, walls=Walls.box([0, 0, -D], [W, H, D], dim=2))
        rng = np.random.default_rng(1)
        k = np.arange(300)
        pos = np.zeros((300, 3))
        pos[:, 0] = (k % 17 + 0.8) * 1.1 * D + rng.uniform(-0.03, 0.03, 300) * D
        pos[:, 1] = (k // 17 + 0.8) * 1.05 * D
        vel = np.zeros((300, 3))
        vel[:, :2] = rng.normal(0, 0.05, (300, 2))
        dem.add_particles(pos, D, RHO, vel=vel)
        return dem

    ref, par = make(), make()
    par.attach_exchange(ex, distribute=True)
    dt = ref.dt
    ref.advance(600, dt)
    for _ in range(3):
        par.advance(200, dt)
    gid, x, _, w = gathered(par)
    o = np.argsort(ref.particles.gid)
    assert np.array_equal(gid, np.arange(300))
    assert np.abs(x - ref.particles.pos[o]).max() <= 1e-9 * H
    assert np.all(x[:, 2] == 0.0) and np.all(w[:, :2] == 0.0)


def test_particles_inserted_anywhere_go_to_their_owners():
    """Each rank inserts particles all over the box (far outside its part too): the first step sends them home."""
    L = 0.012
    ex = box_exchange([0, 0, 0], [L, L, 4 * L], [3, 3, 8])
    dem = DEM(DEMParams(gravity=0.0))
    dem.attach_exchange(ex)
    rng = np.random.default_rng(COMM.rank)
    z = (np.arange(40) + 0.5) / 40 * 4 * L
    pos = np.stack([rng.uniform(D, L - D, 40), rng.uniform(D, L - D, 40), z], axis=1)
    gids = dem.add_particles(pos, D, RHO)
    dem.advance(1)
    P = dem.particles
    n = P.n_owned
    everyone = np.concatenate(COMM.allgather(gids))
    held = np.concatenate(COMM.allgather(P.gid[:n].copy()))
    assert np.array_equal(np.sort(held), np.sort(everyone)) and np.unique(held).size == 40 * COMM.size
    assert np.all(ex.claim(P.pos[:n]) == COMM.rank)  # each particle sits in a cell of its rank


@pytest.mark.parametrize("kind", ["cells", "work"])
def test_elastic_energy_counts_every_contact_once_after_rows_moved_to_their_owners(kind):
    """Overlapping pairs all along the box, inserted unevenly by the ranks (most in other ranks' parts): the
    energy rebuilds the lists first, which moves rows to their owners and changes each rank's count; it is then
    0.5 k δ² for every pair once, whichever rank holds each side."""
    L, k_n, npairs = 0.012, 1000.0, 40
    ex = box_exchange([0, 0, 0], [L, L, 4 * L], [3, 3, 8], kind)
    dem = DEM(DEMParams(gravity=0.0, stiffness=k_n))
    dem.attach_exchange(ex)
    k = np.arange(npairs)
    inserter = np.where(k % 3 == 0, 0, 1 + k % max(COMM.size - 1, 1)) % COMM.size
    z = (k[inserter == COMM.rank] + 0.5) / npairs * 4 * L  # pairs 1.2 D apart in z: only the pairs touch
    a = np.stack([np.full_like(z, L / 2 - 0.475 * D), np.full_like(z, L / 2), z], axis=1)
    dem.add_particles(np.concatenate([a, a + [0.95 * D, 0.0, 0.0]]), D, RHO)  # overlaps of 0.05 D
    e = dem.elastic_energy()
    assert e == pytest.approx(npairs * 0.5 * k_n * (0.05 * D) ** 2, rel=1e-9)
    assert COMM.allreduce(dem.particles.n_owned) == 2 * npairs


@pytest.mark.mpi
def test_balance_line_reports_particles_and_pairs_per_rank():
    """The log's balance line: both counts gathered in rank order, max/mean of each, the same line on every rank."""
    from febed.parallel.exchange import balance_line

    comm = MPI.COMM_WORLD
    r, n = comm.rank, comm.size
    line = balance_line(comm, 10 * (r + 1), 100 * (r + 1) ** 2)
    owned, pairs = [10 * (k + 1) for k in range(n)], [100 * (k + 1) ** 2 for k in range(n)]
    expect = (
        f"particles per rank {owned}: load imbalance max/mean = {max(owned) / np.mean(owned):.3f}; "
        f"listed pairs per rank {pairs}: max/mean = {max(pairs) / np.mean(pairs):.3f} (the DEM's work)"
    )
    assert line == expect and comm.allgather(line) == [line] * n
    if n == 2:
        assert "max/mean = 1.333" in line and "max/mean = 1.600" in line
    empty = balance_line(comm, 0, 0)  # an empty bed, or before the first step: balanced, not NaN; no pairs yet
    assert empty.endswith("load imbalance max/mean = 1.000") and "pairs" not in empty
