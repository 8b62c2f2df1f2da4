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
    kernels.momentum_rhs(ops.indptr, ops.indices, ops.grad, ops.tens, q, u, gp, np.full(ops.n_ext, nu), rho, hdt, out)
    uc = ufl.as_vector([float(c) for c in u0])
    for c in range(gdim):
        conv = -rho * v * ufl.dot(uc, ufl.grad(qf[c])) * ufl.dx  # −ρ∇·(q⊗u) with u constant
        tg = -rho * hdt * ufl.dot(uc, ufl.grad(v)) * ufl.dot(uc, ufl.grad(qf[c])) * ufl.dx
        ref = ufl_vector(ops, conv + tg)  # viscous term vanishes: u is constant
        assert np.allclose(out[:, c], ref, atol=1e-12)
    # viscous term alone: −∫ ν ∇φ_i·∇u_h with u = q (field), convection off via zero velocity in the flux
    kernels.momentum_rhs(ops.indptr, ops.indices, ops.grad, ops.tens, q, q, gp, np.full(ops.n_ext, nu), 0.0, 0.0, out)
    for c in range(gdim):
        ref = ufl_vector(ops, -nu * ufl.dot(ufl.grad(v), ufl.grad(qf[c])) * ufl.dx)
        assert np.allclose(out[:, c], ref, atol=1e-12)
