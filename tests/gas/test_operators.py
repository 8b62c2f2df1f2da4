"""The Numba sweeps over the constant nodal operators against plain UFL assembly."""

from mpi4py import MPI

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import pytest
import ufl

from febed.gas import kernels
from febed.gas.operators import accumulate, build_operators


def ufl_vector(ops, form):
    vec = dolfinx.fem.petsc.assemble_vector(dolfinx.fem.form(form))
    out = accumulate(vec)[: ops.n_owned]
    vec.destroy()
    return out


MESHES = {
    "quadrilateral": lambda: dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 6, 5, dolfinx.mesh.CellType.quadrilateral),
    "triangle": lambda: dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 6, 5, dolfinx.mesh.CellType.triangle),
    "hexahedron": lambda: dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 3, 4, 3, dolfinx.mesh.CellType.hexahedron),
    "tetrahedron": lambda: dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 3, 3, 4, dolfinx.mesh.CellType.tetrahedron),
}


@pytest.mark.mpi
@pytest.mark.parametrize("cell", list(MESHES))
def test_sweeps_match_ufl(cell):
    mesh = MESHES[cell]()
    ops = build_operators(mesh)
    gdim, n = ops.gdim, ops.n_owned
    V = dolfinx.fem.VectorFunctionSpace(mesh, ("Q" if cell in ("quadrilateral", "hexahedron") else "Lagrange", 1))
    x = ops.Q.tabulate_dof_coordinates()
    q = np.stack([np.sin(3 * x[:, 0] + 2 * x[:, 1]) + x[:, 2], np.cos(x[:, 0] * x[:, 1]) + x[:, 2] ** 2, x[:, 0]])
    q = np.ascontiguousarray(q[:gdim].T)
    qf = dolfinx.fem.Function(V)
    qf.x.array[:] = q.ravel()
    q = ops.extension.extend("q", qf.vector, qf.x.array)  # + nodes of off-rank cells touching owned nodes
    q0 = dolfinx.fem.Function(ops.Q)
    q0.x.array[:] = qf.x.array[::gdim]
    v = ufl.TestFunction(ops.Q)
    # node volumes and divergence
    assert MPI.COMM_WORLD.allreduce(float(ops.mass[:n].sum())) == pytest.approx(1.0, rel=1e-12)
    div = np.zeros(n)
    kernels.divergence(ops.indptr, ops.indices, ops.grad, q, div)
    assert np.allclose(div, ufl_vector(ops, v * ufl.div(qf) * ufl.dx), atol=1e-13)
    # gradient of a scalar
    grad = np.zeros((n, gdim))
    kernels.gradient(ops.indptr, ops.indices, ops.grad, ops.extension.extend("q0", q0.vector, q0.x.array), grad)
    for d in range(gdim):
        assert np.allclose(grad[:, d], ufl_vector(ops, v * qf[0].dx(d) * ufl.dx), atol=1e-13)
    # momentum RHS with constant coefficients: viscous and Taylor-Galerkin terms are exact weak forms
    u0 = np.array([0.7, -0.4, 0.3])[:gdim]
    u = np.tile(u0, (ops.n_ext, 1))
    nu, rho, hdt = 0.3, 1.3, 0.05
    out = np.zeros((n, gdim))
    gp = np.zeros((n, gdim))
    kernels.momentum_rhs(ops.edges, q, u, gp, np.full(ops.n_ext, nu), rho, hdt, out)
    uc = ufl.as_vector([float(c) for c in u0])
    for c in range(gdim):
        conv = -rho * v * ufl.dot(uc, ufl.grad(qf[c])) * ufl.dx  # −ρ∇·(q⊗u) with u constant
        tg = -rho * hdt * ufl.dot(uc, ufl.grad(v)) * ufl.dot(uc, ufl.grad(qf[c])) * ufl.dx
        ref = ufl_vector(ops, conv + tg)  # viscous term vanishes: u is constant
        assert np.allclose(out[:, c], ref, atol=1e-12)
    # viscous term alone: −∫ ν ∇φ_i·∇u_h with u = q (field), convection off via zero velocity in the flux
    kernels.momentum_rhs(ops.edges, q, q, gp, np.full(ops.n_ext, nu), 0.0, 0.0, out)
    for c in range(gdim):
        ref = ufl_vector(ops, -nu * ufl.dot(ufl.grad(v), ufl.grad(qf[c])) * ufl.dx)
        assert np.allclose(out[:, c], ref, atol=1e-12)


def _rows_reference(ops, q, u, gradp, nu, rho, hdt):
    """The momentum right-hand side entry by entry of the owned rows, in plain numpy (the kernel's formula)."""
    n, gdim = ops.n_owned, ops.gdim
    i = np.repeat(np.arange(n), np.diff(ops.indptr))
    j = ops.indices
    g, t = ops.grad, ops.tens
    sc = np.einsum("kd,kd->k", g, u[j])
    s = 0.5 * rho * (sc + np.einsum("kd,kd->k", g, u[i]))
    c = t[:, :gdim].sum(axis=1) * 0.5 * (nu[i] + nu[j])
    b = 0.5 * (u[i] + u[j])
    w = np.einsum("kd,kd->k", t[:, :gdim], b * b)
    pairs = [(0, 1), (0, 2), (1, 2)] if gdim == 3 else [(0, 1)]
    for m, (d, e) in enumerate(pairs):
        w = w + t[:, gdim + m] * b[:, d] * b[:, e]
    w = rho * hdt * w
    term = s[:, None] * q[j] + c[:, None] * (u[j] - u[i]) + w[:, None] * (q[j] - q[i])
    out = np.zeros((n, gdim))
    np.add.at(out, i, -term)
    dv = np.zeros(n)
    np.add.at(dv, i, sc)
    return out - 0.5 * rho * dv[:, None] * q[:n] - gradp


@pytest.mark.mpi
@pytest.mark.parametrize("cell", list(MESHES))
def test_momentum_sweep_by_edges_equals_the_sweep_by_rows(cell):
    # the kernel visits each pair of owned nodes once and adds to both rows, the ghost and extra columns to
    # their row only: with variable u, q, ν and the Taylor-Galerkin term on, every owned row equals the
    # entry-by-entry sum of the rows' formula to round-off (the row j takes `tens` of the entry (i, j))
    mesh = MESHES[cell]()
    x = mesh.geometry.x
    x[:, 0] += 0.05 * np.sin(3.0 * x[:, 1] + 1.0)  # non-affine cells: no two rows alike
    ops = build_operators(mesh)
    e = ops.edges
    assert 2 * e.ei.size + ops.n_owned + e.oi.size == ops.indices.size  # every entry of the owned rows, once
    assert np.all(e.ei < e.ej) and np.all(e.ej < ops.n_owned) and np.all(e.oi < ops.n_owned)
    rng = np.random.default_rng(11 + MPI.COMM_WORLD.rank)
    m = ops.n_ext
    u = rng.normal(size=(m, ops.gdim))
    q = u * rng.uniform(0.4, 1.0, (m, 1))
    nu = rng.uniform(1e-5, 3e-5, m)
    gradp = rng.normal(size=(ops.n_owned, ops.gdim))
    out = np.zeros((ops.n_owned, ops.gdim))
    kernels.momentum_rhs(e, q, u, gradp, nu, 1.3, 2e-3, out)
    ref = _rows_reference(ops, q, u, gradp, nu, 1.3, 2e-3)
    err = MPI.COMM_WORLD.allreduce(float(np.abs(out - ref).max(initial=0.0)), op=MPI.MAX)
    scale = MPI.COMM_WORLD.allreduce(float(np.abs(ref).max(initial=0.0)), op=MPI.MAX)
    assert err <= 1e-13 * scale, (cell, err, scale)
    ghosts = MPI.COMM_WORLD.allreduce(int(e.oi.size), op=MPI.SUM)
    assert (ghosts > 0) == (MPI.COMM_WORLD.size > 1)  # on several ranks the one-sided entries are exercised
