"""The particle bed of a case: walls from its mesh, the bed loaded, inserted or packed, and the DEM that steps it.

Walls are the boundary facets of the case mesh whose `[gas.boundary.<tag>]` says particles collide with
them: every tag with `particles = true` except outlets, plus outlets with `particles = false` (closed to
particles). Without any `[gas.boundary]` table every tagged boundary is a wall.

The bed: `[particles] bed_file` is loaded if it exists; if it does not and `pack_if_missing`, particles are
inserted, settled to `settle_energy` (with every contact's restitution set to `pack_restitution`, if given,
for a quicker settling) and saved there, and the run starts from the packed bed. Without a
bed file the inserted particles are simply released at t = 0 (a pour). The DEM takes the case's contact law
with its coarse-grain scaling (`febed.coarse.setup`).

With MPI (`mpirun -n N febed run`), every rank loads or inserts the same bed, then keeps the particles whose
centres lie in its own mesh cells (`febed.parallel.ParticleExchange`); particles migrate and ghosts cross the
partition inside `DEM.advance`.

`build_dem` serves every run mode with particles (`febed.runs.dem`, `febed.solver.build_solver`,
`febed.runs.oneway`) and the pre-flight checks (`febed.preflight`).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed.coarse import setup as coarse
from febed.dem.insertion import (
    count_from_mass,
    lattice_capacity,
    lattice_positions,
    load_bed,
    random_positions,
    save_bed,
    settle,
)
from febed.dem.particles import Particles
from febed.dem.solver import DEM
from febed.dem.walls import Walls, touching
from febed.parallel import BoxExchange, ParticleExchange


def wall_tags(case, md) -> list[str]:
    """Mesh tags that confine particles, from the case's boundary table (see module docstring)."""
    if not case.boundary:
        return sorted(md.tags)
    tags = []
    for tag, b in case.boundary.items():
        if (b.type != "outlet" and b.particles) or (b.type == "outlet" and not b.particles):
            tags.append(tag)
    return sorted(tags)


def walls_from_mesh(case, md) -> Walls:
    """Walls of the case's particle-confining tags (allgathered boundary facets; collective).

    A face of the mesh's bounding box that they cover completely becomes a plane (`Walls.from_facets`).
    """
    tags = wall_tags(case, md)
    if not tags:
        return Walls()
    x = md.mesh.geometry.x
    comm = md.comm
    lo = x.min(axis=0) if x.size else np.full(3, np.inf)
    hi = x.max(axis=0) if x.size else np.full(3, -np.inf)
    comm.Allreduce(MPI.IN_PLACE, lo, op=MPI.MIN)
    comm.Allreduce(MPI.IN_PLACE, hi, op=MPI.MAX)
    return Walls.from_facets(md.boundary_facet_coords(tags), box=(lo, hi))


def inside_mesh(md, pos: np.ndarray) -> np.ndarray:
    """Boolean mask of the points (n, 3) inside a cell of the mesh (of any rank's part; collective with MPI)."""
    from dolfinx import geometry

    mesh = md.mesh
    tree = geometry.BoundingBoxTree(mesh, mesh.topology.dim)
    cand = geometry.compute_collisions(tree, np.ascontiguousarray(pos, dtype=np.float64))
    cells = geometry.compute_colliding_cells(mesh, cand, np.ascontiguousarray(pos, dtype=np.float64))
    inside = (np.diff(cells.offsets) > 0).astype(np.uint8)
    if md.comm.size > 1:
        md.comm.Allreduce(MPI.IN_PLACE, inside, op=MPI.MAX)
    return inside.astype(bool)


def insertion_region(case, md, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """The box (lo, hi) where particles are inserted: `[particles] region` clipped to the mesh (collective)."""
    x = md.mesh.geometry.x
    lo = np.minimum.reduce(md.comm.allgather(x.min(axis=0)))
    hi = np.maximum.reduce(md.comm.allgather(x.max(axis=0)))
    r = np.asarray(case.particles.region, dtype=float)
    rlo = np.where(np.isfinite(r[:3]), np.maximum(r[:3], lo), lo)
    rhi = np.where(np.isfinite(r[3:]), np.minimum(r[3:], hi), hi)
    if dim == 2:
        rlo[2] = rhi[2] = 0.0
    if np.any(rhi[:dim] <= rlo[:dim]):
        raise ValueError(f"[particles] region {list(r)} does not intersect the mesh box {lo}..{hi}")
    return rlo, rhi


def original_count(case) -> int:
    """Number of original particles of the case: `[particles] count`, or `bed_mass` in originals."""
    p = case.particles
    count = p.count if p.count > 0 else (count_from_mass(p.bed_mass, p.diameter, p.density) if p.bed_mass > 0 else 0)
    if count <= 0:
        raise ValueError("[particles] give count > 0 or bed_mass > 0 (or an existing bed_file)")
    return count


def insert_in_mesh(case, md, walls: Walls, dim: int, count: int | None = None, d: float | None = None) -> np.ndarray:
    """Centres of `count` particles of diameter d (default: the case's), in its region, inside the mesh, off walls."""
    p = case.particles
    d = p.diameter if d is None else d
    count = original_count(case) if count is None else count
    lo, hi = insertion_region(case, md, dim)
    factor = 1.0
    for _ in range(8):
        k = int(math.ceil(count * factor))
        try:
            if p.insertion == "lattice":
                k = min(k, lattice_capacity(lo, hi, d, dim))  # sites off the mesh or on walls are dropped below
                pos = lattice_positions(k, lo, hi, d, dim, rng=np.random.default_rng(case.run.seed))
            else:
                pos = random_positions(k, lo, hi, d, dim, seed=case.run.seed)
        except ValueError:
            break
        ok = inside_mesh(md, pos) & ~touching(walls, pos, np.full(k, 0.5 * d))
        if ok.sum() >= count:
            return pos[ok][:count]
        factor *= 1.6 * count / max(ok.sum(), 1) if ok.sum() else 2.0
    raise ValueError(
        f"could not place {count} particles of {d} m in [particles] region {lo}..{hi} inside the mesh; "
        "enlarge the region or use insertion = 'lattice'"
    )


def gather_particles(dem: DEM) -> Particles | None:
    """Every rank's owned particles, ordered by gid, on rank 0 (None elsewhere; collective with MPI)."""
    P = dem.particles
    if dem.exchange is None:
        return P
    data = {k: v[np.argsort(P.gid[: P.n_owned])] for k, v in P.to_dict().items()}
    parts = dem.exchange.comm.gather(data, root=0)
    if dem.exchange.rank != 0:
        return None
    data = {k: np.concatenate([d[k] for d in parts]) for k in data}
    order = np.argsort(data["gid"], kind="stable")
    return Particles.from_dict({k: v[order] for k, v in data.items()})


def particle_exchange(md, comm, partition: str = "mesh"):
    """The particle exchange: over the mesh partition, or work-balanced boxes for "work"; None on one process."""
    if comm.size == 1:
        return None
    if partition == "work":
        return BoxExchange(comm, dim=md.gdim)
    return ParticleExchange.from_mesh(md.mesh)


def dem_from_case(case, walls: Walls, dim: int, particles: Particles) -> DEM:
    """`DEM.from_case` with the case's coarse-grain contact law (TM parcels, PCPM group scaling)."""
    dem = DEM.from_case(case, walls=walls, dim=dim, particles=particles)
    params = coarse.dem_params(case, dem.params)
    if params is not dem.params:
        dem = DEM(params, particles=particles, walls=walls)
    coarse.configure_dem(case, dem)
    return dem


def build_dem(case, md, log, exchange=None) -> DEM:
    """The DEM of a case: walls from the mesh and the bed loaded, or inserted (and packed/saved if asked).

    With an `exchange` (MPI), each rank keeps the particles of its own cells and the DEM runs distributed.
    """
    dim = md.gdim
    walls = walls_from_mesh(case, md)
    npl = walls.plane_p.shape[0]
    log.info(f"DEM walls: {npl} plane(s) (bounding-box faces) and {walls.count - npl} facets of tags "
             f"{wall_tags(case, md)}, dim {dim}")  # fmt: skip
    p = case.particles
    bed_path = case.resolve_path(p.bed_file) if p.bed_file else None
    if bed_path is not None and Path(bed_path).exists():
        parts, _ = load_bed(bed_path)
        log.info(f"loaded packed bed {bed_path}: {parts.n_owned} particles")
        dem = dem_from_case(case, walls, dim, parts)
        if exchange is not None:
            dem.attach_exchange(exchange, distribute=True)
        return dem
    if bed_path is not None and not p.pack_if_missing:
        raise ValueError(f"[particles] bed_file {bed_path} does not exist and pack_if_missing = false")
    dem = dem_from_case(case, walls, dim, Particles())
    if bed_path is not None and p.pack_restitution > 0:  # packing only: the run itself uses the case's e
        e = p.pack_restitution
        dem = DEM(replace(dem.params, restitution_pp=e, restitution_pw=e), particles=dem.particles, walls=walls)
        coarse.configure_dem(case, dem)
    spec = coarse.parcels(case, original_count(case), dim)
    pos = insert_in_mesh(case, md, walls, dim, spec.count, spec.diameter)
    dem.add_particles(pos, spec.diameter, spec.density, n_orig=spec.n_orig)
    if exchange is not None:
        dem.attach_exchange(exchange, distribute=True)
    cg = f", {case.coarse_grain.model} l = {case.coarse_grain.ratio:g}" if case.coarse_grain.model != "none" else ""
    log.info(f"inserted {pos.shape[0]} particles of {spec.diameter:g} m ({p.insertion}{cg}); DEM step {dem.dt:.3e} s")
    if bed_path is not None:
        e = f", restitution {p.pack_restitution:g} while packing" if p.pack_restitution > 0 else ""
        log.info(f"packing the bed until the mean kinetic energy < {p.settle_energy:g} J{e} ...")
        t = settle(dem, p.settle_energy, max_time=p.settle_max_time, log=log)
        everyone = gather_particles(dem)
        if md.comm.rank == 0:
            save_bed(bed_path, everyone, settle_time=t)
        md.comm.barrier()
        log.info(f"packed in {t:.3f} s of simulated time; saved {bed_path}")
        parts = dem.particles
        parts.n_ghost = 0
        dem = dem_from_case(case, walls, dim, parts)
        if exchange is not None:
            dem.attach_exchange(exchange)
    return dem
