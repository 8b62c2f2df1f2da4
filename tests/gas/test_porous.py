"""Porous media: the Ergun pressure gradient, global mass balance with a time-varying ε, stiff momentum exchange."""

from mpi4py import MPI

import numpy as np
import pytest
from _gas_cases import channel, channel_solver, darcy_errors, owned

RHO, MU, D, EPS, U = 1.2, 1.8e-5, 1e-3, 0.45, 0.3


def ergun_gradient(U, eps):
    """Ergun's -dp/dx for superficial velocity U [Pa/m]."""
    return 150 * MU * (1 - eps) ** 2 * U / (eps**3 * D**2) + 1.75 * RHO * (1 - eps) * U**2 / (eps**3 * D)


def ergun_K(u, eps):
    """Momentum-exchange coefficient K with K u = Ergun's -dp/dx, u the interstitial speed [kg/(m^3 s)]."""
    return 150 * MU * (1 - eps) ** 2 / (eps**2 * D**2) + 1.75 * RHO * (1 - eps) * np.abs(u) / (eps * D)


def test_ergun_pressure_gradient():
    md = channel(0.1, 0.02, 40, 8)
    s = channel_solver(md, U, rho=RHO, mu=MU, eps=EPS, slip=True)
    s.q[:, 0] = U
    s.set_void_fraction(EPS)
    for _ in range(300):
        K = ergun_K(np.linalg.norm(s.u, axis=1), s.eps)
        info = s.step(s.compute_dt(), K=K)
    x = owned(s, s.x)
    inner = (x[:, 0] > 0.02) & (x[:, 0] < 0.08)
    gp = owned(s, s.grad_p)[inner, 0]
    mean = MPI.COMM_WORLD.allreduce(float(gp.sum())) / MPI.COMM_WORLD.allreduce(gp.size)
    assert -mean == pytest.approx(ergun_gradient(U, EPS), rel=0.01)
    assert abs(info.outflow - info.inflow) < 1e-6 * info.inflow


def varying_eps(x, t, width, height):
    return 0.6 + 0.25 * np.sin(np.pi * x[:, 1] / width) * np.sin(np.pi * x[:, 0] / height) * np.cos(40 * t)


def test_mass_balance_time_varying_eps():
    # gas enters at x = 0 through an inlet with a wall patch counted in the cross-section (seed 001 bed)
    length, width, Uf = 0.2, 0.09, 0.5
    md = channel(length, width, 40, 18, patch=(0.035, 0.055))
    s = channel_solver(md, Uf, rho=RHO, mu=MU, eps=varying_eps(np.zeros((1, 3)), 0.0, width, length)[0])
    s.set_void_fraction(varying_eps(s.x, 0.0, width, length))
    worst = 0.0
    for _ in range(60):
        dt = s.compute_dt()
        info = s.step(dt, eps=varying_eps(s.x, s.t + dt, width, length))
        assert info.inflow == pytest.approx(Uf * width, rel=1e-12)  # U_f over the whole cross-section
        worst = max(worst, abs(info.mass_imbalance) / (RHO * info.inflow))
    print("worst relative mass imbalance per step", worst)
    assert worst < 1e-6
    assert abs(info.storage_rate) > 1e-3 * info.inflow  # ε really varies


def test_inlet_ramp():
    md = channel(0.2, 0.05, 8, 4)
    s = channel_solver(md, 0.4, rho=RHO, mu=MU)
    s.bc.inlets[0].spec.ramp_time = 0.1
    info = s.step(0.025)
    assert info.inflow == pytest.approx(0.4 * 0.05 * 0.25, rel=1e-12)
    with pytest.raises(ValueError, match="dt must be > 0"):
        s.step(0.0)
    with pytest.raises(ValueError, match="eps"):
        s.step(1e-3, eps=np.full(3, 0.5))


def test_stiff_momentum_exchange_stays_bounded():
    md = channel(0.1, 0.04, 20, 8)
    s = channel_solver(md, U, rho=RHO, mu=MU, eps=EPS)
    dt = 1e-3
    K = 1e3 * RHO * EPS / dt
    rng = np.random.default_rng(1)
    vbar = 0.5 * (rng.random((s.n_local, 2)) - 0.5)
    for _ in range(100):
        info = s.step(dt, K=K, Kv=K * vbar)
    speed = MPI.COMM_WORLD.allreduce(float(np.abs(owned(s, s.u)).max()), op=MPI.MAX)
    assert np.isfinite(speed) and speed < 10 * (U / EPS + 0.25)
    assert abs(info.mass_imbalance) < 1e-6 * RHO * info.inflow


@pytest.mark.mpi
def test_drag_number_limits_the_time_step():
    # a dense half (K of a packed bed of 1 mm beads) next to a clear half: dt = D_max rho eps / max K, reduced
    # over the ranks; without the limit the same step is CFL-limited, three orders of magnitude longer
    md = channel(0.1, 0.04, 20, 8)
    K_bed = 4.0e4
    limited = channel_solver(md, U, rho=RHO, mu=MU, eps=EPS, drag_number=0.3)
    free = channel_solver(md, U, rho=RHO, mu=MU, eps=EPS)
    for s in (limited, free):
        K = np.where(s.x[:, 0] > 0.05, K_bed, 10.0)
        s.step(1e-5, K=K)
    assert limited.compute_dt() == pytest.approx(0.3 * RHO * EPS / K_bed, rel=1e-12)
    assert free.compute_dt() > 100 * limited.compute_dt()
    with pytest.raises(ValueError, match="drag_number"):
        channel_solver(md, U, drag_number=-1.0)


@pytest.mark.mpi
@pytest.mark.parametrize("passes", [1, 2, 3])
def test_pressure_lags_the_drag_by_D_over_1_plus_D_per_pass(passes):
    # uniform flow through a uniform porous channel with D = K dt/(rho eps) = 4, from p = 0: with the plain
    # projection the error of the pressure gradient against Darcy's -K U/eps decays by exactly (D/(1+D))^passes
    # per step (module docstring)
    md = channel(0.1, 0.02, 40, 8)
    dt, D = 2e-4, 4.0
    K = D * RHO * EPS / dt
    s = channel_solver(
        md, U, rho=RHO, mu=MU, eps=EPS, slip=True, pressure_passes=passes, drag_weighted_projection=False
    )
    s.q[:, 0] = U
    s.set_void_fraction(EPS)
    x = owned(s, s.x)
    inner = (x[:, 0] > 0.02) & (x[:, 0] < 0.08)
    target = -K * U / EPS
    errors = []
    for _ in range(5):
        info = s.step(dt, K=K)
        local = np.abs(owned(s, s.grad_p)[inner, 0] - target).max(initial=0.0)
        errors.append(MPI.COMM_WORLD.allreduce(float(local), op=MPI.MAX) / abs(target))
    assert np.allclose(np.array(errors[1:]) / errors[:-1], (D / (1 + D)) ** passes, rtol=1e-3), errors
    assert abs(info.mass_imbalance) < 1e-6 * RHO * info.inflow  # the last pass closes the mass balance
    with pytest.raises(ValueError, match="pressure_passes"):
        channel_solver(md, U, pressure_passes=0)


@pytest.mark.mpi
def test_drag_weighted_projection_gives_darcys_pressure_in_one_step():
    # the same channel with the drag-weighted projection (`gas.drag_weighted_projection`): the pressure
    # equation and the correction carry the predictor's 1/(1 + D), so the first step already balances the
    # drag (to the Poisson tolerance) where the plain projection is still 0.8 off; with a drag that jumps
    # along the channel (D = 4 and 0.4) each part holds Darcy's gradient of its own K (the plain projection:
    # 0.8 and 0.29 off), and the mass balance closes
    md = channel(0.1, 0.02, 40, 8)
    for jump in (False, True):
        for step, (err, imbalance) in enumerate(darcy_errors(md, U, RHO, MU, EPS, 2e-4, jump)):
            assert err < 1e-6, (jump, step, err)
            assert imbalance < 1e-6


@pytest.mark.mpi
@pytest.mark.parametrize("passes", [1, 2])
def test_pressure_share_carries_minus_eps_grad_p_with_nothing_lagged(passes):
    # model A, as the coupled solver's nodal pressure-gradient reaction runs it: the momentum carries −ε∇p,
    # given as −∇p^n in the predictor plus (1 − ε)∇p^n in `force`. With the pressure's share ε the first step
    # balances the drag (∇p = −K U/ε², to the Poisson tolerance); with the force alone the new gradient's
    # (1 − ε) part trails it, the error falling by a factor 1 − ε per step whatever the passes
    md = channel(0.1, 0.02, 40, 8)
    dt, D = 2e-4, 4.0
    K = D * RHO * EPS / dt
    target = -K * U / EPS**2
    for share in (EPS, None):
        s = channel_solver(md, U, rho=RHO, mu=MU, eps=EPS, slip=True, pressure_passes=passes)
        s.q[:, 0] = U
        s.set_void_fraction(EPS)
        x = owned(s, s.x)
        inner = (x[:, 0] > 0.02) & (x[:, 0] < 0.08)
        errors = []
        for _ in range(5):
            info = s.step(dt, K=K, force=(1.0 - EPS) * s.grad_p, pressure_share=share)
            local = np.abs(owned(s, s.grad_p)[inner, 0] - target).max(initial=0.0)
            errors.append(MPI.COMM_WORLD.allreduce(float(local), op=MPI.MAX) / abs(target))
            assert abs(info.mass_imbalance) < 1e-6 * RHO * info.inflow
        if share is None:
            assert errors[0] == pytest.approx(1.0 - EPS, rel=1e-3)
            assert np.allclose(np.array(errors[1:]) / errors[:-1], 1.0 - EPS, rtol=1e-3), errors
        else:
            assert errors[0] < 1e-6 and max(errors) < 1e-4, errors  # then the flow's own slow development
    with pytest.raises(ValueError, match="pressure_share"):
        s.step(dt, K=K, pressure_share=0.0)


def test_drag_weighted_projection_refuses_a_one_shot_weighted_solve():
    # the weighted solve has options of its own (prefix ..._pressure_weighted_): a direct factorisation of the
    # constant Laplacian is fine beside it, but a one-shot (preonly) weighted solve would apply a preconditioner
    # built at an earlier step once, and is refused with the option's name
    from petsc4py import PETSc

    from febed.gas.vans import apply_petsc_options

    apply_petsc_options("-febedpreonly_pressure_ksp_type preonly -febedpreonly_pressure_pc_type lu")
    try:
        md = channel(0.1, 0.02, 10, 2)
        s = channel_solver(md, U, rho=RHO, mu=MU, eps=EPS, drag_weighted_projection=True, prefix="febedpreonly_")
        info = s.step(1e-4, K=1e4)
        assert abs(info.mass_imbalance) < 1e-6 * RHO * info.inflow
        apply_petsc_options("-febedpreonlyw_pressure_weighted_ksp_type preonly")
        with pytest.raises(ValueError, match="febedpreonlyw_pressure_weighted_ksp_type preonly"):
            channel_solver(md, U, drag_weighted_projection=True, prefix="febedpreonlyw_")
    finally:
        for key in ("febedpreonly_pressure_ksp_type", "febedpreonly_pressure_pc_type"):
            PETSc.Options().delValue(key)
        PETSc.Options().delValue("febedpreonlyw_pressure_weighted_ksp_type")


@pytest.mark.mpi
def test_drag_number_limit_survives_a_restart():
    # the limit of the next step is part of the state: a solver restored from it takes the same step
    md = channel(0.1, 0.04, 20, 8)
    a = channel_solver(md, U, rho=RHO, mu=MU, eps=EPS, drag_number=0.3)
    K = np.where(a.x[:, 0] > 0.05, 4.0e4, 10.0)
    for _ in range(2):
        a.step(1e-5, K=K)
    b = channel_solver(md, U, rho=RHO, mu=MU, eps=EPS, drag_number=0.3)
    b.set_state(a.get_state(), a.t)
    assert b.compute_dt() == a.compute_dt() == pytest.approx(0.3 * RHO * EPS / 4.0e4, rel=1e-12)
