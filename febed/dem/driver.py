"""Pure-DEM run (`[run] mode = "dem"`): walls from the mesh, a packed or inserted bed, stepping, output.

Walls are the boundary facets of the case mesh whose `[gas.boundary.<tag>]` says particles collide with
them: every tag with `particles = true` except outlets, plus outlets with `particles = false` (closed to
particles). Without any `[gas.boundary]` table every tagged boundary is a wall. Particles that leave the
mesh's bounding box (through an open outlet) are removed and counted in the log.

The bed: `[particles] bed_file` is loaded if it exists; if it does not and `pack_if_missing`, particles are
inserted, settled to `settle_energy` (with every contact's restitution set to `pack_restitution`, if given,
for a quicker settling) and saved there, and the run starts from the packed bed. Without a
bed file the inserted particles are simply released at t = 0 (a pour).

With MPI (`mpirun -n N febed run`), every rank loads or inserts the same bed, then keeps the particles whose
centres lie in its own mesh cells (`febed.parallel.ParticleExchange`); particles migrate and ghosts cross the
partition inside `DEM.advance`. Output gathers every particle once; the log gives the particle load
imbalance (max/mean particles per rank) at each output.

Like a coupled run, a pure-DEM run (`DEMRun`) writes checkpoints (every `[output] checkpoint_interval`
simulated or `checkpoint_wall_interval` wall seconds, on SIGINT/SIGTERM/SIGUSR1, at the end, and the last good
state when the particles blow up), continues from one with `febed run CASE --restart` on any number of
ranks, shows a progress line and keeps `status.json` up to date.
"""

from __future__ import annotations

import math
import time
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
from febed.dem.solver import DEM, DEMFailure, StopRequested
from febed.dem.walls import Walls, touching


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


def _region(case, md, dim: int) -> tuple[np.ndarray, np.ndarray]:
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
    lo, hi = _region(case, md, dim)
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


def particle_exchange(md, comm):
    """The particle exchange over the mesh partition, or None on one process."""
    if comm.size == 1:
        return None
    from febed.parallel import ParticleExchange

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


class DEMRun:
    """A pure-DEM run with its output: `advance_to(t)` steps the DEM, writing particles and checkpoints.

    Checkpoints (`checkpoints/checkpoint_<step>.npz`, the same files as a coupled run's: the DEM state by
    global id, `febed.restart.dem_arrays`) are written every `[output] checkpoint_interval` simulated or
    `checkpoint_wall_interval` wall seconds, on SIGINT/SIGTERM/SIGUSR1 and at the end. The state at each particle
    output is kept in memory: a blow-up (`DEMFailure`) writes it as the last good checkpoint.
    """

    def __init__(self, case, outdir: Path, log, comm=MPI.COMM_WORLD, restart=None):
        """Build the mesh, walls and bed; `restart`: (path, arrays, meta) of a checkpoint to continue."""
        from febed import restart as rs
        from febed.io.particles import ParticleWriter
        from febed.io.progress import Progress, RateMeter
        from febed.meshing import load_case_mesh
        from febed.run import guarded_write

        self.case, self.outdir, self.log, self.comm = case, Path(outdir), log, comm
        md = load_case_mesh(case, comm)
        exchange = particle_exchange(md, comm)
        self.restarted_from = None
        files = []
        self.left = 0  # particles that left the domain, on this rank
        o = case.output
        if restart is None:
            self.dem = build_dem(case, md, log, exchange)
            self.next_out, self.next_ckpt = o.particle_interval, o.checkpoint_interval
        else:
            path, arrays, meta = restart
            walls = walls_from_mesh(case, md)
            self.dem = dem_from_case(case, walls, md.gdim, Particles())
            if exchange is not None:
                self.dem.attach_exchange(exchange)
            rs.load_dem(self.dem, arrays, meta, comm.size)
            sched = meta["run"]
            self.next_out = float(sched["next_out"])
            self.next_ckpt = self.dem.time + o.checkpoint_interval
            files = sched["particle_files"]
            self.left = int(sched["left"]) if comm.rank == 0 else 0  # the total, counted once
            self.restarted_from = path
        self.lo = np.minimum.reduce(comm.allgather(md.mesh.geometry.x.min(axis=0))) - 1e-9
        self.hi = np.maximum.reduce(comm.allgather(md.mesh.geometry.x.max(axis=0))) + 1e-9
        folder = self.outdir / "particles"
        self.writer = guarded_write(comm, folder, ParticleWriter, folder, comm=comm, entries=files)
        self.display = Progress(log, comm.rank)
        self.good = None  # (arrays, meta) of the last particle output
        self.output_failed = False  # an output error stopped the run
        self.checkpoint_written = None  # (time, path) of the newest checkpoint this run wrote
        self._signal = 0
        self._last_progress = self._last_checkpoint = time.perf_counter()
        self._meter = RateMeter(self.dem.time)

    # ------------------------------------------------------------------------------------ state
    def capture(self) -> tuple[dict, dict]:
        """This rank's state (copies) and the JSON-able meta record of a checkpoint."""
        from febed import restart as rs

        meta = {
            "time": self.dem.time,
            "step": self.dem.steps,
            "ranks": self.comm.size,
            "mode": "dem",
            "run": {
                "next_out": self.next_out,
                "particle_files": [list(e) for e in self.writer.entries],
                "left": self.comm.allreduce(self.left),
            },
        }
        return rs.dem_arrays(self.dem), meta

    def checkpoint(self, state=None) -> Path:
        """Write a checkpoint of the current state, or of `state` from `capture` (collective)."""
        from febed import restart as rs
        from febed.io.checkpoint import FOLDER, write_checkpoint
        from febed.run import checkpoint_or_fail

        arrays, meta = state if state is not None else self.capture()
        meta = {**meta, "case": self.case.to_toml()}
        path = checkpoint_or_fail(
            write_checkpoint, self.outdir / FOLDER, rs.gather(arrays, meta, self.comm), meta,
            self.case.output.keep_checkpoints, self.comm,
        )  # fmt: skip
        self.checkpoint_written = (meta["time"], path)
        self._last_checkpoint = time.perf_counter()
        self.next_ckpt = self.dem.time + self.case.output.checkpoint_interval
        self.log.info(f"checkpoint at t = {meta['time']:.6g} s (DEM step {meta['step']}): {path}")
        return path

    def status(self, state: str, message: str = "", collective: bool = True) -> None:
        """Write `status.json` (running / finished / failed / interrupted) at the DEM's time (`write_run_status`)."""
        from febed.run import write_run_status

        dem = self.dem
        end = self.case.run.end_time
        write_run_status(self.outdir, state, dem.time, end, dem.steps, message, self.comm, collective)

    # ------------------------------------------------------------------------------------- loop
    def output(self, scheduled: bool = True) -> None:
        """Write the particles, move the next output time on if `scheduled`, keep the state as the last good one.

        A failed write raises `OutputFailure` on every rank (and leaves the schedule as it was).
        """
        from febed.run import guarded_write

        guarded_write(self.comm, self.writer.outdir, self.writer.write, self.dem.time, self.dem.particles)
        if scheduled:
            self.next_out += self.case.output.particle_interval
        _log_balance(self.dem, self.log)
        self.good = self.capture()

    def advance_to(self, end: float) -> None:
        """Step to `end` (s), writing particles, checkpoints and progress (collective).

        Raises DEMFailure (after writing the last good state), `febed.run.OutputFailure` or
        `febed.run.Interrupted` (after a checkpoint).
        """
        from febed.run import after_step

        dem = self.dem
        dt = dem.dt
        if self.good is None:
            if self.restarted_from is None:
                self.output(scheduled=False)
            elif dem.time >= self.next_out - 0.5 * dt:  # due when the run before stopped on an output error
                self.output()
            else:
                self.good = self.capture()
        self.status("running")
        while dem.time < end - 0.5 * dt:
            target = min(end, self.next_out, self.next_ckpt)
            n = max(1, int(round((target - dem.time) / dt)))
            try:
                dem.advance(min(n, CHUNK), dt)
            except DEMFailure as e:  # raised on every rank
                self.fail(f"the particles blew up: {e}")
                raise
            except StopRequested:  # a stop signal, agreed on every rank: the particles are at a whole step
                pass  # `after_step` below writes the checkpoint and stops
            x = dem.particles.pos[: dem.particles.n_owned]
            gone = np.any((x < self.lo) | (x > self.hi), axis=1)
            if gone.any():
                self.left += int(gone.sum())
                dem.remove_particles(gone)
            if dem.time >= self.next_out - 0.5 * dt:
                self.output()
            if after_step(self, dem.time, dem.time >= self.next_ckpt - 0.5 * dt):
                self.progress(end)
        self.progress(end)
        self.display.end()

    def progress(self, end: float) -> None:
        """The progress line: simulated time, steps, particles, particles left, wall time rate, ETA (collective)."""
        now = time.perf_counter()
        self._last_progress = now
        dem = self.dem
        self.display.show(
            f"t = {dem.time:.5f} / {end:g} s  step {dem.steps}  {dem.count()} particles  "
            f"{self.comm.allreduce(self.left)} left  {self._meter.text(dem.time, end, now)}"
        )

    def fail(self, message: str) -> None:
        """Record a failure: write the last good state as a checkpoint and the status (collective)."""
        from febed.run import record_failure

        record_failure(self, message)

    def close(self, last_output: bool = True) -> None:
        """Nothing to close: every particle output is a complete file of its own."""

    def catch_signals(self):
        """Handle `febed.run.STOP_SIGNALS` by stopping within a second (`DEM.stop_check`); returns the restorer."""
        from febed.run import catch_stop_signals

        return catch_stop_signals(self, "these DEM steps", self.dem)


CHUNK = 500  # DEM steps per `advance` call between output, signal and progress checks


def run(case, outdir, log, comm=MPI.COMM_WORLD, restart=None) -> DEM:
    """Run a pure-DEM case to `run.end_time` (called by `febed run`); returns the DEM.

    `restart`: a checkpoint file or run folder to continue from (its newest valid checkpoint).
    """
    from febed import restart as rs
    from febed.io.checkpoint import load_checkpoint
    from febed.run import run_to_end

    ckpt = None
    if restart is not None:
        ckpt = load_checkpoint(Path(restart), comm)
        rs.check_restartable(ckpt[2], case)
    r = DEMRun(case, outdir, log, comm, restart=ckpt)
    dem = r.dem
    start = f"restarted from {r.restarted_from} at t = {dem.time:.6g} s" if ckpt else "DEM"
    end = case.run.end_time
    log.info(f"{start}: {dem.count()} particles on {comm.size} process(es), dt = {dem.dt:.3e} s "
             f"(T_C/{dem.params.dt_factor:g}), {dem.params.integrator}, law {dem.params.contact_model}, "
             f"to t = {end:g} s")  # fmt: skip
    wall0 = time.time()
    run_to_end(r, end)
    left = comm.allreduce(r.left)
    log.info(
        f"DEM done: t = {dem.time:.5f} s, {dem.steps} steps in {time.time() - wall0:.1f} s; "
        f"max overlap {100 * dem.global_max(dem.max_overlap):.3f} % d; {left} particles left the domain"
    )
    if dem.exchange is not None:
        t = dem.exchange.timers
        log.info("particle exchange: " + ", ".join(f"{k} {comm.allreduce(v, op=MPI.MAX):.2f} s" for k, v in t.items())
                 + f"; {comm.allreduce(dem.exchange.migrated)} migrations")  # fmt: skip
    return dem


def _log_balance(dem: DEM, log) -> None:
    """Log the particle load imbalance max/mean over ranks (collective; nothing on one process)."""
    if dem.exchange is None:
        return
    from febed.parallel.exchange import balance_line

    total, ghosts = dem.exchange.counts(dem.particles)
    line = balance_line(dem.exchange.comm, dem.particles.n_owned, dem.pairs.size)
    log.info(f"{line}; {total} particles, {ghosts} ghosts")
