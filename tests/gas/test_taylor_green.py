"""Decaying Taylor-Green vortex in a free-slip box: observed spatial order >= 1.8 and temporal order.

In [-π/2, π/2]^2 the vortex u = (-cos x sin y, sin x cos y) e^{-2νt}, p = -(cos 2x + cos 2y) e^{-4νt}/4
has zero normal velocity and zero shear on the box sides, so it is an exact solution with slip walls
(and a pure-Neumann pressure problem: the constant null space is exercised).
"""

from mpi4py import MPI

import dolfinx
import numpy as np
from _gas_cases import tagged_mesh

from febed.gas import BoundarySpec, VANSParameters, VANSSolver

NU = 0.05
A = np.pi / 2


def exact_u(x, t):
    f = np.exp(-2 * NU * t)
    return np.stack([-np.cos(x[:, 0]) * np.sin(x[:, 1]) * f, np.sin(x[:, 0]) * np.cos(x[:, 1]) * f], axis=1)


def run_tg(n, dt, t_end, cell=dolfinx.mesh.CellType.quadrilateral, substeps=None):
    mesh = dolfinx.mesh.create_rectangle(MPI.COMM_WORLD, [[-A, -A], [A, A]], [n, n], cell)
    md = tagged_mesh(mesh, {"walls": lambda x: np.full(x.shape[1], True)})
    bcs = {"walls": BoundarySpec("wall", slip=True)}
    par = VANSParameters(gravity=0.0, density=1.0, viscosity=NU, dt_max=1.0, pressure_rtol=1e-10, boundaries=bcs)
    if substeps is not None:
        par.convection_substeps = substeps
    s = VANSSolver(md, par)
    s.q[:] = exact_u(s.x, 0.0)
    s.set_void_fraction(1.0)
    s.set_pressure(-0.25 * (np.cos(2 * s.x[:, 0]) + np.cos(2 * s.x[:, 1])))
    for _ in range(int(round(t_end / dt))):
        s.step(dt)
    return s


def l2_error(s, ref):
    n = s.n_owned
    m = s.node_volume[:n]
    e = MPI.COMM_WORLD.allreduce(float(np.sum(m * np.sum((s.u[:n] - ref[:n]) ** 2, axis=1))))
    r = MPI.COMM_WORLD.allreduce(float(np.sum(m * np.sum(ref[:n] ** 2, axis=1))))
    return np.sqrt(e / r)


def test_spatial_order():
    errors = []
    for n in (8, 16, 32):
        s = run_tg(n, 2.5e-4, 0.1)
        errors.append(l2_error(s, exact_u(s.x, s.t)))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    print("Taylor-Green spatial errors", errors, "orders", orders)
    assert errors[-1] < 5e-5
    assert np.all(orders >= 1.8)


def test_temporal_order():
    t_end, n = 0.4, 24
    # the order of one step: no convective sub-steps (their accuracy: tests/gas/test_convection_substeps.py)
    ref = run_tg(n, 0.0025, t_end, substeps=1).u.copy()
    errors = [l2_error(run_tg(n, dt, t_end, substeps=1), ref) for dt in (0.04, 0.02, 0.01)]
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    print("Taylor-Green temporal errors", errors, "orders", orders)
    assert np.all(orders >= 0.9)
