"""PCPM crush and merge on distributed particles (serially, under `mpirun -n 2`, and on 3, 4 and 8 ranks).

Groups packed in a box split into z slabs, with events forced near the other ranks' groups: the originals and
the momentum are conserved over all ranks, gids stay unique, and no group placed by an event overlaps any
other group (on any rank) beyond the tolerance — the other ranks' groups are obstacles, and the ranks take
turns at the partition, each once every `size` evaluations. The same with the groups owned by boxes of equal
work (`BoxExchange`), the events' energy measured as in a run (a collective rebuild after the events).
"""

from mpi4py import MPI

import numpy as np
import pytest

from febed.coarse.pcpm import NO_CRUSH, GroupDynamics
from febed.dem import DEM, DEMParams, Walls
from febed.dem.insertion import random_positions
from febed.parallel import BoxExchange, ParticleExchange, slab_partitioner

pytestmark = pytest.mark.mpi
COMM = MPI.COMM_WORLD
DO, RHO, L, TOL = 1e-3, 2500.0, 0.012, 0.05


def near_other_ranks(P, reach=3 * DO):
    """Owned groups within `reach` of a group owned by another rank (serially: of the plane z = L)."""
    n = P.n_owned
    if COMM.size == 1:
        return np.abs(P.pos[:n, 2] - L) < reach
    parts = COMM.allgather(P.pos[:n])
    others = np.concatenate([x for r, x in enumerate(parts) if r != COMM.rank])
    if n == 0 or others.size == 0:
        return np.zeros(n, bool)
    return np.linalg.norm(P.pos[:n, None] - others[None], axis=2).min(axis=1) < reach


def gathered(P):
    """gid, pos, diameter, n_orig, momentum of every rank's owned groups."""
    n = P.n_owned
    parts = COMM.allgather((P.gid[:n], P.pos[:n], P.diameter[:n], P.n_orig[:n], P.mass[:n, None] * P.vel[:n]))
    return [np.concatenate([p[k] for p in parts]) for k in range(5)]


@pytest.mark.parametrize(("min_group", "kind"), [(1.0, "cells"), (0.125, "cells"), (1.0, "work")])
def test_events_across_the_partition_conserve_and_do_not_overlap(min_group, kind):
    import dolfinx.mesh as dm

    lo, hi = np.zeros(3), np.array([L, L, 2 * L])  # the partition plane is z = L on 2 ranks
    mesh = dm.create_box(COMM, [lo, hi], [2, 2, 4], dm.CellType.hexahedron, dm.GhostMode.shared_facet,
                         slab_partitioner())  # fmt: skip
    dem = DEM(DEMParams(gravity=0.0, stiffness=800.0, contact_model="linear"), walls=Walls.box(lo, hi))
    rng = np.random.default_rng(11)
    pos = random_positions(150, lo, hi, 2.1 * DO, seed=2)  # the same on every rank, then distributed
    vel = np.array([0.2, 0.0, 0.0]) + 1e-4 * rng.normal(size=(150, 3))
    dem.add_particles(pos, 2 * DO, RHO, vel=vel, n_orig=8)
    dem.attach_exchange(ParticleExchange.from_mesh(mesh) if kind == "cells" else BoxExchange(COMM), distribute=True)
    gd = GroupDynamics(DO, RHO, 1.2, 1.8e-5, 0.45, overlap_tolerance=TOL, merge_tolerance=1.0, max_group=16,
                       min_group=min_group, measure_energy=kind == "work", conserve_energy=False,
                       seed=3 + COMM.rank)  # fmt: skip
    # divisible originals (min_group 1/8): crushes down to pieces of an original, counts in eighths
    # (the energy rule is tested serially in test_pcpm_energy.py; here events near the partition are wanted)
    P = dem.particles
    gid0, _, _, n0, p0 = gathered(P)
    crushed = merged = near = 0
    turns = max(COMM.size, 2)  # a group near another rank's takes part only on its rank's turn
    for k in range(12 * turns):
        dem.advance(2, dem.dt)  # refreshes the ghosts
        old = set(P.gid[: P.n_owned].tolist())
        p_before = gathered(P)[4].sum(axis=0)  # the walls change the momentum between evaluations, events do not
        n = P.n_owned
        at_plane = near_other_ranks(P)
        crush = (k // turns) % 2 == 0  # crush evaluations, then merge ones: each rank has a turn of each
        want = at_plane & (P.n_orig[:n] > min_group) if crush else np.zeros(n, bool)
        d_cl = 1.3 * DO if min_group == 1.0 else 0.6 * P.diameter[:n]
        s = gd.apply(dem, np.where(want, d_cl, NO_CRUSH if crush else 10 * DO))
        crushed += COMM.allreduce(s.crushed)
        merged += COMM.allreduce(s.merged)
        n = P.n_owned
        new = np.array([P.gid[i] not in old for i in range(n)], dtype=bool)
        near += COMM.allreduce(int(np.sum(new & near_other_ranks(P))))
        gid, x, d, no, mom = gathered(P)
        is_new = np.concatenate(COMM.allgather(new))
        assert np.unique(gid).size == gid.size  # no gid lost or duplicated
        assert no.sum() == n0.sum()  # originals, exactly
        assert np.allclose(mom.sum(axis=0), p_before, rtol=0, atol=1e-12 * np.abs(p0.sum(axis=0)).max())
        rows = np.flatnonzero(is_new)
        if rows.size:
            r = 0.5 * d
            dist = np.linalg.norm(x[rows][:, None] - x[None], axis=2)
            dist[np.arange(rows.size), rows] = np.inf
            worst = ((r[rows][:, None] + r[None] - dist) / (2 * np.minimum(r[rows][:, None], r[None]))).max()
            assert worst <= TOL + 1e-12, f"evaluation {k}: a new group overlaps another by {worst:.3f} of a diameter"
    assert crushed > 10 and merged > 5 and near > 10
    if min_group < 1.0:  # pieces of originals were made, on both sides of the partition
        assert gathered(P)[3].min() < 1.0
    assert gid0.size == 150
