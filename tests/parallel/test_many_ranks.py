"""Distributed particles on any number of ranks, with partition corners (run serially and under `mpirun -n K`).

The mesh is a box cut into a grid of blocks, `MPI.Compute_dims(K, 3)` of them (`block_partitioner`): 2 ranks
cut it in two slabs, 3 in three, 4 in four columns meeting at a line (a 2 x 2 arrangement), 8 in eight blocks
meeting at a point (2 x 2 x 2). The particles sit at the partition corner nearest the centre, so the halo of a
particle there reaches every rank that meets at that corner, and particles that move cross from one block to
a diagonal neighbour, through cells that neither rank holds as a ghost (the mesh ghosts share a facet only).
On one rank the same tests run against the serial DEM with an exchange over a single rank.

`test_a_checkpoint_written_on_4_ranks_restarts_on_2_then_on_1` runs `febed run` under `mpirun -n 4`, then
`-n 2`, then serially, as users do: it is a serial test that starts its own MPI runs.
"""

import shutil
import subprocess
import sys
from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest
from _febed_process import MPIRUN, clean_env

from febed.dem import DEM, DEMParams
from febed.parallel import ParticleExchange, block_partitioner
from febed.parallel.state import gather_state

COMM = MPI.COMM_WORLD
D, RHO = 1e-3, 2500.0
L = 0.024  # the box [0, L]^3


def blocks_of(comm) -> list[int]:
    """Blocks per axis for the ranks of `comm`: 1 -> 1x1x1, 2 -> 2x1x1, 3 -> 3x1x1, 4 -> 2x2x1, 8 -> 2x2x2."""
    return list(MPI.Compute_dims(comm.size, 3))


def cells_of(blocks) -> list[int]:
    """Cells per axis: a multiple of the blocks, so that the partition boundaries are the planes x = k L / blocks."""
    return [b * max(1, 6 // b) for b in blocks]


def corner_of(blocks) -> np.ndarray:
    """The partition corner nearest the centre: on every cut axis the middle cut plane, elsewhere L / 2."""
    return np.array([(b // 2) * L / b if b > 1 else 0.5 * L for b in blocks])


def block_exchange(comm=COMM):
    """An exchange over a hexahedral mesh of the box cut into `blocks_of(comm)` blocks, one per rank."""
    import dolfinx.mesh as dm

    blocks, cells = blocks_of(comm), cells_of(blocks_of(comm))
    mesh = dm.create_box(comm, [[0, 0, 0], [L, L, L]], cells, dm.CellType.hexahedron, dm.GhostMode.shared_facet,
                         block_partitioner(cells, blocks))  # fmt: skip
    return ParticleExchange.from_mesh(mesh)


def meeting(blocks) -> int:
    """How many blocks (ranks) meet at the corner of `corner_of(blocks)`."""
    return int(np.prod([min(b, 2) for b in blocks]))


def block_index(pos, blocks) -> np.ndarray:
    """(n, 3) block coordinates of the points `pos`."""
    b = np.array(blocks)
    return np.minimum((np.asarray(pos) / L * b).astype(np.int64), b - 1)


def gathered(dem, *fields):
    """gid and the given fields of every rank's owned particles, sorted by gid (the same on every rank)."""
    P = dem.particles
    n = P.n_owned
    parts = COMM.allgather([P.gid[:n].copy()] + [getattr(P, f)[:n].copy() for f in fields])
    gid = np.concatenate([p[0] for p in parts])
    o = np.argsort(gid)
    return [gid[o]] + [np.concatenate([p[k + 1] for p in parts])[o] for k in range(len(fields))]


def by_gid(dem, *fields):
    """gid and fields of a serial DEM's particles, sorted by gid."""
    P = dem.particles
    o = np.argsort(P.gid[: P.n_owned])
    return [P.gid[o]] + [getattr(P, f)[: P.n_owned][o] for f in fields]


def corner_cluster(integrator, n_side=6, spacing=0.99, seed=3, **kw):
    """n_side^3 spheres on a jittered lattice around the partition corner, pressed together, moving and spinning."""
    p = DEMParams(contact_model="linear-history", stiffness=1000.0, restitution_pp=0.6, friction_pp=0.4, gravity=0.0,
                  integrator=integrator, **kw)  # fmt: skip
    dem = DEM(p)
    rng = np.random.default_rng(seed)
    k = np.arange(n_side**3)
    idx = np.stack([k % n_side, (k // n_side) % n_side, k // n_side**2], axis=1) - 0.5 * (n_side - 1)
    pos = corner_of(blocks_of(COMM)) + idx * spacing * D + rng.uniform(-0.02, 0.02, (k.size, 3)) * D
    dem.add_particles(pos, D, RHO, vel=rng.normal(0, 0.05, (k.size, 3)), omega=rng.normal(0, 50.0, (k.size, 3)))
    return dem


def owners(dem) -> np.ndarray:
    """The rank holding each particle, by gid (the same on every rank)."""
    P = dem.particles
    n = P.n_owned
    gid = np.concatenate(COMM.allgather(P.gid[:n].copy()))
    return np.concatenate(COMM.allgather(np.full(n, COMM.rank)))[np.argsort(gid)]


@pytest.mark.mpi
@pytest.mark.parametrize("dim", [2, 3])
def test_block_partitioner_gives_each_rank_its_block(dim):
    """Rank r owns the cells of block r, (bz * blocks_y + by) * blocks_x + bx, and nothing else."""
    import dolfinx.mesh as dm

    blocks = list(MPI.Compute_dims(COMM.size, dim))
    cells = cells_of(blocks)
    part = block_partitioner(cells, blocks)
    if dim == 2:
        mesh = dm.create_rectangle(COMM, [[0, 0], [L, L]], cells, dm.CellType.quadrilateral, dm.GhostMode.shared_facet,
                                   part)  # fmt: skip
    else:
        mesh = dm.create_box(COMM, [[0, 0, 0], [L, L, L]], cells, dm.CellType.hexahedron, dm.GhostMode.shared_facet,
                             part)  # fmt: skip
    ex = ParticleExchange.from_mesh(mesh)
    own = ex.ma.bbox[: ex.ma.num_owned_cells, :, :dim]
    stride = np.cumprod([1] + blocks[:-1])
    mine = [(COMM.rank // stride[a]) % blocks[a] for a in range(dim)]
    size = L / np.array(blocks)
    lo, hi = own[:, 0].min(axis=0), own[:, 1].max(axis=0)
    got = COMM.allgather((ex.ma.num_owned_cells, np.abs(lo - np.multiply(mine, size)).max(),
                          np.abs(hi - (np.multiply(mine, size) + size)).max()))  # fmt: skip
    assert all(n == int(np.prod(cells)) // COMM.size for n, _, _ in got), got  # same share on every rank
    assert max(max(a, b) for _, a, b in got) <= 1e-12 * L, got


def test_block_partitioner_refuses_bad_blocks():
    import dolfinx.mesh as dm

    with pytest.raises(ValueError, match="one per axis"):
        block_partitioner([4, 4, 4], [2, 1])
    with pytest.raises(ValueError, match="blocks <= cells"):
        block_partitioner([4, 4, 4], [5, 1, 1])
    if COMM.size == 1:
        with pytest.raises(ValueError, match="make 2 blocks, but the mesh is partitioned on 1 ranks"):
            dm.create_box(COMM, [[0, 0, 0], [L, L, L]], [4, 4, 4], dm.CellType.hexahedron, dm.GhostMode.shared_facet,
                          block_partitioner([4, 4, 4], [2, 1, 1]))  # fmt: skip


@pytest.mark.mpi
@pytest.mark.parametrize("integrator", ["verlet", "rk2"])
def test_forces_next_to_a_partition_corner_equal_the_serial_forces(integrator):
    """Every pair force at the corner is computed from ghost copies held by all the ranks meeting there."""
    blocks = blocks_of(COMM)
    ex = block_exchange()
    ref, par = corner_cluster(integrator), corner_cluster(integrator)
    par.attach_exchange(ex, distribute=True)
    dt = ref.dt
    assert par.dt == dt
    # the halo of the particles at the corner reaches every rank meeting there: count the copies of each gid
    par.advance(1, dt)
    ref.advance(1, dt)
    P = par.particles
    held = np.concatenate(COMM.allgather(P.gid[: P.n].copy()))
    copies = np.bincount(held, minlength=216)
    assert copies.max() >= meeting(blocks), (copies.max(), blocks)
    corner = corner_of(blocks)
    m = RHO * np.pi / 6 * D**3

    def pull(P):
        """A spring towards the corner (10 chunks of 10 steps) keeps the cluster pressed together."""
        return -m * 5e6 * (P.pos[: P.n_owned] - corner)

    for chunks in (0, 10):  # fresh contacts, then contacts with sliding history
        for _ in range(chunks):
            par.advance(10, dt, pull(par.particles))
            ref.advance(10, dt, pull(ref.particles))
        gid, x, f, t = gathered(par, "pos", "force", "torque")
        rgid, rx, rf, rt = by_gid(ref, "pos", "force", "torque")
        assert np.array_equal(gid, rgid) and np.array_equal(gid, np.arange(216))  # none lost, none duplicated
        near = np.linalg.norm(x - corner, axis=1) < 1.5 * D  # next to the corner: neighbours on every rank there
        assert near.sum() >= 8 and np.unique(owners(par)[near]).size == meeting(blocks)
        fs, ts = np.abs(rf).max(), np.abs(rt).max()
        dev = np.abs(f - rf).max() / fs, np.abs(t - rt).max() / ts
        print(f"{integrator} on {COMM.size} ranks {blocks}, {10 * chunks} steps: force deviation {dev[0]:.1e}, "
              f"torque {dev[1]:.1e}; at the corner {np.abs(f - rf)[near].max() / fs:.1e}")  # fmt: skip
        assert fs > 0 and ts > 0
        tol = 1e-14 if chunks == 0 else 1e-11  # the order of summation, then its growth over 100 steps
        assert dev[0] <= tol and dev[1] <= tol, dev
        assert np.abs(x - rx).max() <= tol * L


@pytest.mark.mpi
def test_migration_through_partition_corners_loses_and_duplicates_nothing_and_conserves_momentum():
    """A colliding cloud shaken back and forth along the diagonal through the corner where the ranks meet.

    The square-wave force points along the cut axes together (x and y for 4 ranks, x, y and z for 8), so
    particles cross diagonally from a block to the one opposite it, past the corner. The gid set is checked
    after every chunk, the momentum against the impulse of the forces, and the trajectories against the
    serial DEM as long as the granular gas has not amplified the round-off.
    """
    blocks = blocks_of(COMM)
    ex = block_exchange()
    p = dict(
        contact_model="linear-history", stiffness=200.0, restitution_pp=0.8, friction_pp=0.3, gravity=0.0, skin=0.5
    )
    par, ref = DEM(DEMParams(**p)), DEM(DEMParams(**p))
    rng = np.random.default_rng(2)
    corner = corner_of(blocks)
    cut = np.array([1.0 if b > 1 else 0.0 for b in blocks])
    axis = cut / np.linalg.norm(cut) if cut.any() else np.array([0.0, 0.0, 1.0])
    k = np.arange(216)
    pos = corner + (np.stack([k % 6, (k // 6) % 6, k // 36], axis=1) - 2.5) * 1.1 * D
    # the amplitude acc period^2 / 32 along the diagonal: up to 4 mm, the cloud (3.25 mm about its centre at the
    # start, spreading) staying inside the box, where the mesh decides the owners
    room = min((min(c, L - c) - 5 * D) / a for c, a in zip(corner, axis, strict=True) if a > 0)
    for dem in (par, ref):
        dem.add_particles(pos, D, RHO)
    dt = ref.dt
    chunk, half = 20, 12  # the force changes sign every 12 chunks of 20 steps (a period of about 15 ms)
    period = 2 * half * chunk * dt
    acc = 32 * min(4 * D, room) / period**2
    vel = rng.normal(0, 0.05, (216, 3)) - acc * period / 4 * axis
    for dem in (par, ref):
        assert np.array_equal(dem.particles.gid, k)  # rows in insertion order until the first step
        dem.particles.vel[:] = vel
        dem.touch()
    par.attach_exchange(ex, distribute=True)
    m = RHO * np.pi / 6 * D**3
    assert par.dt == dt

    def force(P, c):
        """A weak spring pulling each particle back to the corner (the cloud stays in the box), and the square wave."""
        n = P.n_owned
        f = -m * 2000.0 * (P.pos[:n] - corner)
        return f + m * acc * (1.0 if c % (2 * half) < half else -1.0) * axis

    impulse = np.zeros(3)
    holder = blk = None
    changes = diagonal = 0
    dev = []
    for c in range(3 * 2 * half):
        f = force(par.particles, c)
        impulse += COMM.allreduce(f.sum(axis=0)) * chunk * dt
        par.advance(chunk, dt, f)
        ref.advance(chunk, dt, force(ref.particles, c))
        gid, x = gathered(par, "pos")
        assert np.array_equal(gid, np.arange(216)), "particles lost or duplicated"
        rank_now = owners(par)
        b = block_index(x, blocks)
        lo = np.stack([(rank_now // np.prod(blocks[:a], dtype=int)) % blocks[a] for a in range(3)], axis=1)
        lo = lo * L / np.array(blocks)
        away = np.max(np.maximum(lo - x, 0.0) + np.maximum(x - (lo + L / np.array(blocks)), 0.0), axis=1)
        assert np.all((x > 0) & (x < L)), (x.min(axis=0), x.max(axis=0))  # inside the mesh, where cells decide owners
        assert away.max() <= 0.25 * D + 1e-15, away.max()  # each within half the skin of its owner's cells
        if holder is not None:
            changes += int(np.sum(rank_now != holder))
            diagonal += int(np.sum(np.sum(b != blk, axis=1) >= 2))  # moved to a block touching its own at an edge
        holder, blk = rank_now, b
        dev.append(np.abs(x - by_gid(ref, "pos")[1]).max() / L)
    P = par.particles
    mom = COMM.allreduce((P.mass[: P.n_owned, None] * P.vel[: P.n_owned]).sum(axis=0))
    err = np.abs(mom - (m * vel.sum(axis=0) + impulse)).max() / (216 * m * acc * period / 4)
    moved = COMM.allreduce(ex.migrated)
    print(f"corner stress on {COMM.size} ranks {blocks}: {changes} changes of rank ({diagonal} diagonal), "
          f"{moved} migrations, amplitude {acc * period**2 / 32 * 1e3:.2f} mm, momentum error {err:.1e}, "
          f"deviation from serial after 1 chunk {dev[0]:.1e} L, after {len(dev)} {dev[-1]:.1e} L")  # fmt: skip
    assert err <= 1e-12
    assert moved >= changes
    assert dev[0] <= 1e-12  # then the granular gas amplifies the round-off of the summation order
    if COMM.size > 1:
        assert changes > 200, changes
    if meeting(blocks) >= 4:
        assert diagonal > 50, diagonal  # particles crossed at the corner, not only through the faces


def pressed(dem, chunks: int, dt: float):
    """`chunks` times 10 steps of the corner cluster pulled towards the corner (a spring): its contacts last."""
    m = RHO * np.pi / 6 * D**3
    corner = corner_of(blocks_of(COMM))
    for _ in range(chunks):
        P = dem.particles
        dem.advance(10, dt, -m * 1e6 * (P.pos[: P.n_owned] - corner))


def same_state(a: dict, b: dict):
    """Two merged states hold the same particles with the same fields and the same contact history."""
    assert np.array_equal(a["p_gid"], b["p_gid"])
    for k in ("p_pos", "p_vel", "p_omega", "p_force", "p_diameter", "p_mass", "saved_keys", "saved_vals"):
        assert np.array_equal(np.asarray(a[k]), np.asarray(b[k])), k
    assert (a["time"], a["steps"]) == (b["time"], b["steps"])


@pytest.mark.mpi
def test_a_checkpoint_of_n_ranks_is_read_on_half_of_them_then_on_one(mpi_tmp_path):
    """N ranks write a checkpoint, N // 2 of them (a sub-communicator) read it and write one, a single rank reads that.

    Each reader holds the same particles and contact history as were written, and the run continued through
    both restarts follows the run continued on N ranks to round-off. The particles are the corner cluster,
    pressed together: every contact lasts and carries sliding history.
    """
    n_write = COMM.size
    n_half = max(1, n_write // 2)
    straight = corner_cluster("rk2", n_side=8, spacing=1.0)
    straight.attach_exchange(block_exchange(), distribute=True)
    dt = straight.dt
    pressed(straight, 10, dt)
    first = gather_state(straight)
    if COMM.rank == 0:
        np.savez(mpi_tmp_path / "on_n.npz", **first)
    pressed(straight, 20, dt)
    end = COMM.bcast(gather_state(straight), root=0)
    assert COMM.bcast(first["saved_keys"].size if COMM.rank == 0 else None) > 1000  # the history matters

    half = COMM.Split(0 if COMM.rank < n_half else MPI.UNDEFINED, COMM.rank)
    read_half = written_half = None
    if half != MPI.COMM_NULL:
        with np.load(mpi_tmp_path / "on_n.npz") as f:
            state = dict(f)
        dem = corner_cluster("rk2", n_side=8, spacing=1.0)
        dem.set_state(state)
        dem.attach_exchange(block_exchange(half), distribute=True)
        assert dem.exchange.comm.size == n_half
        read_half = gather_state(dem)  # what the half holds, before it steps
        pressed(dem, 10, dt)
        written_half = gather_state(dem)
        if half.rank == 0:
            np.savez(mpi_tmp_path / "on_half.npz", **written_half)
        half.Free()
    COMM.barrier()
    read_half, written_half = COMM.bcast((read_half, written_half), root=0)
    with np.load(mpi_tmp_path / "on_n.npz") as f:
        first = dict(f)
    same_state(read_half, first)
    with np.load(mpi_tmp_path / "on_half.npz") as f:
        state = dict(f)
    same_state(state, written_half)
    serial = corner_cluster("rk2", n_side=8, spacing=1.0)  # every rank reads it alone, without an exchange
    serial.set_state(state)
    assert np.array_equal(np.sort(serial.particles.gid), first["p_gid"])
    pressed(serial, 10, dt)
    gid, x, v = by_gid(serial, "pos", "vel")
    assert np.array_equal(gid, end["p_gid"]) and np.array_equal(gid, np.arange(512))
    dev = np.abs(x - end["p_pos"]).max() / L
    print(f"restart {n_write} -> {n_half} -> 1 ranks: position deviation from the run on {n_write} ranks {dev:.1e} L")
    assert dev <= 1e-11
    assert np.abs(v - end["p_vel"]).max() <= 1e-8 * np.abs(end["p_vel"]).max()
    assert serial.steps == end["steps"] == 300 and serial.time == pytest.approx(end["time"], rel=1e-14)


# ------------------------------------------------------------------------------------ febed run, 4 -> 2 -> 1 ranks
CASE = """
[run]
mode = "dem"
end_time = {end}
gravity = 1000.0  # the particles pile up on the floor within 4 ms: contacts with history

[mesh]
builtin = "box"
extent = [0.024, 0.024, 0.03]
size = 0.006

[gas.boundary.inlet]
type = "inlet"
velocity = 0.0

[gas.boundary.walls]
type = "wall"

[gas.boundary.outlet]
type = "outlet"
particles = false

[particles]
diameter = 0.002
count = 500
region = [0.0, 0.0, 0.0, 0.024, 0.024, 0.016]

[contact]
stiffness = 1e5

[output]
particle_interval = 0.002
checkpoint_interval = 0.01  # one at the end of each segment
keep_checkpoints = 5
directory = "{out}"
"""


def febed_run(ranks: int, case: Path, *extra):
    cmd = [sys.executable, "-m", "febed.cli", "run", str(case), *extra]
    if ranks > 1:
        assert MPIRUN[1:3] == ["-n", "2"], MPIRUN  # the 2-rank command line, with the rank count replaced
        cmd = [MPIRUN[0], "-n", str(ranks), *MPIRUN[3:], *cmd]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=900, env=clean_env())
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]


def checkpoints(out: Path):
    """DEM step -> (state by gid, ranks, time, pair-history entries of a distributed run) of every checkpoint."""
    from febed.io.checkpoint import list_checkpoints, read_checkpoint

    got = {}
    for path in list_checkpoints(out / "checkpoints"):
        state, meta = read_checkpoint(path)
        order = np.argsort(state["dem/p_gid"])
        rows = {k: state[f"dem/p_{k}"][order] for k in ("gid", "pos", "vel")}
        keys = [state.get(f"dem/{k}", np.zeros(0)) for k in ("saved_keys", "saved_wkeys")]
        history = sum(k.size for k in keys)  # pairs and walls (a one-rank checkpoint keeps its lists instead)
        got[int(meta["step"])] = (rows, int(meta["ranks"]), float(meta["time"]), history)
    return got


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("mpirun") is None, reason="needs mpirun")
def test_a_checkpoint_written_on_4_ranks_restarts_on_2_then_on_1(tmp_path):
    """`febed run` of a pure-DEM case on 4 ranks to 4 ms, continued with --restart on 2 ranks to 4.2 ms, then
    serially to 4.4 ms, against the same three segments run on 4 ranks each: the same particles in each
    segment's last checkpoint and the same positions to round-off. The particles are piling up on the floor by
    then, which amplifies round-off about a hundredfold per millisecond: the restarted segments are short."""
    if COMM.size > 1:
        pytest.skip("starts its own MPI runs: run it serially")
    runs = {}
    for name, ranks in (("on4", (4, 4, 4)), ("on421", (4, 2, 1))):
        (tmp_path / name).mkdir()
        case = tmp_path / name / "case.toml"
        case.write_text(CASE.format(end=0.004, out=tmp_path / name / "run"))
        febed_run(ranks[0], case)
        febed_run(ranks[1], case, "--restart", "--set", "run.end_time=0.0042")
        febed_run(ranks[2], case, "--restart", "--set", "run.end_time=0.0044")
        runs[name] = checkpoints(tmp_path / name / "run")
    a, b = runs["on4"], runs["on421"]
    steps = sorted(a)
    assert steps == sorted(b) and len(steps) == 3, (steps, sorted(b))  # the end of each segment
    assert [round(a[k][2], 5) for k in steps] == [0.004, 0.0042, 0.0044]
    assert [a[k][1] for k in steps] == [4, 4, 4] and [b[k][1] for k in steps] == [4, 2, 1]
    assert a[steps[0]][3] > 50  # contacts with sliding history where the run is split
    for k in steps:
        (ra, _, t, _), (rb, _, _, _) = a[k], b[k]
        assert np.array_equal(ra["gid"], rb["gid"]) and np.array_equal(ra["gid"], np.arange(500)), t
        dev = np.abs(ra["pos"] - rb["pos"]).max()
        print(f"t = {t:.6f} s: position deviation {dev:.1e} m")
        assert dev <= 1e-9 * 0.03, (t, dev)
