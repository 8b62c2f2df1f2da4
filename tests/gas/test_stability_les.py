"""Convective stability of the explicit predictor at high Reynolds number, and the Smagorinsky viscosity."""

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
from _gas_cases import tagged_mesh

from febed.gas import BoundarySpec, VANSParameters, VANSSolver

A = np.pi / 2


def box_solver(n, **kw):
    mesh = dolfinx.mesh.create_rectangle(
        MPI.COMM_WORLD, [[-A, -A], [A, A]], [n, n], dolfinx.mesh.CellType.quadrilateral
    )
    md = tagged_mesh(mesh, {"walls": lambda x: np.full(x.shape[1], True)})
    par = VANSParameters(
        gravity=0.0, density=1.0, dt_max=1.0, boundaries={"walls": BoundarySpec("wall", slip=True)}, **kw
    )
    return VANSSolver(md, par)


def kinetic_energy(s):
    n = s.n_owned
    return MPI.COMM_WORLD.allreduce(float(np.sum(s.node_volume[:n] * np.sum(s.u[:n] ** 2, axis=1))))


@pytest.mark.parametrize("substeps", [1, 4])
def test_nearly_inviscid_vortex_loses_energy(substeps):
    """At the CFL limit (one predictor per step, or four sub-steps of a step four times longer)."""
    s = box_solver(24, viscosity=1e-6, convection_substeps=substeps)
    x = s.x
    s.q[:] = np.stack(
        [-np.cos(x[:, 0]) * np.sin(x[:, 1]) + 0.3 * np.sin(3 * x[:, 1] + 1), np.sin(x[:, 0]) * np.cos(x[:, 1])], axis=1
    )
    s.q[:, 1] += 0.3 * np.cos(2 * x[:, 0])
    s.set_void_fraction(1.0)
    energy = [kinetic_energy(s)]
    every = 100 // substeps  # the same simulated time between samples and in all
    for k in range(2000 // substeps):
        info = s.step(s.compute_dt())
        if k % every == every - 1:
            energy.append(kinetic_energy(s))
    assert info.cfl == pytest.approx(0.2 * substeps, rel=0.05)
    assert np.all(np.diff(energy) <= 1e-12 * energy[0])  # never gains energy
    assert energy[-1] > 0.3 * energy[0]  # and is not over-damped


@pytest.mark.parametrize("les", ["none", "smagorinsky"])
def test_smagorinsky_viscosity_in_shear(les):
    s = box_solver(16, viscosity=1e-3, les=les, smagorinsky_cs=0.17)
    gamma = 2.0
    s.q[:] = 0.0
    s.q[:, 0] = gamma * s.x[:, 1]
    s.set_void_fraction(1.0)
    mu = s.effective_viscosity()
    h = np.pi / 16
    inner = np.all(np.abs(s.x[:, :2]) < A - 1.5 * h, axis=1)[: s.n_owned]
    expected = 1e-3 + (les == "smagorinsky") * (0.17 * h) ** 2 * gamma  # ρ (C_s Δ)^2 |S|, |S| = γ
    assert np.allclose(mu[: s.n_owned][inner], expected, rtol=1e-10)
    dt = s.compute_dt()
    mu_max = MPI.COMM_WORLD.allreduce(float(mu[: s.n_owned].max()), op=MPI.MAX)
    k = s.params.convection_substeps  # the step spans up to k sub-steps, each within both limits
    assert dt == pytest.approx(k * min(0.2 * h / (gamma * A), 0.15 * h**2 / mu_max), rel=1e-6)


def test_petsc_options_reach_the_pressure_solver():
    from petsc4py import PETSc

    from febed.gas.vans import apply_petsc_options

    apply_petsc_options("-febedtest_pressure_pc_type jacobi -febedtest_pressure_ksp_monitor_cancel")
    try:
        s = box_solver(4, viscosity=1e-3, prefix="febedtest_")
        assert s.pressure.ksp.getPC().getType() == "jacobi"
    finally:
        PETSc.Options().delValue("febedtest_pressure_pc_type")
        PETSc.Options().delValue("febedtest_pressure_ksp_monitor_cancel")
    with pytest.raises(ValueError, match="petsc_options"):
        apply_petsc_options("pc_type gamg")


@pytest.mark.parametrize("gdim", [2, 3])
def test_strain_rate_norm_of_a_general_gradient(gdim):
    """|S| = sqrt(2 S:S), S = (A + Aᵀ)/2, for a node whose Galerkin sums give ΔV·A (every entry exercised)."""
    from febed.gas.kernels import strain_rate_norm

    rng = np.random.default_rng(gdim)
    A = rng.normal(size=(gdim, gdim))
    mass = 0.37
    u = np.eye(gdim)  # column node j carries the unit vector e_j, so Σ_k grad[k, d] u[k, c] = grad[c, d]
    grad = mass * A
    out = np.zeros(1)
    indptr, indices = np.array([0, gdim], dtype=np.int64), np.arange(gdim, dtype=np.int32)  # the operators' dtypes
    strain_rate_norm(indptr, indices, np.ascontiguousarray(grad), u, np.array([mass]), out)
    S = 0.5 * (A + A.T)
    assert out[0] == pytest.approx(np.sqrt(2.0 * np.sum(S * S)), rel=1e-14)
