"""The pressure Poisson solver's default: a Cholesky factorisation on small serial meshes, CG + AMG otherwise.

Both must give the same increment φ to the iterative tolerance; a user's PETSc options always win, and one
solver's choice never leaks into the next through PETSc's global options database.
"""

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np
import pytest

from febed.gas import pressure
from febed.gas.pressure import PressureSolver


def _space(n=12):
    mesh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, n, n, dolfinx.mesh.CellType.quadrilateral)
    Q = dolfinx.fem.FunctionSpace(mesh, ("Q", 1))
    top = dolfinx.mesh.locate_entities_boundary(mesh, 1, lambda x: np.isclose(x[1], 1.0))
    dofs = dolfinx.fem.locate_dofs_topological(Q, 1, top)
    return Q, dofs


def _rhs(Q):
    x = Q.tabulate_dof_coordinates()[: Q.dofmap.index_map.size_local]
    return np.sin(3.0 * x[:, 0]) * np.cos(2.0 * x[:, 1]) + x[:, 1]


@pytest.mark.mpi
def test_direct_and_iterative_agree_and_options_do_not_leak(monkeypatch):
    comm = MPI.COMM_WORLD
    Q, dofs = _space()
    b = _rhs(Q)
    direct = PressureSolver(Q, dofs, True, "febed_test_direct_")
    expect_direct = comm.size == 1
    assert (direct.ksp.getType() == PETSc.KSP.Type.PREONLY) == expect_direct
    assert (direct.ksp.getPC().getType() == "cholesky") == expect_direct
    phi_d, _ = direct.solve(b, 1e-12, 1e-300)
    # the same problem, too large for the direct default: CG + AMG to a tight tolerance
    monkeypatch.setattr(pressure, "DIRECT_MAX_NODES", 10)
    cg = PressureSolver(Q, dofs, True, "febed_test_direct_")  # same prefix: nothing left behind by `direct`
    assert cg.ksp.getType() == PETSc.KSP.Type.CG
    phi_i, its = cg.solve(b, 1e-12, 1e-300)
    assert its > 1
    n = Q.dofmap.index_map.size_local
    err = comm.allreduce(float(np.max(np.abs(phi_d[:n] - phi_i[:n]), initial=0.0)), op=MPI.MAX)
    scale = comm.allreduce(float(np.max(np.abs(phi_i[:n]), initial=0.0)), op=MPI.MAX)
    assert err <= 1e-9 * scale
    # the residual of the factorised solve is round-off
    assert abs(direct.residual_sum()) < 1e-10 * comm.allreduce(float(np.abs(b).sum()))
    # CG's defaults, now in the options database, are febed's and not the user's: a small mesh is factorised again
    monkeypatch.setattr(pressure, "DIRECT_MAX_NODES", 50_000)
    again = PressureSolver(Q, dofs, True, "febed_test_direct_")
    assert (again.ksp.getType() == PETSc.KSP.Type.PREONLY) == expect_direct
    # an option of the user's for the drag-weighted solve (its own prefix) leaves the constant one factorised
    opts = PETSc.Options()
    opts["febed_test_direct_weighted_ksp_rtol"] = "1e-9"
    try:
        weighted = PressureSolver(Q, dofs, True, "febed_test_direct_", weighted=True)
        assert (weighted.ksp.getType() == PETSc.KSP.Type.PREONLY) == expect_direct
    finally:
        opts.delValue("febed_test_direct_weighted_ksp_rtol")
    for s in (direct, cg, again, weighted):
        s.destroy()


def test_user_options_keep_the_iterative_solver():
    Q, dofs = _space(6)
    opts = PETSc.Options()
    opts["febed_test_user_pc_type"] = "jacobi"
    try:
        s = PressureSolver(Q, dofs, True, "febed_test_user_")
        assert s.ksp.getType() == PETSc.KSP.Type.CG and s.ksp.getPC().getType() == "jacobi"
        s.destroy()
    finally:
        opts.delValue("febed_test_user_pc_type")


def test_a_user_tolerance_keeps_the_iterative_solver():
    Q, dofs = _space(6)
    opts = PETSc.Options()
    opts["febed_test_tol_ksp_max_it"] = 50
    try:
        s = PressureSolver(Q, dofs, True, "febed_test_tol_")
        assert s.ksp.getType() == PETSc.KSP.Type.CG
        s.destroy()
    finally:
        opts.delValue("febed_test_tol_ksp_max_it")


def test_closed_domain_keeps_the_iterative_solver():
    """Without a pressure node L is singular (constant null space): no factorisation."""
    Q, _ = _space(6)
    s = PressureSolver(Q, np.zeros(0, dtype=np.int32), False, "febed_test_closed_")
    assert s.ksp.getType() == PETSc.KSP.Type.CG
    s.destroy()


def test_a_failed_default_preconditioner_falls_back_to_gamg():
    """A closed domain's L is singular: an LU factorisation of it fails (zero pivot), like a failed ML setup."""
    Q, _ = _space(6)
    b = _rhs(Q)
    b -= b.mean()  # compatible with the constant null space
    s = PressureSolver(Q, np.zeros(0, dtype=np.int32), False, "febed_test_fallback_")
    s.ksp.getPC().setType("lu")  # as if the default preconditioner's setup failed
    phi, its = s.solve(b, 1e-10, 1e-300)
    assert s.fallbacks == 1 and s.ksp.getPC().getType() == "gamg" and its > 0
    ref = PressureSolver(Q, np.zeros(0, dtype=np.int32), False, "febed_test_fallback_ref_")
    phi_ref, _ = ref.solve(b, 1e-10, 1e-300)
    n = Q.dofmap.index_map.size_local
    d = (phi - phi.mean())[:n] - (phi_ref - phi_ref.mean())[:n]
    assert np.max(np.abs(d)) <= 1e-7 * np.max(np.abs(phi_ref))
    for solver in (s, ref):
        solver.destroy()


def test_a_failed_user_preconditioner_is_reported_not_replaced():
    Q, _ = _space(6)
    b = _rhs(Q)
    b -= b.mean()
    opts = PETSc.Options()
    opts["febed_test_userlu_pc_type"] = "lu"
    try:
        s = PressureSolver(Q, np.zeros(0, dtype=np.int32), False, "febed_test_userlu_")
        with pytest.raises(pressure.PressureSolveError, match="did not converge"):
            s.solve(b, 1e-10, 1e-300)
        assert s.fallbacks == 0
        s.destroy()
    finally:
        opts.delValue("febed_test_userlu_pc_type")


def test_a_failed_default_preconditioner_of_the_weighted_solve_falls_back_to_gamg(monkeypatch):
    """The same for the drag-weighted solve (its own prefix): a singular L_w whose default factorisation fails."""
    Q, _ = _space(6)
    b = _rhs(Q)
    b -= b.mean()
    n_local = Q.dofmap.index_map.size_local + Q.dofmap.index_map.num_ghosts
    w = np.linspace(0.2, 1.0, n_local)
    monkeypatch.setattr(pressure, "DEFAULT_OPTIONS", {"ksp_type": "cg", "pc_type": "lu"})  # fails as ML may
    s = PressureSolver(Q, np.zeros(0, dtype=np.int32), False, "febed_test_wfallback_", weighted=True)
    s.set_weights(w)
    phi, its = s.solve(b, 1e-10, 1e-300, weighted=True)
    assert s.fallbacks == 1 and s.ksp_w.getPC().getType() == "gamg" and its > 0
    r = s.weighted.A.createVecs()[1]
    x = r.duplicate()
    x.array[:] = phi[: x.array.size]
    s.weighted.A.mult(x, r)
    assert np.max(np.abs(r.array - b[: r.array.size])) <= 1e-8 * np.max(np.abs(b))
    s.destroy()


@pytest.mark.mpi
def test_small_serial_meshes_precondition_the_weighted_solve_by_cholesky(monkeypatch):
    # on one process with an outlet and few nodes the weighted solve's preconditioner is the Cholesky factor
    # of L_w, elsewhere its AMG; both solve the same weighted problem to the tolerance
    comm = MPI.COMM_WORLD
    Q, dofs = _space()
    b = _rhs(Q)
    imap = Q.dofmap.index_map
    n = imap.size_local
    w = 0.05 + (imap.local_to_global(np.arange(n + imap.num_ghosts, dtype=np.int32)) % 7) / 7.0
    phis = []
    for limit in (5_000, 0):
        monkeypatch.setattr(pressure, "WEIGHTED_DIRECT_MAX_NODES", limit)
        s = PressureSolver(Q, dofs, True, "febed_test_wdirect_", weighted=True)
        s.set_weights(w)
        phi, its = s.solve(b, 1e-12, 1e-300, weighted=True)
        expect = "cholesky" if comm.size == 1 and limit else ("ml" if comm.size == 1 else "gamg")
        assert s.ksp_w.getPC().getType() == expect and its >= 1
        phis.append(phi[:n])
        s.destroy()
    err = comm.allreduce(float(np.max(np.abs(phis[0] - phis[1]), initial=0.0)), op=MPI.MAX)
    scale = comm.allreduce(float(np.max(np.abs(phis[1]), initial=0.0)), op=MPI.MAX)
    assert err <= 1e-9 * scale
