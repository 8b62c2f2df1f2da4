"""Insertion of particles, settling, and packed-bed files.

Particles are inserted by count or bed mass, on a lattice or at random without overlap; the packed bed is
saved (.npz, written atomically) so a bed is packed once and loaded by later cases.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from numba import njit

from febed.dem.particles import GID_LIMIT, Particles
from febed.io.atomic import atomic_open


def count_from_mass(bed_mass: float, diameter: float, density: float) -> int:
    """Number of spheres (rounded) of `diameter` (m) and `density` (kg/m^3) making `bed_mass` (kg)."""
    if bed_mass <= 0 or diameter <= 0 or density <= 0:
        raise ValueError("bed_mass, diameter and density must be > 0")
    return int(round(bed_mass / (density * math.pi / 6.0 * diameter**3)))


def _check_box(lo, hi, diameter, dim):
    lo = np.asarray(lo, dtype=float).copy()
    hi = np.asarray(hi, dtype=float).copy()
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo[:dim])) or not np.all(np.isfinite(hi[:dim])):
        raise ValueError("region lo and hi must be finite 3-vectors (clip infinite bounds to the mesh first)")
    if dim == 2:
        lo[2] = hi[2] = 0.0
    if np.any(hi[:dim] - lo[:dim] < diameter):
        raise ValueError(f"region {lo}..{hi} is smaller than one diameter {diameter}")
    return lo, hi


def _lattice_shape(lo, hi, diameter, dim, gap):
    n = np.maximum(np.floor((hi - lo - diameter) / (diameter * (1.0 + gap))).astype(int) + 1, 1)
    if dim == 2:
        n[2] = 1
    return n


def lattice_capacity(lo, hi, diameter: float, dim: int = 3, gap: float = 0.05) -> int:
    """Number of lattice sites `lattice_positions` has in the box [lo, hi] for spheres of `diameter`."""
    lo, hi = _check_box(lo, hi, diameter, dim)
    return int(np.prod(_lattice_shape(lo, hi, diameter, dim, gap)))


def lattice_positions(count: int, lo, hi, diameter: float, dim: int = 3, gap: float = 0.05, rng=None) -> np.ndarray:
    """Centres (count, 3) on a cubic lattice of spacing d (1 + gap) inside [lo, hi], filled from the bottom.

    The bottom is -z in 3D and -y in 2D. With `rng`, each centre gets a random offset of up to gap d / 4
    (no overlap) to break the lattice's symmetry. Raises ValueError if the box cannot hold `count`.
    """
    lo, hi = _check_box(lo, hi, diameter, dim)
    s = diameter * (1.0 + gap)
    n = _lattice_shape(lo, hi, diameter, dim, gap)
    up = 1 if dim == 2 else 2
    per_layer = int(np.prod(n)) // n[up]
    if per_layer * n[up] < count:
        raise ValueError(f"region holds {per_layer * n[up]} particles on a lattice, {count} requested")
    k = np.arange(count)
    layer = k // per_layer
    rest = k % per_layer
    idx = np.zeros((count, 3), dtype=int)
    idx[:, up] = layer
    others = [a for a in range(3) if a != up]
    idx[:, others[0]] = rest % n[others[0]]
    idx[:, others[1]] = rest // n[others[0]]
    pos = lo + 0.5 * diameter + idx * s
    if dim == 2:
        pos[:, 2] = 0.0
    if rng is not None:
        jit = rng.uniform(-0.25 * gap * diameter, 0.25 * gap * diameter, size=pos.shape)
        if dim == 2:
            jit[:, 2] = 0.0
        pos += jit
    return pos


@njit(cache=True)
def _random_fill(count, lo, hi, radius, dim, seed, max_tries):
    np.random.seed(seed)  # noqa: NPY002 (Numba supports only the legacy API)
    size = 2.0 * radius
    dims = np.ones(3, dtype=np.int64)
    for a in range(dim):
        dims[a] = max(1, int((hi[a] - lo[a]) / size))
    head = -np.ones(dims[0] * dims[1] * dims[2], dtype=np.int64)
    nxt = -np.ones(count, dtype=np.int64)
    pos = np.zeros((count, 3))
    placed = 0
    tries = 0
    while placed < count and tries < max_tries:
        tries += 1
        p = np.zeros(3)
        for a in range(dim):
            p[a] = lo[a] + radius + np.random.random() * (hi[a] - lo[a] - 2.0 * radius)  # noqa: NPY002
        c = np.zeros(3, dtype=np.int64)
        for a in range(3):
            c[a] = min(max(int((p[a] - lo[a]) / size), 0), dims[a] - 1)
        ok = True
        for x in range(max(c[0] - 1, 0), min(c[0] + 2, dims[0])):
            for y in range(max(c[1] - 1, 0), min(c[1] + 2, dims[1])):
                for z in range(max(c[2] - 1, 0), min(c[2] + 2, dims[2])):
                    q = head[(x * dims[1] + y) * dims[2] + z]
                    while q >= 0 and ok:
                        d2 = 0.0
                        for a in range(3):
                            d2 += (pos[q, a] - p[a]) ** 2
                        if d2 < size * size:
                            ok = False
                        q = nxt[q]
        if ok:
            pos[placed] = p
            cell = (c[0] * dims[1] + c[1]) * dims[2] + c[2]
            nxt[placed] = head[cell]
            head[cell] = placed
            placed += 1
    return pos, placed


def random_positions(count: int, lo, hi, diameter: float, dim: int = 3, seed: int = 0) -> np.ndarray:
    """Centres (count, 3) drawn uniformly in [lo, hi] without overlap (random sequential addition)."""
    lo, hi = _check_box(lo, hi, diameter, dim)
    pos, placed = _random_fill(int(count), lo, hi, 0.5 * diameter, dim, int(seed), 200 * int(count) + 1000)
    if placed < count:
        raise ValueError(
            f"placed only {placed} of {count} particles at random in the region; enlarge it or use a lattice"
        )
    return pos


def insert(dem, count: int, lo, hi, diameter: float, density: float, how: str = "random", seed: int = 0):
    """Add `count` spheres in the box [lo, hi] to `dem` (how = "random" or "lattice"); returns their gids."""
    dim = dem.params.dim
    if how == "random":
        pos = random_positions(count, lo, hi, diameter, dim, seed)
    elif how == "lattice":
        pos = lattice_positions(count, lo, hi, diameter, dim, rng=np.random.default_rng(seed))
    else:
        raise ValueError(f"insertion must be 'random' or 'lattice', got {how!r}")
    return dem.add_particles(pos, diameter, density)


def settle(dem, energy: float, max_time: float = 5.0, chunk: int = 200, log=None, min_time=None) -> float:
    """Advance `dem` until the mean kinetic energy per particle is below `energy` (J); returns the time taken (s).

    Particles inserted at rest have no kinetic energy yet: the criterion is applied only after `min_time`
    (default: the free-fall time over the bed's extent along gravity, sqrt(2 h / g)).
    """
    t0 = dem.time
    if min_time is None:
        g = float(np.linalg.norm(dem.gvec))
        x = dem.particles.pos[: dem.particles.n_owned] @ dem.gvec
        top = dem.global_max(float(x.max()) if x.size else -np.inf)  # collective with MPI
        bottom = -dem.global_max(float(-x.min()) if x.size else -np.inf)
        h = (top - bottom) / g if g > 0 and top > bottom else 0.0
        min_time = math.sqrt(2.0 * h / g) if g > 0 else 0.0
    wall = time.time()
    while dem.time - t0 < max_time:
        dem.advance(chunk)
        ke = dem.mean_kinetic_energy()
        if log is not None and time.time() - wall > 5.0:
            log.info(f"settling: t = {dem.time - t0:.4f} s, mean kinetic energy {ke:.3e} J (target {energy:.1e})")
            wall = time.time()
        if ke < energy and dem.time - t0 >= min_time:
            break
    return dem.time - t0


def save_bed(path, particles: Particles, **meta) -> Path:
    """Write the owned particles to `path` (.npz) atomically (`febed.io.atomic`: temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = particles.to_dict()
    for k, v in meta.items():
        data[f"meta_{k}"] = np.asarray(v)
    with atomic_open(path, "wb") as f:
        np.savez(f, **data)
    return path


class BedError(ValueError):
    """A packed-bed file that cannot be used; the message names the file and what is wrong."""


_BED_REQUIRED = ("pos", "diameter", "mass")
_BED_VECTORS = ("pos", "vel", "omega", "force", "torque")
_BED_FORMAT = (
    "a bed file is a .npz archive as `save_bed` writes it: per-particle arrays pos (n, 3) m, diameter (n,) m and "
    "mass (n,) kg, optionally vel, omega (n, 3), inertia, gid, n_orig (n,)"
)


def load_bed(path) -> tuple[Particles, dict]:
    """Particles and metadata saved by `save_bed`; BedError naming the file if it is not a usable bed.

    Checks that the file is a readable .npz archive, that it holds pos, diameter and mass of at least one
    particle with matching lengths, that every value is finite, diameters and masses > 0, n_orig > 0 and
    gids unique. A missing inertia is that of a solid sphere, 0.1 m d^2.
    """
    path = Path(path)
    if not path.exists():
        raise BedError(f"bed file {path} does not exist")
    if path.is_dir():
        raise BedError(f"bed file {path} is a folder; [particles] bed_file names a .npz file ({_BED_FORMAT})")
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError as e:
        raise BedError(f"bed file {path} cannot be read: {e.strerror or e}") from None
    if head[:2] != b"PK":
        what = "is not a .npz archive (it is not a zip file)"
        if not head:
            what = "is empty"
        elif head == b"\x93NUM":
            what = "holds a single array (.npy), not a .npz archive"
        raise BedError(f"bed file {path} {what}; {_BED_FORMAT}")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: np.asarray(z[k]) for k in z.files}
    except Exception as e:  # BadZipFile, OSError, EOFError, ValueError (pickled or garbage data), zlib errors
        why = f"{type(e).__name__}: {e}"
        raise BedError(f"bed file {path} is not a readable .npz archive ({why}); {_BED_FORMAT}") from None
    meta = {k[5:]: data.pop(k) for k in list(data) if k.startswith("meta_")}
    _check_bed_arrays(path, data)
    if "inertia" not in data:
        data["inertia"] = 0.1 * data["mass"] * data["diameter"] ** 2
    return Particles.from_dict(data), meta


def _check_bed_arrays(path: Path, data: dict[str, np.ndarray]) -> None:
    missing = [k for k in _BED_REQUIRED if k not in data]
    if missing:
        raise BedError(
            f"bed file {path} lacks the array(s) {', '.join(missing)} (it has: {', '.join(sorted(data)) or 'none'}); "
            f"{_BED_FORMAT}"
        )
    pos = data["pos"]
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise BedError(f"bed file {path}: pos has shape {pos.shape}, expected (n, 3) (z = 0 for a 2D bed)")
    n = pos.shape[0]
    if n == 0:
        raise BedError(f"bed file {path} holds no particles")
    for k, v in data.items():
        want = (n, 3) if k in _BED_VECTORS else (n,)
        if k in ("pos", "vel", "omega", "force", "torque", "diameter", "mass", "inertia", "gid", "n_orig",
                 "cell", "material"):  # fmt: skip
            if v.shape != want:
                raise BedError(f"bed file {path}: {k} has shape {v.shape}, expected {want} ({n} particles in pos)")
            if not np.issubdtype(v.dtype, np.number):
                raise BedError(f"bed file {path}: {k} holds {v.dtype} values, expected numbers")
            if not np.all(np.isfinite(v)):
                bad = int(np.count_nonzero(~np.isfinite(v).reshape(n, -1).all(axis=1)))
                raise BedError(f"bed file {path}: {k} is not finite (inf or nan) for {bad} of {n} particles")
    for k in ("diameter", "mass"):
        if np.any(data[k] <= 0):
            raise BedError(f"bed file {path}: {k} must be > 0; {int(np.count_nonzero(data[k] <= 0))} particle(s) have "
                           f"{data[k].min():g}")  # fmt: skip
    if "n_orig" in data and np.any(data["n_orig"] <= 0):
        raise BedError(f"bed file {path}: n_orig must be > 0 (originals, or a piece of one, per particle)")
    if "gid" in data:
        gid = data["gid"]
        if np.any(gid < 0) or np.any(gid >= GID_LIMIT) or np.unique(gid).size != n:
            raise BedError(f"bed file {path}: gid must be unique integers in [0, {GID_LIMIT})")
