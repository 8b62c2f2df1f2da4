"""The coupled loop: momentum exchange consistency, terminal velocity, fixed-bed Ergun, fluidized bed."""

import logging
import math
from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest

from febed.bed import walls_from_mesh
from febed.case import _merge, load_case
from febed.dem.solver import DEM
from febed.gas.vans import VANSSolver
from febed.meshing import load_case_mesh
from febed.solver import CoupledSolver

LOG = logging.getLogger("febed.test")
ROOT = Path(__file__).resolve().parents[1]


def box_case(tmp_path, extent, size, **sections):
    """A case on a built-in box: inlet at the bottom, outlet on top, walls around (override by sections)."""
    data = {
        "run": {"mode": "cfd-dem"},
        "mesh": {"builtin": "box", "extent": list(extent), "size": size},
        "gas": {"boundary": {"walls": {"type": "wall", "slip": True}, "outlet": {"type": "outlet"}}},
        "output": {"directory": str(tmp_path / "out")},
    }
    return load_case(data=_merge(data, sections))


def coupled(case, tmp_path, positions, diameter, density):
    """A CoupledSolver on the case's mesh with particles at `positions` (no insertion, no packing)."""
    md = load_case_mesh(case, cache_dir=tmp_path / "mesh")
    dem = DEM.from_case(case, walls=walls_from_mesh(case, md), dim=md.gdim)
    dem.add_particles(np.asarray(positions, dtype=float), diameter, density)
    return CoupledSolver(case, md, dem, VANSSolver.from_case(case, md), LOG)


def lattice(lo, hi, spacing):
    axes = [np.arange(a + spacing / 2, b, spacing) for a, b in zip(lo, hi, strict=True)]
    return np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)


def lattice_bed(tmp_path):
    """A lattice of 1 mm beads 6 mm deep at the bottom of a 1 x 1 x 3 cm box, air at 0.1 m/s (not stepped)."""
    case = box_case(
        tmp_path, (0.01, 0.01, 0.03), 0.002, gas={"boundary": {"inlet": {"type": "inlet", "velocity": 0.1}}}
    )
    return coupled(case, tmp_path, lattice((0, 0, 0), (0.01, 0.01, 0.006), 0.002), 1e-3, 2500.0)


def exchange_bed(tmp_path, coupling, **sections):
    """729 beads of 1 mm in a 1 cm cube at the bottom of a 1 x 1 x 3 cm box, air at 0.3 m/s, after 5 gas steps."""
    case = box_case(
        tmp_path,
        (0.01, 0.01, 0.03),
        0.002,
        gas={"boundary": {"inlet": {"type": "inlet", "velocity": 0.3}}},
        coupling={"filter_passes": 0, "drag": "gidaspow-blend", **coupling},
        contact={"stiffness": 10.0},
        **sections,
    )
    rng = np.random.default_rng(1)
    pos = lattice((0, 0, 0), (0.01, 0.01, 0.01), 0.0011) + rng.uniform(-1e-5, 1e-5, (729, 3))
    s = coupled(case, tmp_path, pos, 1e-3, 2500.0)
    for _ in range(5):
        s.step()  # a developed, non-uniform gas field
    return s


def test_momentum_exchange_is_newtons_third_law(tmp_path):
    """What the particles receive from the gas, the gas gives: Σ_p K_p(u@p − v_p) = Σ_i ΔV_i K_i(u_i − v̄_i)."""
    s = exchange_bed(tmp_path, {})  # the particles move
    K, f_drag, _ = s.fluid_state()
    v = s.dem.particles.vel[: s.dem.particles.n_owned]
    received = f_drag.sum(axis=0)  # F_D = K_p (u@p − v_p)
    _, K_i, Kv_i, _ = s.project()
    dV = s.ma.node_volume
    given = (dV[:, None] * (K_i[:, None] * s.gas.u - Kv_i)).sum(axis=0)
    assert np.abs(received).max() > 1e-6  # a real exchange
    assert np.allclose(given, received, rtol=1e-12, atol=1e-12 * np.abs(received).max())
    for passes in (1, 3):  # filtered: the totals of K and K v are still conserved exactly
        s.coupler.filter_passes = passes
        _, K_i, Kv_i, _ = s.project()
        assert math.isclose((dV * K_i).sum(), K.sum(), rel_tol=1e-12)
        assert np.allclose((dV[:, None] * Kv_i).sum(axis=0), (K[:, None] * v).sum(axis=0), rtol=1e-11, atol=1e-18)


@pytest.mark.mpi
@pytest.mark.parametrize("passes", [0, 1, 2])
def test_nodal_pressure_gradient_reaction_is_exactly_minus_what_the_particles_receive(mpi_tmp_path, passes):
    """`pressure_gradient_reaction = "nodal"`: the gas receives (1 − ε_i)∇p_i at every local node (ghosts
    included); the particles interpolate ∇p averaged by the filter's transpose, so that with any number of
    filter passes the gas's total is minus theirs, Σ_p F_P, to round-off (particles at rest)."""
    comm = MPI.COMM_WORLD
    coupling = {"pressure_gradient_reaction": "nodal", "filter_passes": passes}
    s = exchange_bed(mpi_tmp_path, coupling, particles={"fixed": True})
    _, _, f_p = s.fluid_state()  # F_P = −V_p ∇p@p from the current gas
    eps, _, _, F = s.project()
    assert np.array_equal(F, (1.0 - eps)[:, None] * s.gas.grad_p)
    n = s.ma.num_owned_dofs
    given = comm.allreduce((s.ma.node_volume[:n, None] * F[:n]).sum(axis=0))
    received = comm.allreduce(f_p.sum(axis=0))
    assert received[2] > 1e-4  # ∇p points down through the bed: F_P lifts it
    assert np.allclose(given, -received, rtol=1e-11, atol=1e-11 * np.abs(received).max())
    if passes:  # given the gas's own ∇p, the particles would receive in total more than round-off apart
        _, _, gp = s.coupler.gas_at_particles(s.gas.u, s.gas.eps, s.gas.grad_p)
        plain = comm.allreduce((math.pi / 6 * 1e-9 * gp).sum(axis=0))
        assert abs(plain[2] - given[2]) > 1e-4 * abs(given[2]), (plain, given)


@pytest.mark.mpi
@pytest.mark.parametrize("reaction", ["nodal", "projected"])
def test_the_gas_step_carries_the_nodal_reactions_share_of_the_pressure(mpi_tmp_path, reaction):
    """With the nodal reaction the gas step is given the pressure's share ε (the void fraction it is given), so
    that it ends with −ε∇p^{n+1}; with the projected reaction the gas carries the whole −∇p (no share)."""
    s = exchange_bed(mpi_tmp_path, {"pressure_gradient_reaction": reaction}, particles={"fixed": True})
    seen = {}
    step = s.gas.step

    def spy(dt, **kw):
        seen.update(kw)
        return step(dt, **kw)

    s.gas.step = spy
    s.step()
    if reaction == "nodal":
        assert np.array_equal(seen["pressure_share"], seen["eps"])
        assert MPI.COMM_WORLD.allreduce(float(seen["eps"].min()), op=MPI.MIN) < 0.9  # the bed's ε
    else:
        assert seen["pressure_share"] is None


def test_particle_locations_are_current_exactly_when_the_rows_are_unchanged(tmp_path):
    s = lattice_bed(tmp_path)
    s.step()
    assert s.located  # the projection located the particles at the end of the step
    s.dem.advance(1)
    assert not s.located
    s.locate_particles()
    assert s.located
    s.dem.remove_particles(np.array([0]))
    assert not s.located
    s.step()
    assert s.located and s.coupler.cell.size == s.dem.particles.n_owned


@pytest.mark.mpi
def test_rows_changed_on_one_rank_are_located_again_on_every_rank(mpi_tmp_path, monkeypatch):
    """PCPM events, and the ghost rows they drop, change the rows of some ranks only (`DEM.touch`). Locating the
    particles is collective (its migration check), so at the next gas step every rank locates them again."""
    comm = MPI.COMM_WORLD
    s = lattice_bed(mpi_tmp_path)
    s.step()
    calls = []

    def located_without_collectives(self):  # records each call; the rows did not really change
        calls.append(self.dem.layout)
        self._located = self.dem.layout

    monkeypatch.setattr(CoupledSolver, "locate_particles", located_without_collectives)
    if comm.rank == comm.size - 1:
        s.dem.touch()
    s.step()
    # before the fluid forces of the DEM sub-steps, and after them for the projection: on every rank
    assert comm.allgather(len(calls)) == [2] * comm.size


@pytest.mark.mpi
def test_a_fluid_record_missing_on_one_rank_is_made_again_on_every_rank(mpi_tmp_path, monkeypatch):
    """Rows added without their fluid record (PCPM children restarted on other ranks) may sit on one rank only;
    the projection then makes the record again, which is collective, on every rank."""
    from febed.coupling.drag import RECORD_SET
    from febed.solver import FLUID

    comm = MPI.COMM_WORLD
    s = lattice_bed(mpi_tmp_path)
    s.step()
    calls = []

    def record_without_collectives(self, relocate, drag=None):  # marks the rows filled, keeps their values
        calls.append(relocate)
        self.dem.particles.aux(FLUID)[:, RECORD_SET] = 1.0
        return math.inf

    monkeypatch.setattr(CoupledSolver, "_fluid", record_without_collectives)
    P = s.dem.particles
    if comm.rank == comm.size - 1 and P.n_owned:
        P.aux(FLUID)[0, RECORD_SET] = 0.0
    s.project()
    assert comm.allgather(calls) == [[False]] * comm.size


@pytest.mark.mpi
def test_a_checkpoint_of_another_mesh_is_refused_on_every_rank(mpi_tmp_path):
    """A node without its counterpart in the checkpoint may be on one rank only: every rank raises the error."""
    from febed.io.checkpoint import CheckpointError
    from febed.io.state import gas_arrays, restore_gas

    comm = MPI.COMM_WORLD
    case = box_case(mpi_tmp_path, (0.01, 0.01, 0.03), 0.002)
    gas = VANSSolver.from_case(case, load_case_mesh(case, cache_dir=mpi_tmp_path / "mesh"))
    saved = comm.bcast(gas_arrays(gas) if comm.rank == 0 else None)  # rank 0's nodes only
    if comm.size == 1:
        saved["gas/x"][0] += 1e-4  # a node moved by 0.1 mm
    with pytest.raises(CheckpointError, match="has no counterpart in the checkpoint"):
        restore_gas(gas, saved, 0.0, comm)


def schiller_naumann_terminal(d, rho_p, rho_g, mu, g):
    """Terminal velocity of a sphere (m/s): (ρ_p − ρ_g) V g = 3π μ d v (1 + 0.15 Re^0.687), by bisection."""
    lo, hi = 0.0, (rho_p - rho_g) * g * d * d / (18 * mu)
    for _ in range(200):
        v = 0.5 * (lo + hi)
        re = rho_g * v * d / mu
        drag = 3 * math.pi * mu * d * v * (1 + 0.15 * re**0.687)
        lo, hi = (v, hi) if drag < (rho_p - rho_g) * math.pi / 6 * d**3 * g else (lo, v)
    return 0.5 * (lo + hi)


def test_single_particle_reaches_schiller_naumann_terminal_velocity(tmp_path):
    d, rho_p, rho_g, mu = 50e-6, 2500.0, 1.2, 1.8e-5
    case = box_case(
        tmp_path,
        (0.04, 0.04, 0.06),
        0.01,
        gas={"density": rho_g, "viscosity": mu, "dt_max": 1e-3},
        coupling={"drag": "schiller-naumann"},
        contact={"stiffness": 1e-4},  # no contacts happen; a soft spring keeps the DEM step near the gas step
    )
    s = coupled(case, tmp_path, [[0.021, 0.019, 0.05]], d, rho_p)
    tau = rho_p * d * d / (18 * mu)
    while s.t < 10 * tau:
        s.step()
    v = -s.dem.particles.vel[0, 2]
    expected = schiller_naumann_terminal(d, rho_p, rho_g, mu, 9.81)
    assert abs(v / expected - 1) < 0.01, (v, expected)
    assert abs(s.dem.particles.vel[0, 0]) < 1e-3 * v


def test_fixed_bed_pressure_drop_is_ergun(tmp_path):
    """Gas through a fixed lattice bed (uniform ε = 1 − π/6): the pressure gradient is Ergun's within 3 %."""
    d, rho_g, mu, U = 1e-3, 1.2, 1.8e-5, 0.1
    case = box_case(
        tmp_path,
        (0.01, 0.01, 0.03),
        0.002,
        gas={
            "density": rho_g,
            "viscosity": mu,
            "dt_max": 1e-3,
            "boundary": {"inlet": {"type": "inlet", "velocity": U}},
        },
        coupling={"drag": "ergun", "filter_passes": 1},
        particles={"fixed": True},
    )
    s = coupled(case, tmp_path, lattice((0, 0, 0), (0.01, 0.01, 0.016), d), d, 2500.0)
    for _ in range(300):
        s.step()
    from febed.runs.probes import SectionAverage

    lo, hi = np.zeros(3), np.array([0.01, 0.01, 0.03])
    z1, z2 = 0.002, 0.012
    grad = (SectionAverage(s.ma, 2, z1, lo, hi)(s.gas.p) - SectionAverage(s.ma, 2, z2, lo, hi)(s.gas.p)) / (z2 - z1)
    grad -= rho_g * 9.81 * (1 - math.pi / 6)  # gas weight in the bed
    eps = 1 - math.pi / 6
    ergun = 150 * mu * U * (1 - eps) ** 2 / (eps**3 * d**2) + 1.75 * rho_g * U**2 * (1 - eps) / (eps**3 * d)
    assert abs(grad / ergun - 1) < 0.03, (grad, ergun)
    assert np.array_equal(s.dem.particles.vel, np.zeros_like(s.dem.particles.vel))  # the bed stayed fixed


def test_outlet_removes_particles_and_a_leak_elsewhere_stops_the_run(tmp_path):
    from febed.solver import RunFailure

    case = box_case(tmp_path, (0.01, 0.01, 0.02), 0.0025, contact={"stiffness": 10.0})
    s = coupled(case, tmp_path, [[0.005, 0.005, 0.019], [0.005, 0.005, 0.005]], 1e-3, 2500.0)
    s.dem.particles.vel[0] = [0.0, 0.0, 2.0]  # heading for the outlet
    while s.t < 0.01:
        s.step()
    assert s.left_outlet == 1 and s.dem.particles.n_owned == 1
    assert s.dem.particles.gid[0] == 1  # the other one is still there
    # walls that do not hold particles: a particle crossing them is an error naming it
    leaky = box_case(tmp_path, (0.01, 0.01, 0.02), 0.0025, gas={"boundary": {"walls": {"particles": False}}})
    s = coupled(leaky, tmp_path, [[0.0095, 0.005, 0.01]], 1e-3, 2500.0)
    s.dem.particles.vel[0] = [2.0, 0.0, 0.0]
    with pytest.raises(RunFailure, match=r"particle 0 at .* left the mesh other than through an outlet"):
        while s.t < 0.01:
            s.step()
            s.check()


@pytest.mark.mpi
def test_outlet_closed_to_particles_is_a_lid_the_gas_still_leaves_by(mpi_tmp_path):
    """`particles = false` on an outlet: a particle thrown at it bounces back (restitution e) and stays, while
    the gas flows out through it (the outflow equals the inflow)."""
    comm = MPI.COMM_WORLD
    e = 0.8
    case = box_case(
        mpi_tmp_path,
        (0.01, 0.01, 0.02),
        0.0025,
        gas={"boundary": {"inlet": {"type": "inlet", "velocity": 0.2}, "outlet": {"particles": False}}},
        contact={"stiffness": 1000.0, "restitution_pw": e, "friction_pw": 0.0},
    )
    s = coupled(case, mpi_tmp_path, [[0.005, 0.005, 0.017]], 1e-3, 2500.0)
    P = s.dem.particles
    if P.n_owned:
        P.vel[0] = [0.0, 0.0, 1.0]  # heading for the outlet 2.5 mm above, ~2.5 ms away
    vmin = 0.0
    while s.t < 0.006:
        s.step()
        s.check()
        vz = P.vel[: P.n_owned, 2]
        vmin = min(vmin, comm.allreduce(float(vz.min()) if vz.size else 0.0, op=MPI.MIN))
    assert comm.allreduce(P.n_owned) == 1 and comm.allreduce(s.left_outlet) == 0
    z = comm.allreduce(float(P.pos[0, 2]) if P.n_owned else -1.0, op=MPI.MAX)
    assert 0.0 < z < 0.02 - 0.5e-3  # inside, below the lid
    # it came back down at about e times its arrival speed (gravity and drag over ~3 ms: a few percent)
    assert -vmin == pytest.approx(e, abs=0.06), vmin
    # the gas is not held back: through the lid it leaves as it comes in (0.2 m/s over the 1 cm² top)
    from febed.runs.probes import SectionAverage

    lo, hi = np.zeros(3), np.array([0.01, 0.01, 0.02])
    w_top = SectionAverage(s.ma, 2, 0.02, lo, hi)(np.ascontiguousarray(s.gas.u[:, 2]))
    assert w_top == pytest.approx(0.2, rel=0.05), w_top


@pytest.mark.mpi
def test_pseudo2d_box_walls_are_planes(mpi_tmp_path):
    """The pseudo-2D column's walls (sides, front, back, bottom) are five planes; the open top is none."""
    case = load_case(ROOT / "demos" / "pseudo2d" / "C1.toml", [f"output.directory={mpi_tmp_path}"])
    md = load_case_mesh(case, cache_dir=mpi_tmp_path / "mesh")
    walls = walls_from_mesh(case, md)
    assert walls.facets.shape[0] == 0 and walls.plane_p.shape[0] == 5
    assert not np.any(np.isclose(walls.plane_p[:, 2], 0.25) & (walls.plane_n[:, 2] != 0))


@pytest.mark.mpi
def test_particle_beyond_its_ranks_cells_is_migrated_not_a_failure(mpi_tmp_path):
    """Between two pair-list rebuilds a particle can leave its rank's owned and ghost cells (across a corner of
    a staircase partition boundary, whose diagonal neighbour is no ghost): it is migrated at once and found."""
    comm = MPI.COMM_WORLD
    case = box_case(mpi_tmp_path, (0.08, 0.01, 0.02), 0.005)  # 16 columns: ranks' far ends are no ghosts
    s = coupled(case, mpi_tmp_path, [[0.004, 0.005, 0.01]], 1e-3, 2500.0)
    s.project()
    assert comm.allreduce(s.dem.particles.n_owned) == 1
    far = np.array([0.076, 0.005, 0.01])  # at the other end of the box: another rank's cells when there are two
    if s.dem.particles.n_owned:
        s.dem.particles.pos[0] = far
    s.locate_particles()
    s.check()  # no failure on any rank
    P = s.dem.particles
    assert comm.allreduce(P.n_owned) == 1 and comm.allreduce(s.left_outlet) == 0
    if P.n_owned:
        assert np.array_equal(P.pos[0], far) and P.cell[0] >= 0 and P.cell[0] < s.ma.num_owned_cells
