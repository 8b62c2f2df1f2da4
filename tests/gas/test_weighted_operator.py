"""The drag-weighted pressure operator L_w = Σ_c w_c K_c (febed.gas.weighted) on every cell type."""

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx.mesh
import numpy as np
import pytest

from febed.gas import weighted
from febed.gas.operators import build_operators

CELLS = ["triangle", "quadrilateral", "tetrahedron", "hexahedron"]


def distorted_mesh(cell: str):
    """A small box of `cell`s with curved, non-affine cells (hexahedra and quadrilaterals are not parallelepipeds)."""
    comm = MPI.COMM_WORLD
    kind = getattr(dolfinx.mesh.CellType, cell)
    if cell in ("triangle", "quadrilateral"):
        mesh = dolfinx.mesh.create_rectangle(comm, [[0.0, 0.0], [1.0, 0.5]], [8, 5], kind)
    else:
        mesh = dolfinx.mesh.create_box(comm, [[0.0, 0.0, 0.0], [1.0, 0.5, 0.3]], [6, 4, 3], kind)
    x = mesh.geometry.x
    x[:, 0] += 0.05 * np.sin(3.0 * x[:, 1] + 1.0) * (1.0 + x[:, 0])
    x[:, 1] += 0.04 * np.cos(4.0 * x[:, 0])
    return mesh


def operator(cell: str):
    """The nodal operators of the distorted mesh of `cell`s and its weighted operator without Dirichlet nodes."""
    ops = build_operators(distorted_mesh(cell))
    return ops, weighted.WeightedLaplacian(ops.Q, np.zeros(0, dtype=np.int32))


def ghosted(ops, owned: np.ndarray) -> np.ndarray:
    """`owned` values (a PETSc vector's array) over the owned and ghost nodes."""
    v = dolfinx.la.create_petsc_vector(ops.Q.dofmap.index_map, 1)
    v.array[:] = owned
    v.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
    with v.localForm() as loc:
        return ops.extension.extend("test", v, loc.array.copy()).copy()


@pytest.mark.mpi
@pytest.mark.parametrize("cell", CELLS)
def test_unit_weights_give_the_assembled_laplacian(cell):
    # with w = 1 and no Dirichlet nodes, L_w x is DOLFINx's own stiffness matrix times x, to round-off: the
    # element matrices, their quadrature and the ghost rows summed into their owners agree with the assembly
    ops, op = operator(cell)
    op.set_weights(np.ones(ops.n_local))
    x = op.A.createVecs()[0]
    x.array[:] = np.random.default_rng(MPI.COMM_WORLD.rank).random(x.array.size)
    y = op.A.createVecs()[1]
    op.A.mult(x, y)
    # reference: the owned CSR rows of ∫∇φ_i·∇φ_j dx (febed.gas.operators) applied to x over the extended columns
    x_ext = ghosted(ops, x.array_r)
    rows = zip(ops.indptr[:-1], ops.indptr[1:], strict=True)
    ref = np.array([ops.laplacian[a:b] @ x_ext[ops.indices[a:b]] for a, b in rows])
    err = MPI.COMM_WORLD.allreduce(float(np.abs(y.array_r - ref).max(initial=0.0)), op=MPI.MAX)
    scale = MPI.COMM_WORLD.allreduce(float(np.abs(ref).max(initial=0.0)), op=MPI.MAX)
    assert err < 1e-12 * scale, (cell, err, scale)
    op.destroy()


@pytest.mark.mpi
@pytest.mark.parametrize("cell", CELLS)
def test_weighted_operator_is_symmetric_positive_semidefinite_with_zero_row_sums(cell):
    # weights spanning four decades (a packed bed beside clear gas, wall nodes): x·L_w y = y·L_w x, L_w 1 = 0,
    # and x·L_w x >= 0 for random x (an edge-by-edge weighting of L, used before, made CG stop on an indefinite
    # operator in the tetrahedral pseudo-2D bed of test_bed3d.py)
    ops, op = operator(cell)
    rng = np.random.default_rng(7 + MPI.COMM_WORLD.rank)
    op.set_weights(ghosted(ops, 10.0 ** rng.uniform(-4.0, 0.0, ops.n_owned))[: ops.n_local])
    x, y = op.A.createVecs()
    ax, ay = op.A.createVecs()
    one, row_sums = op.A.createVecs()
    one.set(1.0)
    op.A.mult(one, row_sums)
    assert row_sums.norm(PETSc.NormType.INFINITY) < 1e-12 * op.A.norm(PETSc.NormType.INFINITY)
    for _ in range(5):
        x.array[:] = rng.standard_normal(x.array.size)
        y.array[:] = rng.standard_normal(y.array.size)
        op.A.mult(x, ax)
        op.A.mult(y, ay)
        assert abs(x.dot(ay) - y.dot(ax)) < 1e-12 * abs(x.dot(ax)) + 1e-300
        assert x.dot(ax) >= 0.0
    op.destroy()


@pytest.mark.mpi
def test_restart_rebuilds_the_weighted_preconditioner_bit_for_bit(monkeypatch):
    # the weighted solve's preconditioner is rebuilt from time to time and kept in between: a solver restored
    # from a state of step 6 (which holds the weights of the last build) continues exactly as the original,
    # with a build forced after every solve (REFRESH_ITERATIONS = 0) and with none after the first
    from _gas_cases import channel, channel_solver

    from febed.gas import pressure

    md = channel(0.1, 0.04, 20, 8)

    def K_at(s, t):  # a drag that moves and changes, as a bubbling bed's
        return 3.0e4 * (1.2 + np.sin(300.0 * t + 80.0 * s.x[:, 0]) * np.cos(60.0 * s.x[:, 1]))

    for refresh in (0, 1000):
        monkeypatch.setattr(pressure, "REFRESH_ITERATIONS", refresh)
        a = channel_solver(md, 0.3, eps=0.45)
        for k in range(12):
            a.step(1e-4, K=K_at(a, a.t))
            if k == 5:
                state, t = {key: v.copy() for key, v in a.get_state().items()}, a.t
        assert "pc_weights" in state
        b = channel_solver(md, 0.3, eps=0.45)
        b.set_state(state, t)
        for _ in range(6):
            b.step(1e-4, K=K_at(b, b.t))
        same = np.array_equal(a.q, b.q) and np.array_equal(a.p, b.p)
        assert MPI.COMM_WORLD.allreduce(same, op=MPI.LAND), refresh
        builds = a.pressure.pc_setups
        assert builds > 10 if refresh == 0 else builds == 1, builds


@pytest.mark.mpi
@pytest.mark.parametrize("cell", ["tetrahedron", "hexahedron"])
def test_coo_fill_equals_the_fill_by_rows(cell, monkeypatch):
    # on several ranks L_w is filled through PETSc's COO assembly (febed.gas.petsc_coo), which sums the ghost
    # rows' entries into their owners; the fill by rows into DOLFINx's pattern (kept for a PETSc without COO
    # assembly) must give the same operator, Dirichlet rows included, after a refill with other weights
    ops = build_operators(distorted_mesh(cell))
    rng = np.random.default_rng(3 + MPI.COMM_WORLD.rank)
    bc = np.flatnonzero(ops.Q.tabulate_dof_coordinates()[: ops.n_local, 0] < 0.2).astype(np.int32)
    coo = weighted.WeightedLaplacian(ops.Q, bc)
    monkeypatch.setattr(weighted, "coo_matrix", lambda *args: None)
    rows = weighted.WeightedLaplacian(ops.Q, bc)
    for _ in range(2):
        w = ghosted(ops, 10.0 ** rng.uniform(-3.0, 0.0, ops.n_owned))[: ops.n_local]
        coo.set_weights(w)
        rows.set_weights(w)
    x, y_coo = coo.A.createVecs()
    y_rows = y_coo.duplicate()
    x.array[:] = rng.standard_normal(x.array.size)
    coo.A.mult(x, y_coo)
    rows.A.mult(x, y_rows)
    y_rows.axpy(-1.0, y_coo)
    assert y_rows.norm(PETSc.NormType.INFINITY) <= 1e-13 * y_coo.norm(PETSc.NormType.INFINITY)
    coo.destroy()
    rows.destroy()
