"""Convective sub-steps (`gas.convection_substeps` = k): up to k explicit predictor sub-steps per gas step.

Checked: the step the CFL limit allows is k times longer; a step takes the fewest sub-steps its CFL number
needs, and one the convective limit does not bind is the plain single-step predictor, bit for bit; the
drag-weighted projection still balances a porous channel's drag in one step (it needs the sub-stepped
predictor's response, not 1/(1 + D)); the decaying Taylor-Green vortex keeps the accuracy of single steps at
the same sub-step and converges with the gas step; a nearly inviscid vortex never gains kinetic energy; the
step limit kept from the end of a step is not reused for a state restored at the same time.
Where a test needs exactly k sub-steps at any step, a tiny `cfl` makes every step ask for more than k.
"""

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
from _gas_cases import channel, darcy_errors, tagged_mesh

from febed.gas import BoundarySpec, VANSParameters, VANSSolver

RHO, MU, EPS, U = 1.2, 1.8e-5, 0.45, 0.3
A = np.pi / 2


def vortex(n, nu, k, **kw):
    """The Taylor-Green vortex u = (-cos x sin y, sin x cos y) in a slip box [-π/2, π/2]^2 at t = 0."""
    quads = dolfinx.mesh.CellType.quadrilateral
    mesh = dolfinx.mesh.create_rectangle(MPI.COMM_WORLD, [[-A, -A], [A, A]], [n, n], quads)
    md = tagged_mesh(mesh, {"walls": lambda x: np.full(x.shape[1], True)})
    bcs = {"walls": BoundarySpec("wall", slip=True)}
    par = VANSParameters(
        gravity=0.0, density=1.0, viscosity=nu, dt_max=1.0, pressure_rtol=1e-10, boundaries=bcs,
        convection_substeps=k, **kw,
    )  # fmt: skip
    s = VANSSolver(md, par)
    s.q[:] = exact_u(s.x, 0.0, nu)
    s.set_void_fraction(1.0)
    s.set_pressure(-0.25 * (np.cos(2 * s.x[:, 0]) + np.cos(2 * s.x[:, 1])))
    return s


def exact_u(x, t, nu):
    f = np.exp(-2 * nu * t)
    return np.stack([-np.cos(x[:, 0]) * np.sin(x[:, 1]) * f, np.sin(x[:, 0]) * np.cos(x[:, 1]) * f], axis=1)


def error(s, nu):
    n = s.n_owned
    ref = exact_u(s.x, s.t, nu)[:n]
    m = s.node_volume[:n]
    e = MPI.COMM_WORLD.allreduce(float(np.sum(m * np.sum((s.u[:n] - ref) ** 2, axis=1))))
    r = MPI.COMM_WORLD.allreduce(float(np.sum(m * np.sum(ref**2, axis=1))))
    return np.sqrt(e / r)


def by_position(s, a):
    """The owned values of nodal array `a` of every rank, ordered by node position (any partition).

    The positions are rounded first: a node's coordinates, tabulated from different cells on different
    partitions, can differ in the last bit, which would order a column of nodes by that bit instead of by y.
    """
    n = s.n_owned
    x = np.round(np.concatenate(MPI.COMM_WORLD.allgather(s.x[:n, :2])), 9)
    v = np.concatenate(MPI.COMM_WORLD.allgather(np.asarray(a)[:n].reshape(n, -1)))
    return v[np.lexsort((x[:, 1], x[:, 0]))]


def kinetic_energy(s):
    n = s.n_owned
    return MPI.COMM_WORLD.allreduce(float(np.sum(s.node_volume[:n] * np.sum(s.u[:n] ** 2, axis=1))))


@pytest.mark.mpi
def test_the_cfl_step_is_k_times_longer():
    steps = [vortex(16, 0.05, k).compute_dt() for k in (1, 2, 3)]
    assert steps[1] == pytest.approx(2 * steps[0], rel=1e-12) and steps[2] == pytest.approx(3 * steps[0], rel=1e-12)
    with pytest.raises(ValueError, match="convection_substeps"):
        vortex(4, 0.05, 0)


@pytest.mark.mpi
def test_the_step_limit_follows_the_state_within_a_time_level():
    # the CFL and Fourier rates are kept from the end of a step for the next compute_dt; a state restored at
    # the same time (twice the velocity) must not reuse them
    s = vortex(16, 0.05, 1)
    s.step(s.compute_dt())
    dt1 = s.compute_dt()
    state = s.get_state()
    state["q"] = 2.0 * state["q"]
    s.set_state(state, s.t)
    assert s.compute_dt() == pytest.approx(0.5 * dt1, rel=1e-12)


@pytest.mark.mpi
def test_a_step_takes_the_substeps_its_cfl_number_needs():
    # CFL-limited vortex: a step of 0.6 convective steps is the plain predictor (k = 1's, to round-off: two
    # solvers in one process differ there through the pressure preconditioner), 2.5 take 3 sub-steps, the
    # compute_dt step 4
    single = vortex(16, 0.05, 1)
    dt0 = single.compute_dt()
    sub = vortex(16, 0.05, 4)
    assert sub.compute_dt() == pytest.approx(4 * dt0, rel=1e-12)
    for _ in range(3):
        assert sub.step(0.6 * dt0).substeps == 1
        single.step(0.6 * dt0)
    assert np.allclose(by_position(sub, sub.q), by_position(single, single.q), rtol=0, atol=1e-12)
    assert np.allclose(by_position(sub, sub.p), by_position(single, single.p), rtol=0, atol=1e-10)
    dt0 = single.compute_dt()  # the limit of the current state, which both solvers share to round-off
    assert sub.step(2.5 * dt0).substeps == 3
    assert sub.step(sub.compute_dt()).substeps == 4


@pytest.mark.mpi
@pytest.mark.parametrize("k", [2, 3])
def test_substeps_keep_darcys_pressure_in_one_step(k):
    # as tests/gas/test_porous.py for one step: uniform flow through a porous channel, D = K dt/(rho eps) = 4
    # and a jump to 0.4; the first gas step of k sub-steps balances the drag to the Poisson tolerance (with the
    # one-step weights 1/(1 + D) it would be 11-15 % off). Behind the jump the velocity is no longer uniform
    # after the first step, and the later sub-steps' convection, which the correction does not see, leaves
    # up to 6e-6 there in the second step (k = 4)
    md = channel(0.1, 0.02, 40, 8)
    for jump in (False, True):
        for step, (err, imbalance) in enumerate(
            darcy_errors(md, U, RHO, MU, EPS, 2e-4, jump, convection_substeps=k, cfl=1e-6)
        ):
            assert err < (1e-5 if jump and step else 1e-6), (jump, step, err)
            assert imbalance < 1e-6


def test_taylor_green_keeps_its_accuracy_at_the_same_substep():
    # one gas step of 0.01 against three sub-steps of 0.01 in a step of 0.03, to t = 0.36 on 24 x 24 cells;
    # and the sub-stepped scheme converges at first order in the gas step (k = 3, steps 0.06, 0.03, 0.015)
    nu, t_end = 0.05, 0.36
    single = vortex(24, nu, 1)
    for _ in range(36):
        single.step(0.01)
    sub = vortex(24, nu, 3, cfl=1e-6)  # three sub-steps in every step
    for _ in range(12):
        assert sub.step(0.03).substeps == 3
    e1, e3 = error(single, nu), error(sub, nu)
    assert e3 < 2.0 * e1, (e1, e3)
    errors = []
    for dt in (0.06, 0.03, 0.015):
        s = vortex(24, nu, 3, cfl=1e-6)
        for _ in range(int(round(t_end / dt))):
            s.step(dt)
        errors.append(error(s, nu))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(orders >= 0.8), (errors, orders)


def test_a_nearly_inviscid_vortex_never_gains_energy():
    # nu = 1e-6, CFL 0.2 per sub-step: 300 gas steps of three sub-steps never gain energy and lose what 900
    # single steps of the same convective step lose (the Taylor-Galerkin dissipation is the sub-step's)
    losses = []
    for k, steps in ((3, 300), (1, 900)):
        s = vortex(24, 1e-6, k)
        s.u[:] += 0.05 * np.sin(3 * s.x[:, [1, 0]])  # a perturbation to feed the grid modes
        s.q[:] = s.u
        energy = [kinetic_energy(s)]
        for _ in range(steps):
            s.step(s.compute_dt())
            energy.append(kinetic_energy(s))
        assert np.all(np.diff(energy) <= 1e-12 * energy[0]), (k, max(np.diff(energy)))
        losses.append(1.0 - energy[-1] / energy[0])
    assert losses[0] == pytest.approx(losses[1], rel=0.02), losses


def test_a_case_sets_the_substeps(tmp_path):
    from febed.case import load_case
    from febed.meshing import load_case_mesh

    path = tmp_path / "gas.toml"
    path.write_text(
        '[run]\nmode = "gas"\nend_time = 0.01\n[mesh]\nbuiltin = "box"\nextent = [0.02, 0.06]\nsize = 0.004\n'
        'cell = "quadrilateral"\n[gas]\nconvection_substeps = 3\n[gas.boundary.inlet]\ntype = "inlet"\nvelocity = 0.1\n'
        '[gas.boundary.walls]\ntype = "wall"\n[gas.boundary.outlet]\ntype = "outlet"\n'
    )
    case = load_case(path)
    s = VANSSolver.from_case(case, load_case_mesh(case, MPI.COMM_WORLD, cache_dir=tmp_path / "mesh"))
    assert s.params.convection_substeps == 3
