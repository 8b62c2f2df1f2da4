"""Particles owned by work-balanced boxes instead of the mesh partition (pure-DEM runs, `[run] particle_partition`).

`BoxExchange` is a `ParticleExchange` whose owner rule is the rank's box of a weighted recursive coordinate
bisection of the particles (`febed.parallel.boxes`). At every migration (every pair-list rebuild) the
weight each box holds is summed, and the boxes are cut afresh when the heaviest exceeds the mean by more
than `RECUT_IMBALANCE` (a threshold as in LAMMPS' `fix balance`): the DEM's work stays balanced as the bed
moves, without moving particles back and forth across a cut that shifts a little at every rebuild.

A particle weighs 1 + half its listed pairs (the DEM passes them from its last lists; the force loop's
work is one evaluation per listed pair), so a dense bed's particles weigh more than a dilute region's;
without lists (the first migration after a restart) 1 + its contacts that carry tangential history. Ghosts
are the particles within the halo reach of another rank's box. Migration, ghost updates and reductions are
the base class's.

It needs no mesh. It shares the particles of pure-DEM runs by default and of coupled runs with
`particle_partition = "work"`, whose particles are then coupled on their own ranks over the whole mesh
(`febed.coupling.owners`; docs/scaling.md).
"""

from __future__ import annotations

import time

from mpi4py import MPI

import numpy as np

from febed.parallel.boxes import BoxTree, bisect, box_ghost_targets
from febed.parallel.exchange import _MASK31, ParticleExchange

RECUT_IMBALANCE = 1.05  # cut the boxes afresh when the heaviest holds more than this times the mean weight


class BoxExchange(ParticleExchange):
    """Particle decomposition by weighted recursive bisection boxes (see the module docstring).

    Attributes:
        tree: the current bisection (`BoxTree`; `tree.boxes` the ranks' boxes); cuts: bisections made;
        imbalance: the heaviest box's weight over the mean at the last migration, before any new cut.
        Others as `ParticleExchange` (timers gain "partition", the seconds spent cutting).
    """

    balances_work = True

    def __init__(self, comm, dim: int = 3):
        """An exchange over `comm` for particles in `dim` dimensions (the cut axes: x, y[, z])."""
        if dim not in (2, 3):
            raise ValueError(f"dim: 2 or 3, got {dim!r}")
        self.ma = None
        self.mesh = None
        self.table = None
        self._setup(comm)
        self.dim = dim
        self.timers["partition"] = 0.0
        self.cuts = 0
        self.imbalance = 1.0
        self.tree: BoxTree = bisect(self.comm, np.zeros((0, 3)), dim=dim)

    def repartition(self, pos: np.ndarray, weights: np.ndarray | None = None) -> None:
        """Cut the boxes afresh for this rank's points pos (n, 3) and every other rank's (collective)."""
        t0 = time.perf_counter()
        self.tree = bisect(self.comm, pos, weights, self.dim)
        self.cuts += 1
        self.timers["partition"] += time.perf_counter() - t0

    def contact_weights(self, particles, saved) -> np.ndarray:
        """1 + the number of history-carrying contacts of each owned particle, from the pair keys `saved`."""
        P = particles
        n = P.n_owned
        w = np.ones(n)
        if saved is None or saved[0].size == 0 or n == 0:
            return w
        keys = saved[0]
        gids, counts = np.unique(np.concatenate([keys >> 31, keys & _MASK31]), return_counts=True)
        at = np.minimum(np.searchsorted(gids, P.gid[:n]), gids.size - 1)
        hit = gids[at] == P.gid[:n]
        w[hit] += counts[at[hit]]
        return w

    # ------------------------------------------------------------------------------------ ownership
    def owners(self, particles) -> np.ndarray:
        """Destination rank of each owned particle: the box holding it."""
        return self.tree.owner(particles.pos[: particles.n_owned])

    def _claim_all(self, pos: np.ndarray) -> np.ndarray:
        return self.tree.owner(pos)

    def claim(self, pos: np.ndarray) -> np.ndarray:
        """Owner rank of each point of pos (k, 3) (no communication: every rank knows the boxes)."""
        return self.tree.owner(np.asarray(pos, dtype=np.float64).reshape(-1, 3))

    def distribute(self, particles) -> None:
        """Cut boxes for a particle set every rank holds identically, then keep this rank's (collective)."""
        if self.size > 1:  # each particle counted once; the base class checks that every rank holds them all
            self.repartition(particles.pos[self.rank : particles.n_owned : self.size])
        super().distribute(particles)

    def migrate(self, particles, saved=None, wsaved=None, work=None):
        """Cut the boxes afresh if their weights are out of balance, then migrate (collective).

        work: each owned particle's weight (1 + half its listed pairs), or None: from the saved contacts.
        """
        if self.size > 1:
            pos = particles.pos[: particles.n_owned]
            w = self.contact_weights(particles, saved) if work is None else np.asarray(work, dtype=np.float64)
            t0 = time.perf_counter()
            held = np.bincount(self.tree.owner(pos), weights=w, minlength=self.size).astype(np.float64)
            self.comm.Allreduce(MPI.IN_PLACE, held, op=MPI.SUM)
            self.timers["partition"] += time.perf_counter() - t0
            mean = held.sum() / self.size
            self.imbalance = float(held.max() / mean) if mean > 0 else 1.0
            if self.imbalance > RECUT_IMBALANCE:
                self.repartition(pos, w)
        return super().migrate(particles, saved, wsaved, work)

    # ------------------------------------------------------------------------------------ ghosts
    def _ghost_targets(self, pos: np.ndarray, n: int, reach: float):
        b = self.tree.boxes
        start, rows = box_ghost_targets(pos[:n], n, np.ascontiguousarray(b[:, 0]), np.ascontiguousarray(b[:, 1]),
                                        self.rank, float(reach))  # fmt: skip
        self.strays = 0
        return start, rows
