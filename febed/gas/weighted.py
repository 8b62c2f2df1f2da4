"""The drag-weighted pressure operator L_w = Σ_c w_c K_c, applied cell by cell, and its preconditioner matrix.

The predictor treats the momentum exchange implicitly, so a pressure increment moves the gas at node i by
w_i = 1/(1 + D_i), D_i = K_i Δt/(ρ ε_i) (`febed.gas.vans`, "Drag and the pressure equation"). The pressure
equation that carries the same factor is the finite-element form of ∇·(w ∇φ):

    (L_w)_ij = Σ_c w_c ∫_c ∇φ_i·∇φ_j dx = Σ_c w_c (K_c)_ij,      w_c = mean of w over the nodes of cell c.

Each K_c is symmetric positive semi-definite with zero row sums, so L_w is too for any positive weights, on
every cell type (an edge-by-edge weighting of L is not: on tetrahedra and stretched hexahedra L has positive
off-diagonal entries, and weighting them unequally can make the operator indefinite). For w = 1 it is L.

The element matrices are computed once (basix quadrature on the cell geometry, the degree DOLFINx takes for
∫∇φ_i·∇φ_j dx) over the owned cells of each rank. Each step sums w_c K_c into the matrix in one compiled pass
over the entries (a small share of DOLFINx's own assembly of the same form, which evaluates the quadrature
again).
"""

from __future__ import annotations

from petsc4py import PETSc

import basix
import dolfinx.fem
import dolfinx.fem.petsc
import dolfinx.la
import numpy as np
import ufl

from febed.gas import kernels
from febed.gas.petsc_coo import coo_matrix

# quadrature degree of the element matrices: DOLFINx's own estimate for ∫∇φ_i·∇φ_j dx on degree-1 geometry
# (tests/gas/test_weighted_operator.py checks L_w for w = 1 against the assembled L on every cell type)
_DEGREE = {"triangle": 1, "tetrahedron": 1, "quadrilateral": 4, "hexahedron": 4}
_CELLS = {
    "triangle": basix.CellType.triangle,
    "tetrahedron": basix.CellType.tetrahedron,
    "quadrilateral": basix.CellType.quadrilateral,
    "hexahedron": basix.CellType.hexahedron,
}
_CHUNK = 20_000  # cells per block of the element-matrix computation (bounds its temporary memory)


def element_stiffness(Q) -> tuple[np.ndarray, np.ndarray]:
    """Dofs (n_cells, n_dofs) and matrices K_c = ∫_c ∇φ_a·∇φ_b dx (n_cells, n_dofs, n_dofs) of the owned cells."""
    mesh = Q.mesh
    tdim, gdim = mesh.topology.dim, mesh.geometry.dim
    name = mesh.topology.cell_type.name
    n_cells = mesh.topology.index_map(tdim).size_local
    n_dofs = Q.dofmap.dof_layout.num_dofs
    dofs = np.ascontiguousarray(Q.dofmap.list.array.reshape(-1, n_dofs)[:n_cells], dtype=np.int32)
    X = Q.tabulate_dof_coordinates()[:, :gdim]
    element = basix.create_element(basix.ElementFamily.P, _CELLS[name], 1)
    points, weights = basix.make_quadrature(basix.QuadratureType.Default, _CELLS[name], _DEGREE[name])
    dphi = element.tabulate(1, points)[1:, :, :, 0]  # (tdim, n_q, n_dofs) reference gradients
    K = np.empty((n_cells, n_dofs, n_dofs))
    for c0 in range(0, n_cells, _CHUNK):
        xc = X[dofs[c0 : c0 + _CHUNK]]  # (c, a, gdim)
        J = np.einsum("cai,tqa->cqit", xc, dphi)  # dx_i/dξ_t
        det = np.abs(np.linalg.det(J))
        grad = np.einsum("cqti,tqa->cqai", np.linalg.inv(J), dphi)  # ∇_x φ_a = J⁻ᵀ ∇_ξ φ_a
        K[c0 : c0 + _CHUNK] = np.einsum("q,cq,cqai,cqbi->cab", weights, det, grad, grad)
    return dofs, K


def _local_csr(dofs: np.ndarray, n_local: int):
    """The local CSR pattern (rows and columns local node indices) of the cells' entries, and each entry's place."""
    nd = dofs.shape[1]
    rows = np.repeat(dofs, nd, axis=1).ravel().astype(np.int64)
    cols = np.tile(dofs, (1, nd)).ravel().astype(np.int64)
    keys, place = np.unique(rows * n_local + cols, return_inverse=True)
    r, c = keys // n_local, (keys % n_local).astype(np.int32)
    indptr = np.zeros(n_local + 1, dtype=np.int32)
    np.cumsum(np.bincount(r, minlength=n_local), out=indptr[1:])
    return indptr, c, r, place.astype(np.int32)


class WeightedLaplacian:
    """L_w = Σ_c w_c K_c assembled at every `set_weights`, with the Dirichlet rows (unit) and columns (dropped).

    `set_weights` takes the nodal weights over the local (owned and ghost) nodes and writes `vals`, L_w in the
    local CSR of the cells' entries (one compiled pass over the entries in CSR order). On one process the
    PETSc matrix `A` is built on `vals` itself; on several, `vals` are its COO entries (`febed.gas.petsc_coo`:
    PETSc sums them and sends the ghost rows to their owners by a plan made once). `matrix(vals)` makes
    another such matrix (the preconditioner's).
    `pressure_rows_product` is (L_w x)_i at the Dirichlet (pressure) rows without the modification, over
    the cells that touch them (the mass balance reads it).
    """

    def __init__(self, Q, dirichlet_dofs: np.ndarray):
        dofs, K = element_stiffness(Q)
        self.dofs = dofs
        self.wc = np.ones(dofs.shape[0])
        imap = Q.dofmap.index_map
        n_local = imap.size_local + imap.num_ghosts
        self.comm = Q.mesh.comm
        self.n_owned = imap.size_local
        self.indptr, self.cols, rows, place = _local_csr(dofs, n_local)
        order = np.argsort(place, kind="stable")  # the cells' entries in CSR order
        self.entry_start = np.zeros(self.cols.size + 1, dtype=np.int64)
        np.cumsum(np.bincount(place, minlength=self.cols.size), out=self.entry_start[1:])
        self.entry_cell = (order // (dofs.shape[1] ** 2)).astype(np.int32)
        self.entry_value = K.reshape(-1)[order]
        self.vals = np.zeros(self.cols.size)
        bc = np.zeros(n_local, dtype=bool)
        bc[np.asarray(dirichlet_dofs, dtype=np.int64)] = True
        self.drop = np.flatnonzero(bc[rows] | bc[self.cols])  # Dirichlet rows and columns
        self.unit = np.flatnonzero(bc[rows] & (rows == self.cols) & (rows < imap.size_local))  # owned unit rows
        self.bc_cells = np.flatnonzero(bc[dofs].any(axis=1)).astype(np.int32)
        self.bc_K = np.ascontiguousarray(K[self.bc_cells])
        u, v = ufl.TrialFunction(Q), ufl.TestFunction(Q)
        self.form = dolfinx.fem.form(ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx)  # L's sparsity (several ranks)
        self._global_entries = None  # several ranks: each local CSR entry's global row and column (`matrix`)
        if self.comm.size > 1:
            l2g = imap.local_to_global(np.arange(n_local, dtype=np.int32))
            self._global_entries = (l2g[rows], l2g[self.cols])
        self._coo = {}  # the COO fill of each matrix made on several ranks, by its handle
        self.A = self.matrix(self.vals)
        self.yg = dolfinx.la.create_petsc_vector(imap, 1)

    def matrix(self, vals: np.ndarray) -> PETSc.Mat:
        """A PETSc matrix holding the local CSR values `vals` (on one process it is built on them)."""
        if self.comm.size == 1:
            n = self.indptr.size - 1
            return PETSc.Mat().createAIJWithArrays((n, n), (self.indptr, self.cols, vals), comm=PETSc.COMM_SELF)
        coo = coo_matrix(self.comm, self.n_owned, *self._global_entries)
        if coo is None:  # a PETSc without COO assembly: L's pattern from DOLFINx, filled row by row (`load`)
            return dolfinx.fem.petsc.create_matrix(self.form)
        self._coo[coo.M.handle] = coo
        coo.fill(vals)
        return coo.M

    def set_weights(self, w_local: np.ndarray) -> None:
        """Cell weights w_c from the nodal weights (owned and ghost nodes); `A` = L_w (collective)."""
        kernels.cell_means(self.dofs, w_local, self.wc)
        kernels.csr_weighted_sum(self.entry_start, self.entry_cell, self.entry_value, self.wc, self.vals)
        self.vals[self.drop] = 0.0
        self.vals[self.unit] = 1.0
        self.load(self.A, self.vals)

    def load(self, M: PETSc.Mat, vals: np.ndarray) -> None:
        """Make M (from `matrix(vals)`) hold `vals` after they changed (collective)."""
        coo = self._coo.get(M.handle)
        if coo is not None:  # sums the entries and sends the ghost rows to their owners
            coo.fill(vals)
            return
        if self.comm.size > 1:
            M.zeroEntries()
            M.setValuesLocalCSR(self.indptr, self.cols, vals, addv=PETSc.InsertMode.ADD)
        M.assemble()  # on one process only marks the matrix as changed

    def pressure_rows_product(self, x_local: np.ndarray) -> np.ndarray:
        """Owned rows of Σ_c w_c K_c x, exact at the Dirichlet rows only (collective: ghost rows to owners)."""
        with self.yg.localForm() as loc:
            kernels.cell_products(self.dofs, self.bc_K, self.wc, self.bc_cells, x_local, loc.array)
        self.yg.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return self.yg.array_r

    def destroy(self) -> None:
        """Free the PETSc objects (collective)."""
        for obj in (self.A, self.yg):
            obj.destroy()
