"""Structure-of-arrays particle container with capacity, stable global ids and room for MPI ghosts.

Layout: rows `[0, n_owned)` are the particles this process integrates; rows `[n_owned, n_owned + n_ghost)`
are ghost copies of particles owned elsewhere (filled by the parallel layer, read-only for the DEM: the
contact kernels see them, the integrators skip them). Every array has `capacity` rows; the public
attributes (`pos`, `vel`, ...) are views of the first `n` = n_owned + n_ghost rows, always (n, 3) for
vectors in 2D and 3D alike.

Particles are identified by `gid` (int64, unique and never reused on this process: new ids come from
`next_gid`, which the parallel layer offsets per rank). Contact history is not stored here: it is kept per
contact pair by the neighbour list, keyed by the two gids (see `febed.dem.neighbours`), so reordering,
removing or migrating particles never scrambles it.

Auxiliary per-particle arrays (`attach`, `aux`) follow the owned rows through reordering, removal and MPI
migration: callers keep per-particle state there (e.g. the coupling's frozen drag) instead of by row.
"""

from __future__ import annotations

import numpy as np

VEC_FIELDS = ("pos", "vel", "omega", "force", "torque")
SCALAR_FIELDS = {
    "diameter": np.float64,
    "mass": np.float64,
    "inertia": np.float64,
    "gid": np.int64,
    "n_orig": np.float64,  # originals each particle stands for: whole, or a fraction when divisible (PCPM)
    "cell": np.int64,
    "material": np.int32,
}
FIELDS = VEC_FIELDS + tuple(SCALAR_FIELDS)
GID_LIMIT = 2**31  # gids fit in 31 bits so that a pair of gids packs into one int64 key


class Particles:
    """Particle arrays (SI units): positions m, velocities m/s, angular velocities rad/s, forces N, torques N m.

    Attributes:
        n_owned: number of owned particles (rows 0..n_owned-1).
        n_ghost: number of ghost particles appended after the owned ones.
        next_gid: the gid the next inserted particle receives.
    """

    def __init__(self, capacity: int = 1024, first_gid: int = 0):
        """Create an empty container with room for `capacity` particles."""
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.n_owned = 0
        self.n_ghost = 0
        self.next_gid = int(first_gid)
        self.gid_limit = GID_LIMIT  # gids of this process stay below it (the parallel layer gives each rank a block)
        self._aux: dict[str, np.ndarray] = {}
        self._alloc(int(capacity))

    # ------------------------------------------------------------------ storage
    def _alloc(self, capacity: int) -> None:
        old = getattr(self, "_data", None)
        data = {}
        for name in VEC_FIELDS:
            data[name] = np.zeros((capacity, 3))
        for name, dt in SCALAR_FIELDS.items():
            data[name] = np.zeros(capacity, dtype=dt)
        if old is not None:
            n = self.n
            for name in FIELDS:
                data[name][:n] = old[name][:n]
        for name, a in self._aux.items():
            b = np.zeros((capacity, a.shape[1]))
            b[: min(a.shape[0], capacity)] = a[:capacity]
            self._aux[name] = b
        self._data = data
        self.capacity = capacity

    def reserve(self, capacity: int) -> None:
        """Grow the storage to hold at least `capacity` particles (amortised doubling)."""
        if capacity > self.capacity:
            self._alloc(max(int(capacity), 2 * self.capacity))

    @property
    def n(self) -> int:
        """Number of rows in use: owned plus ghost particles."""
        return self.n_owned + self.n_ghost

    def __len__(self) -> int:
        return self.n_owned

    def __getattr__(self, name: str) -> np.ndarray:
        data = self.__dict__.get("_data")
        if data is not None and name in data:
            return data[name][: self.n_owned + self.n_ghost]
        raise AttributeError(f"Particles has no attribute {name!r}")

    def attach(self, name: str, ncomp: int = 1) -> np.ndarray:
        """Add (if missing) an auxiliary float array of `ncomp` columns that follows the rows; returns `aux(name)`."""
        if not name or not isinstance(name, str):
            raise ValueError(f"name must be a non-empty string, got {name!r}")
        if ncomp < 1:
            raise ValueError(f"ncomp must be >= 1, got {ncomp}")
        a = self._aux.get(name)
        if a is None or a.shape[1] != ncomp:
            self._aux[name] = np.zeros((self.capacity, int(ncomp)))
        return self.aux(name)

    def aux(self, name: str) -> np.ndarray:
        """View (n, ncomp) of the auxiliary array `name` (rows as the particle arrays; ghost rows are zero)."""
        if name not in self._aux:
            raise ValueError(f"no auxiliary array {name!r}; attached: {sorted(self._aux)}")
        return self._aux[name][: self.n_owned + self.n_ghost]

    @property
    def aux_names(self) -> list[str]:
        """Names of the attached auxiliary arrays."""
        return list(self._aux)

    def full(self, name: str) -> np.ndarray:
        """The whole capacity-sized array of field `name` (for kernels that need fixed storage)."""
        return self._data[name]

    # ------------------------------------------------------------------ insert / remove
    def add(
        self,
        pos: np.ndarray,
        diameter: float | np.ndarray,
        density: float | np.ndarray,
        vel: np.ndarray | None = None,
        omega: np.ndarray | None = None,
        n_orig: float | np.ndarray = 1,
        material: int | np.ndarray = 0,
    ) -> np.ndarray:
        """Append owned spheres (diameter m, density kg/m^3) and return their new gids; drops ghosts."""
        pos = np.asarray(pos, dtype=float)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f"pos must have shape (k, 3), got {pos.shape}")
        k = pos.shape[0]
        d = np.broadcast_to(np.asarray(diameter, dtype=float), (k,))
        rho = np.broadcast_to(np.asarray(density, dtype=float), (k,))
        if k and (np.any(d <= 0) or np.any(rho <= 0)):
            raise ValueError("diameter and density must be > 0")
        if self.next_gid + k > self.gid_limit:
            raise ValueError(f"gid space exhausted (this process's gids must stay below {self.gid_limit})")
        self.n_ghost = 0
        self.reserve(self.n_owned + k)
        s = slice(self.n_owned, self.n_owned + k)
        D = self._data
        D["pos"][s] = pos
        D["vel"][s] = 0.0 if vel is None else vel
        D["omega"][s] = 0.0 if omega is None else omega
        D["force"][s] = 0.0
        D["torque"][s] = 0.0
        D["diameter"][s] = d
        m = rho * np.pi / 6.0 * d**3
        D["mass"][s] = m
        D["inertia"][s] = 0.1 * m * d**2  # solid sphere: 2/5 m r^2
        gids = np.arange(self.next_gid, self.next_gid + k, dtype=np.int64)
        D["gid"][s] = gids
        D["n_orig"][s] = n_orig
        D["cell"][s] = -1
        D["material"][s] = material
        for a in self._aux.values():
            a[s] = 0.0
        self.next_gid += k
        self.n_owned += k
        return gids

    def remove(self, which: np.ndarray) -> None:
        """Remove owned particles given by a boolean mask (length n_owned) or an index array; drops ghosts."""
        which = np.asarray(which)
        keep = np.ones(self.n_owned, dtype=bool)
        if which.dtype == bool:
            if which.shape != (self.n_owned,):
                raise ValueError(f"boolean mask must have shape ({self.n_owned},), got {which.shape}")
            keep &= ~which
        else:
            if which.size and (which.min() < 0 or which.max() >= self.n_owned):
                raise ValueError("indices must be in [0, n_owned)")
            keep[which] = False
        self.n_ghost = 0
        idx = np.flatnonzero(keep)
        self._take(idx)

    def reorder(self, perm: np.ndarray) -> None:
        """Permute the owned particles: new row k is old row perm[k]; drops ghosts."""
        perm = np.asarray(perm, dtype=np.int64)
        if perm.shape != (self.n_owned,):
            raise ValueError(f"perm must have shape ({self.n_owned},), got {perm.shape}")
        self.n_ghost = 0
        self._take(perm)

    def _take(self, idx: np.ndarray) -> None:
        k = idx.size
        for name in FIELDS:
            a = self._data[name]
            a[:k] = a[idx]
        for a in self._aux.values():
            a[:k] = a[idx]
        self.n_owned = k

    def pack(self, idx: np.ndarray) -> dict[str, np.ndarray]:
        """Copies of owned rows `idx`: every field and auxiliary array ("aux:<name>"), for migration."""
        idx = np.asarray(idx, dtype=np.int64)
        out = {name: self._data[name][idx] for name in FIELDS}
        for name, a in self._aux.items():
            out[f"aux:{name}"] = a[idx]
        return out

    def keep(self, idx: np.ndarray) -> None:
        """Keep only the owned rows `idx` (in that order); drops ghosts."""
        idx = np.asarray(idx, dtype=np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= self.n_owned):
            raise ValueError("idx must be in [0, n_owned)")
        self.n_ghost = 0
        self._take(idx)

    def drop(self, rows: np.ndarray) -> None:
        """Remove the owned rows `rows` by moving the last surviving rows into their places; drops ghosts.

        The order of the other rows is not kept (unlike `remove`/`keep`), but the cost is in the number of rows
        removed, not in the number kept: migration takes a few dozen rows out of tens of thousands.
        """
        rows = np.unique(np.asarray(rows, dtype=np.int64))
        if rows.size and (rows[0] < 0 or rows[-1] >= self.n_owned):
            raise ValueError("rows must be in [0, n_owned)")
        self.n_ghost = 0
        n = self.n_owned - rows.size
        holes = rows[rows < n]
        tail = np.setdiff1d(np.arange(n, self.n_owned), rows, assume_unique=True)  # as many as holes
        for name in FIELDS:
            a = self._data[name]
            a[holes] = a[tail]
        for a in self._aux.values():
            a[holes] = a[tail]
        self.n_owned = n

    def append(self, data: dict[str, np.ndarray]) -> None:
        """Append owned rows given by `pack` output (gids kept as they are); drops ghosts."""
        k = np.asarray(data["pos"]).shape[0]
        self.n_ghost = 0
        self.reserve(self.n_owned + k)
        s = slice(self.n_owned, self.n_owned + k)
        for name in FIELDS:
            if name in data:
                self._data[name][s] = data[name]
        for name, a in self._aux.items():
            a[s] = data.get(f"aux:{name}", 0.0)
        self.n_owned += k

    def set_ghosts(self, **fields: np.ndarray) -> None:
        """Replace the ghost rows by the given arrays (pos, vel, omega, diameter, mass, inertia, gid, ...)."""
        if "pos" not in fields or "gid" not in fields:
            raise ValueError("set_ghosts needs at least pos and gid")
        k = np.asarray(fields["pos"]).shape[0]
        self.n_ghost = 0
        self.reserve(self.n_owned + k)
        s = slice(self.n_owned, self.n_owned + k)
        for name in FIELDS:
            self._data[name][s] = fields[name] if name in fields else 0
        for a in self._aux.values():
            a[s] = 0.0
        self.n_ghost = k

    # ------------------------------------------------------------------ save / load
    def to_dict(self) -> dict[str, np.ndarray]:
        """Copies of the owned particles' arrays, keyed by field name (for .npz files and output)."""
        return {name: self._data[name][: self.n_owned].copy() for name in FIELDS}

    @classmethod
    def from_dict(cls, data: dict[str, np.ndarray]) -> Particles:
        """Particles holding the arrays of `to_dict` (missing fields get defaults)."""
        pos = np.asarray(data["pos"], dtype=float)
        p = cls(capacity=max(1, pos.shape[0]))
        p.n_owned = pos.shape[0]
        for name in FIELDS:
            if name in data:
                p._data[name][: p.n_owned] = data[name]
        if "gid" not in data:
            p._data["gid"][: p.n_owned] = np.arange(p.n_owned)
        if "n_orig" not in data:
            p._data["n_orig"][: p.n_owned] = 1
        p.next_gid = int(p.gid.max()) + 1 if p.n_owned else 0
        return p

    def kinetic_energy(self) -> float:
        """Translational plus rotational kinetic energy of the owned particles (J)."""
        n = self.n_owned
        v2 = np.einsum("ij,ij->i", self.vel[:n], self.vel[:n])
        w2 = np.einsum("ij,ij->i", self.omega[:n], self.omega[:n])
        return float(0.5 * np.dot(self.mass[:n], v2) + 0.5 * np.dot(self.inertia[:n], w2))
