"""The one interface through which the DEM meets MPI: ownership, migration, ghost particles, reductions.

Ownership (seed 001 sec 2.5): a particle belongs to the rank owning the mesh cell that holds its centre.
At every pair-list rebuild (collective; the coupled solver also forces one when a particle has left its
rank's owned and ghost cells, e.g. diagonally across a corner of the partition boundary) the DEM calls, in
this order:

1. `migrate(particles, saved, wsaved)`: each owned particle is located (walk from `particles.cell`,
   `febed.coupling.locate`); FOUND in a ghost cell -> that cell's owner; OUTSIDE_LOCAL (further than the ghost
   layer, rare) -> resolved by asking every rank; OUTSIDE_DOMAIN -> stays (e.g. between an outlet and the
   box where the driver removes it). Leaving particles go with every field, their auxiliary arrays
   (`Particles.attach`, e.g. the external force) and the contact history of their pairs and walls, keyed by
   gid pairs; the receiver merges it with its own (a pair across the partition is integrated by both
   owners identically, so either copy is right).
2. `refresh_ghosts(particles, reach)`: copies of the owned particles within the halo `reach` (>= largest
   diameter + skin) of other ranks' owned cells go to those ranks (`febed.parallel.halo.HaloTable`); they
   become the ghost rows, which the pair list sees and the integrators skip.

Between rebuilds `update_ghosts(particles, vel, omega)` refreshes the ghosts' positions and velocities at every
force evaluation (each RK2 stage, each Verlet step) with non-blocking point-to-point messages, so the two
owners of a contact across the partition compute the same pair force.
"""

from __future__ import annotations

import time

from mpi4py import MPI

import numpy as np
from numba import njit

from febed.coupling.locate import FOUND, OUTSIDE_LOCAL, locate
from febed.coupling.mesh_arrays import extract_mesh_arrays
from febed.dem.particles import GID_LIMIT
from febed.parallel.halo import HaloTable
from febed.parallel.partition import cell_owners

_GHOST_FLOATS = ("pos", "vel", "omega", "diameter", "mass", "inertia", "n_orig")
_GHOST_INTS = ("gid", "material")
_MASK31 = (1 << 31) - 1


@njit(cache=True)
def _pack(rows, pos, vel, omega, spin, buf):
    """buf[k] = (pos, vel[, omega]) of row rows[k]: one ghost-update message (omega only if `spin`)."""
    for k in range(rows.size):
        i = rows[k]
        for a in range(3):
            buf[k, a] = pos[i, a]
            buf[k, 3 + a] = vel[i, a]
            if spin:
                buf[k, 6 + a] = omega[i, a]


@njit(cache=True)
def _unpack(first, buf, pos, vel, omega, spin):
    """Rows first + k get buf[k]'s pos, vel and omega (zero without `spin`: particles that never rotate)."""
    for k in range(buf.shape[0]):
        i = first + k
        for a in range(3):
            pos[i, a] = buf[k, a]
            vel[i, a] = buf[k, 3 + a]
            omega[i, a] = buf[k, 6 + a] if spin else 0.0


def _split_by_gid(keys: np.ndarray, gid_sets: dict[int, np.ndarray], pair: bool) -> dict[int, np.ndarray]:
    """Rows of `keys` (pair keys gi << 31 | gj, or wall keys gid << 31 | wall) involving each rank's gids."""
    a = keys >> 31
    b = keys & _MASK31
    out = {}
    for r, g in gid_sets.items():
        hit = np.isin(a, g)
        if pair:
            hit |= np.isin(b, g)
        out[r] = np.flatnonzero(hit)
    return out


def _merge(keys: np.ndarray, vals: np.ndarray, more: list[tuple[np.ndarray, np.ndarray]]):
    """Sorted unique keys with their values; on duplicates the first source (this rank's) wins."""
    if not more:
        return keys, vals
    k = np.concatenate([keys] + [m[0] for m in more])
    v = np.concatenate([vals.reshape(-1, 3)] + [m[1].reshape(-1, 3) for m in more])
    order = np.argsort(k, kind="stable")
    k, v = k[order], v[order]
    first = np.ones(k.size, dtype=bool)
    first[1:] = k[1:] != k[:-1]
    return k[first], v[first]


class ParticleExchange:
    """Particle decomposition over the mesh partition of `ma` (see the module docstring).

    `balances_work` (False): whether `migrate` uses the particles' work (the DEM computes it only then).

    Attributes:
        comm: the mesh communicator; rank, size: its rank and size.
        timers: wall seconds in "migrate", "ghosts" (refresh), "update" (per-stage ghost updates),
            "reduce" (collective reductions of the stepping).
        migrated: particles sent away so far; strays: owned particles last found outside the halo region.
    """

    balances_work = False

    def __init__(self, ma, cell_owner: np.ndarray):
        """Set up for mesh arrays `ma` (`extract_mesh_arrays`) and the owner rank of each local cell."""
        cell_owner = np.asarray(cell_owner, dtype=np.int32)
        if cell_owner.shape != (ma.num_cells,):
            raise ValueError(f"cell_owner: must have one rank per local cell ({ma.num_cells},), got {cell_owner.shape}")
        self.ma = ma
        self.mesh = None  # keeps a mesh made by `from_mesh` (and its communicator) alive
        self._setup(ma.comm if ma.comm is not None else MPI.COMM_SELF)
        self.cell_owner = cell_owner
        self.table: HaloTable | None = None

    def _setup(self, comm) -> None:
        """The communication state every decomposition shares (a duplicate of `comm`: no tag clashes)."""
        self.comm = comm.Dup()
        self.rank = self.comm.rank
        self.size = self.comm.size
        self.timers = {"migrate": 0.0, "ghosts": 0.0, "update": 0.0, "reduce": 0.0}
        self.migrated = 0
        self.strays = 0
        self._send_start = np.zeros(self.size + 1, dtype=np.int64)
        self._send_rows = np.zeros(0, dtype=np.int64)
        self._recv_start = np.zeros(self.size + 1, dtype=np.int64)

    @classmethod
    def from_mesh(cls, mesh, Q=None, depth: float = 1.0) -> ParticleExchange:
        """The exchange of a DOLFINx mesh (collective: extracts the coupling's mesh arrays)."""
        ex = cls(extract_mesh_arrays(mesh, Q, depth=depth), cell_owners(mesh))
        ex.mesh = mesh
        return ex

    # ------------------------------------------------------------------------------------ reductions
    def _reduce(self, x, op):
        t = time.perf_counter()
        out = self.comm.allreduce(x, op=op)
        self.timers["reduce"] += time.perf_counter() - t
        return out

    def any(self, flag: bool) -> bool:
        """True on every rank if `flag` is True on any rank."""
        return bool(self._reduce(bool(flag), MPI.LOR))

    def max(self, x: float) -> float:
        """Maximum of x over the ranks."""
        return self._reduce(x, MPI.MAX)

    def min(self, x: float) -> float:
        """Minimum of x over the ranks."""
        return self._reduce(x, MPI.MIN)

    def sum(self, x):
        """Sum of x over the ranks."""
        return self._reduce(x, MPI.SUM)

    def concat(self, a: np.ndarray) -> np.ndarray:
        """The arrays of every rank concatenated in rank order (allgather)."""
        return np.concatenate(self.comm.allgather(np.asarray(a)))

    # ------------------------------------------------------------------------------------ ownership
    def _locate(self, pos: np.ndarray, cell: np.ndarray):
        c = np.ascontiguousarray(cell, dtype=np.int32)
        _, _, status, _, _ = locate(self.ma, np.ascontiguousarray(pos, dtype=np.float64), c)
        return c, status

    def owners(self, particles) -> np.ndarray:
        """Destination rank of each owned particle (collective); updates `particles.cell` where found."""
        P = particles
        n = P.n_owned
        cell, status = self._locate(P.pos[:n], P.cell[:n])
        dest = np.full(n, self.rank, dtype=np.int64)
        found = status == FOUND
        dest[found] = self.cell_owner[cell[found]]
        P.cell[:n] = np.where(found, cell, -1)
        lost = np.flatnonzero(status == OUTSIDE_LOCAL)
        if self.size > 1 and self._reduce(int(lost.size), MPI.SUM):
            claim = self.claim(P.pos[lost])
            dest[lost] = np.where(claim >= 0, claim, self.rank)
        return dest

    def _claim_all(self, pos: np.ndarray) -> np.ndarray:
        """Owner rank of points `pos` (k, 3) that every rank holds alike (collective; -1 outside the mesh)."""
        cell, status = self._locate(pos, np.full(pos.shape[0], -1, dtype=np.int32))
        mine = (status == FOUND) & (cell >= 0)
        mine[mine] = cell[mine] < self.ma.num_owned_cells
        big = np.iinfo(np.int64).max
        c = np.where(mine, self.rank, big).astype(np.int64)
        out = np.empty_like(c)
        self.comm.Allreduce(c, out, op=MPI.MIN)  # a point on a partition boundary goes to the lowest rank
        return np.where(out == big, -1, out)

    def claim(self, pos: np.ndarray) -> np.ndarray:
        """Owner rank of each point of this rank's `pos` (k, 3) (collective, every rank asks; -1 outside the mesh)."""
        pos = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
        counts = self.comm.allgather(pos.shape[0])
        out = self._claim_all(self.concat(pos))
        off = int(np.sum(counts[: self.rank]))
        return out[off : off + counts[self.rank]]

    def distribute(self, particles) -> None:
        """Keep only this rank's share of a particle set every rank holds identically (start of a run).

        Particles outside every rank's cells stay with rank 0. Gids stay; `next_gid` is offset per rank so that
        particles inserted later get globally unique gids.
        """
        P = particles
        n = P.n_owned
        P.n_ghost = 0
        if len(set(self.comm.allgather(n))) > 1:
            raise ValueError("particles: distribute needs the same particles on every rank (use attach_exchange "
                             "without distribute for particles each rank inserted itself)")  # fmt: skip
        owner = self._claim_all(P.pos[:n]) if self.size > 1 else np.zeros(n, dtype=np.int64)
        keep = np.flatnonzero(np.where(owner < 0, 0, owner) == self.rank)
        P.keep(keep)
        P.cell[: P.n_owned] = -1
        self.set_next_gid(P)

    def set_next_gid(self, particles) -> None:
        """Give each rank its own block of future gids above every gid in use (collective)."""
        P = particles
        base = self.max(int(P.next_gid))
        stride = (GID_LIMIT - 1 - base) // self.size
        if stride < 1:
            raise ValueError(f"gid space exhausted: gids up to {base} are in use (limit {GID_LIMIT})")
        P.next_gid = base + self.rank * stride
        P.gid_limit = P.next_gid + stride

    # ------------------------------------------------------------------------------------ migration
    def migrate(self, particles, saved=None, wsaved=None, work=None):
        """Send owned particles to their owners with their history (collective); returns merged (saved, wsaved).

        saved: (keys, vals) of pair history (`PairList.saved_history`), wsaved: (keys, vals) of wall history, or
        None. work: each owned particle's share of the force loop (unused here: ownership follows the mesh).
        Ghost rows are dropped. Arrivals get cell -1 (located afresh by their next walk).
        """
        t0 = time.perf_counter()
        P = particles
        P.n_ghost = 0
        if self.size == 1:
            return saved, wsaved
        dest = self.owners(P)
        leave = dest != self.rank
        out = [None] * self.size
        idx = np.flatnonzero(leave)
        gid_sets = {}
        for r in np.unique(dest[idx]):
            rows = idx[dest[idx] == r]
            out[int(r)] = {"rows": P.pack(rows)}
            gid_sets[int(r)] = P.gid[rows]
        if gid_sets:
            for key, hist in (("pairs", saved), ("walls", wsaved)):
                if hist is None or hist[0].size == 0:
                    continue
                for r, sel in _split_by_gid(hist[0], gid_sets, key == "pairs").items():
                    out[r][key] = (hist[0][sel], hist[1][sel])
        got = self.comm.alltoall(out)
        self.migrated += int(idx.size)
        if idx.size:
            P.drop(idx)  # the last rows fill the holes: O(leavers), not a copy of every staying row
        more_p, more_w = [], []
        for msg in got:
            if msg is None:
                continue
            rows = msg["rows"]
            rows["cell"] = np.full(rows["pos"].shape[0], -1, dtype=np.int64)
            P.append(rows)
            if "pairs" in msg:
                more_p.append(msg["pairs"])
            if "walls" in msg:
                more_w.append(msg["walls"])
        if more_p:
            saved = _merge(*saved, more_p) if saved is not None else _merge(*more_p[0], more_p[1:])
        if more_w:
            wsaved = _merge(*wsaved, more_w) if wsaved is not None else _merge(*more_w[0], more_w[1:])
        self.timers["migrate"] += time.perf_counter() - t0
        return saved, wsaved

    # ------------------------------------------------------------------------------------ ghosts
    def refresh_ghosts(self, particles, reach: float) -> None:
        """Replace the ghost rows by copies of other ranks' particles within `reach` (m) of this rank's cells."""
        t0 = time.perf_counter()
        P = particles
        P.n_ghost = 0
        if self.size == 1:
            return
        n = P.n_owned
        start, rows = self._ghost_targets(P.pos, n, reach)
        self._send_start, self._send_rows = start, rows
        counts = np.diff(start).astype(np.int64)
        recv = np.zeros(self.size, dtype=np.int64)
        self.comm.Alltoall(counts, recv)
        self._recv_start = np.concatenate([[0], np.cumsum(recv)])
        nf = 13
        fbuf = np.empty((rows.size, nf))
        ibuf = np.empty((rows.size, len(_GHOST_INTS)), dtype=np.int64)
        c = 0
        for name in _GHOST_FLOATS:
            a = getattr(P, name)[rows]
            w = 1 if a.ndim == 1 else 3
            fbuf[:, c : c + w] = a.reshape(-1, w)
            c += w
        for k, name in enumerate(_GHOST_INTS):
            ibuf[:, k] = getattr(P, name)[rows]
        m = int(self._recv_start[-1])
        rf = np.empty((m, nf))
        ri = np.empty((m, len(_GHOST_INTS)), dtype=np.int64)
        reqs = []
        for r in range(self.size):
            a, b = self._recv_start[r], self._recv_start[r + 1]
            if b > a:
                reqs.append(self.comm.Irecv(rf[a:b], source=r, tag=11))
                reqs.append(self.comm.Irecv(ri[a:b], source=r, tag=12))
        for r in range(self.size):
            a, b = start[r], start[r + 1]
            if b > a:
                reqs.append(self.comm.Isend(fbuf[a:b], dest=r, tag=11))
                reqs.append(self.comm.Isend(ibuf[a:b], dest=r, tag=12))
        MPI.Request.Waitall(reqs)
        fields = {"pos": rf[:, 0:3], "vel": rf[:, 3:6], "omega": rf[:, 6:9], "diameter": rf[:, 9], "mass": rf[:, 10],
                  "inertia": rf[:, 11], "n_orig": rf[:, 12]}  # fmt: skip
        for k, name in enumerate(_GHOST_INTS):
            fields[name] = ri[:, k]
        fields["cell"] = np.full(m, -1, dtype=np.int64)
        P.set_ghosts(**fields)
        self._bufs = {}  # update messages by width: 9 (pos, vel, omega) or 6 (no rotation)
        self.timers["ghosts"] += time.perf_counter() - t0

    def _ghost_targets(self, pos: np.ndarray, n: int, reach: float):
        """(start (size+1,), rows): rows[start[r]:start[r+1]] of pos[:n] are the ghosts rank r needs; sets `strays`."""
        if self.table is None or self.table.width < reach:
            self.table = HaloTable(self.comm, self.ma.bbox, self.ma.num_owned_cells, 1.2 * reach)
        start, rows, self.strays = self.table.targets(pos[:n], n)
        return start, rows

    def update_ghosts(self, particles, vel: np.ndarray, omega: np.ndarray, local_max: float | None = None,
                      spin: bool = True):  # fmt: skip
        """Copy the owners' pos, `vel`, `omega` ((n, 3), indexed like the particle rows) into the ghost rows.

        vel/omega are the velocities the force evaluation uses (the particle's, or Verlet's predicted ones).
        Without `spin` (a DEM that does not integrate rotation: every omega is zero) omega is not sent and
        the ghosts' omega rows are set to zero, a third less to send.
        With `local_max`, its maximum over the ranks is reduced in the same round of messages and returned
        (the stepping's rebuild criterion: one synchronisation instead of two).
        """
        if self.size == 1:
            return local_max
        t0 = time.perf_counter()
        P = particles
        rows = self._send_rows
        w = 9 if spin else 6
        if w not in self._bufs:
            self._bufs[w] = (np.empty((rows.size, w)), np.empty((int(self._recv_start[-1]), w)))
        sb, rb = self._bufs[w]
        _pack(rows, P.pos, vel, omega, spin, sb)
        reqs = []
        if local_max is not None:
            red = np.array([local_max, 0.0])
            reqs.append(self.comm.Iallreduce(red[:1], red[1:], op=MPI.MAX))
        for r in range(self.size):
            a, b = self._recv_start[r], self._recv_start[r + 1]
            if b > a:
                reqs.append(self.comm.Irecv(rb[a:b], source=r, tag=13))
        for r in range(self.size):
            a, b = self._send_start[r], self._send_start[r + 1]
            if b > a:
                reqs.append(self.comm.Isend(sb[a:b], dest=r, tag=13))
        MPI.Request.Waitall(reqs)
        _unpack(P.n_owned, rb, P.pos, vel, omega, spin)
        self.timers["update"] += time.perf_counter() - t0
        return float(red[1]) if local_max is not None else None

    def counts(self, particles) -> tuple[int, int]:
        """(owned, ghosts) particles summed over ranks (collective); `balance_line` gives the imbalance."""
        c = self.comm.allreduce(np.array([particles.n_owned, particles.n_ghost], dtype=np.int64))
        return int(c[0]), int(c[1])


def balance_line(comm, owned: int, pairs: int) -> str:
    """The log's load-balance line: particles and listed contact pairs per rank, max/mean of each (collective).

    The pairs measure the DEM's work better than the particles: a rank holding the denser part of a bed
    lists more pairs per particle (C2 at t = 4.03 s: particles 1.14 max/mean, pairs 1.27). Before the first
    step (no pair lists yet) only the particles are reported.
    """
    c = np.array(comm.allgather((owned, pairs)), dtype=np.int64)
    ratio = [float(c[:, k].max()) / c[:, k].mean() if c[:, k].sum() > 0 else 1.0 for k in (0, 1)]
    line = f"particles per rank {c[:, 0].tolist()}: load imbalance max/mean = {ratio[0]:.3f}"
    if c[:, 1].sum() > 0:
        line += f"; listed pairs per rank {c[:, 1].tolist()}: max/mean = {ratio[1]:.3f} (the DEM's work)"
    return line
