"""Insertion of particles, settling, and packed-bed files.

Particles are inserted by count or bed mass, on a lattice or at random without overlap; the packed bed is
saved (.npz, written atomically) so a bed is packed once and loaded by later cases.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np
from numba import njit

from febed.dem.particles import Particles


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
    """Write the owned particles to `path` (.npz) atomically (temporary name, then os.replace)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.npz")
    data = particles.to_dict()
    for k, v in meta.items():
        data[f"meta_{k}"] = np.asarray(v)
    np.savez(tmp, **data)
    os.replace(tmp, path)
    return path


def load_bed(path) -> tuple[Particles, dict]:
    """Particles and metadata saved by `save_bed`."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"bed file {path} does not exist")
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    meta = {k[5:]: data.pop(k) for k in list(data) if k.startswith("meta_")}
    return Particles.from_dict(data), meta
