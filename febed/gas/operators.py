"""Constant nodal operators of the gas step, assembled once with DOLFINx and kept as plain CSR arrays.

The gas fields live at the mesh nodes: a scalar P1 (triangles, tetrahedra) or Q1 (quadrilaterals,
hexahedra) space `Q` whose local dof numbering (owned first, then ghosts) is the numbering of every nodal
array. The bilinear forms below are assembled once into PETSc matrices and their owned rows copied into
one CSR structure with local column indices, shared by all coefficients (see `febed.gas.kernels`):

    grad[k, d] = ∫ φ_i ∂_d φ_j dx                      (Galerkin gradient / divergence)
    tens[k, :] = ∫ ∂_d φ_i ∂_e φ_j dx (d = e), ∫ (∂_d φ_i ∂_e φ_j + ∂_e φ_i ∂_d φ_j) dx (d < e)

plus the lumped mass (node control volume) ΔV_i = ∫ φ_i dx, the boundary normal weights
B_i = ∫_∂Ω φ_i n ds (per facet tag too) and a nodal filter width from the surrounding cell volumes.
With MPI every nodal vector is accumulated over ranks (reverse scatter, add) before use.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx.fem
import dolfinx.fem.petsc
import numpy as np
import ufl

from febed.gas.edges import EdgeOperators, edge_operators


def nodal_family(mesh) -> str:
    """The family of the nodal element: "Q" on quadrilaterals/hexahedra, "Lagrange" on simplices."""
    return "Q" if mesh.topology.cell_type.name in ("quadrilateral", "hexahedron") else "Lagrange"


def nodal_space(mesh) -> dolfinx.fem.FunctionSpace:
    """The scalar nodal space: P1 on simplices, Q1 on quadrilaterals/hexahedra."""
    return dolfinx.fem.FunctionSpace(mesh, (nodal_family(mesh), 1))


def accumulate(vec: PETSc.Vec) -> np.ndarray:
    """Sum the ghost contributions of an assembled ghosted vector into owners, refresh ghosts; local array."""
    vec.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    vec.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
    with vec.localForm() as loc:
        return loc.array.copy()


def assemble_nodal(form) -> np.ndarray:
    """Assemble a linear form into a nodal array over the local dofs (owned + ghost), ranks summed."""
    vec = dolfinx.fem.petsc.assemble_vector(dolfinx.fem.form(form))
    out = accumulate(vec)
    vec.destroy()
    return out


def _owned_csr(A: PETSc.Mat, imap, extra: np.ndarray | None):
    """Owned rows of an assembled matrix as CSR with local column indices; the extra (non-ghost) columns.

    Columns owned here or ghosted by the mesh keep their local index; columns of nodes the mesh does not
    ghost (cells touching an owned node only at a vertex/edge, on another rank) are numbered after the
    ghosts, n_local + k, k their rank in `extra` (sorted global indices; computed on the first call).
    """
    indptr, cols, vals = A.getValuesCSR()
    r0, r1 = imap.local_range
    n_local = imap.size_local + imap.num_ghosts
    ghosts = np.asarray(imap.ghosts, dtype=np.int64)
    order = np.argsort(ghosts)
    sorted_ghosts = ghosts[order]
    cols = np.asarray(cols, dtype=np.int64)
    local = cols - r0
    off = np.flatnonzero((cols < r0) | (cols >= r1))
    pos = np.searchsorted(sorted_ghosts, cols[off])
    pos_c = np.minimum(pos, max(sorted_ghosts.size - 1, 0))
    found = (pos < sorted_ghosts.size) & (sorted_ghosts[pos_c] == cols[off]) if sorted_ghosts.size else pos < 0
    local[off[found]] = imap.size_local + order[pos[found]]
    missing = cols[off[~found]]
    if extra is None:
        extra = np.unique(missing)
    local[off[~found]] = n_local + np.searchsorted(extra, missing)
    return np.asarray(indptr, dtype=np.int64), local.astype(np.int32), np.asarray(vals, dtype=np.float64), extra


class GhostExtension:
    """Nodal arrays extended by the values at the extra columns of the owned rows (see `_owned_csr`).

    The mesh ghosts only the cells sharing a facet with this rank's cells, so an owned node can be
    connected to nodes that are neither owned nor ghosts here. Their values are fetched with one PETSc
    scatter per array (collective; nothing to do, and no copy, when no rank has extra columns).
    """

    def __init__(self, imap, extra: np.ndarray, comm):
        self.n_local = imap.size_local + imap.num_ghosts
        self.extra = np.asarray(extra, dtype=np.int64)
        self.n_extra = self.extra.size
        self.active = comm.allreduce(self.n_extra, op=MPI.MAX) > 0
        self._scatters: dict[int, tuple] = {}
        self._buffers: dict[str, np.ndarray] = {}

    def extend(self, name: str, vec: PETSc.Vec, local: np.ndarray) -> np.ndarray:
        """Array (n_local + n_extra, bs) of `local` (the ghosted values of `vec`) followed by the extra values."""
        bs = vec.getBlockSize()
        if not self.active:
            return local.reshape(self.n_local, bs) if bs > 1 else local
        if bs not in self._scatters:
            iset = PETSc.IS().createBlock(bs, self.extra.astype(PETSc.IntType), comm=PETSc.COMM_SELF)
            target = PETSc.Vec().createSeq(self.n_extra * bs, comm=PETSc.COMM_SELF)
            self._scatters[bs] = (PETSc.Scatter().create(vec, iset, target, None), target)
        scatter, target = self._scatters[bs]
        scatter.scatter(vec, target, addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        key = f"{name}/{bs}"
        if key not in self._buffers:
            self._buffers[key] = np.empty((self.n_local + self.n_extra) * bs)
        buf = self._buffers[key]
        buf[: self.n_local * bs] = local
        buf[self.n_local * bs :] = target.array
        return buf.reshape(-1, bs) if bs > 1 else buf


@dataclass
class NodalOperators:
    """The constant nodal operators of one mesh (see the module docstring)."""

    Q: dolfinx.fem.FunctionSpace
    n_owned: int
    n_local: int
    indptr: np.ndarray  # (n_owned + 1,) int64
    indices: np.ndarray  # (nnz,) int32, local columns
    grad: np.ndarray  # (nnz, gdim)
    tens: np.ndarray  # (nnz, gdim (gdim + 1) / 2)
    mass: np.ndarray  # (n_local,) ∫ φ_i dx [m^3]
    bnormal: np.ndarray  # (n_local, gdim) ∫_∂Ω φ_i n ds [m^2]
    width: np.ndarray  # (n_local,) filter width / cell size at the node [m]
    extension: GhostExtension  # values at the extra columns (nodes the mesh does not ghost)

    @property
    def n_ext(self) -> int:
        """Rows of an extended nodal array: owned + ghost + extra column nodes."""
        return self.n_local + self.extension.n_extra

    @property
    def gdim(self) -> int:
        """Geometric dimension."""
        return self.grad.shape[1]

    @cached_property
    def edges(self) -> EdgeOperators:
        """The entries of `grad` and `tens` by edge, for the momentum sweep (`febed.gas.edges`)."""
        return edge_operators(self.indptr, self.indices, self.grad, self.tens)

    @cached_property
    def laplacian(self) -> np.ndarray:
        """Values (nnz,) of the unmodified stiffness ∫ ∇φ_i·∇φ_j dx in the shared CSR structure (owned rows)."""
        return np.ascontiguousarray(self.tens[:, : self.gdim].sum(axis=1))


def build_operators(mesh) -> NodalOperators:
    """Assemble every constant nodal operator of `mesh` once (collective)."""
    Q = nodal_space(mesh)
    gdim = mesh.geometry.dim
    imap = Q.dofmap.index_map
    v, w = ufl.TestFunction(Q), ufl.TrialFunction(Q)
    forms = [v * w.dx(d) for d in range(gdim)]
    forms += [v.dx(d) * w.dx(d) for d in range(gdim)]
    forms += [v.dx(d) * w.dx(e) + v.dx(e) * w.dx(d) for d in range(gdim) for e in range(d + 1, gdim)]
    # one compiled form for all of them: a selector Constant picks each in turn (one JIT compilation per cell
    # type instead of one per form; the selected term is computed exactly as alone: times 1, plus zeros)
    pick = dolfinx.fem.Constant(mesh, PETSc.ScalarType(np.zeros(len(forms))))
    a_all = dolfinx.fem.form(sum(pick[k] * a for k, a in enumerate(forms)) * ufl.dx)
    pattern, coefs, extra = None, [], None
    for k in range(len(forms)):
        pick.value[:] = 0.0
        pick.value[k] = 1.0
        A = dolfinx.fem.petsc.assemble_matrix(a_all)
        A.assemble()
        indptr, indices, vals, extra = _owned_csr(A, imap, extra)
        A.destroy()
        if pattern is None:
            pattern = (indptr, indices)
        elif not (np.array_equal(pattern[0], indptr) and np.array_equal(pattern[1], indices)):
            raise RuntimeError("nodal operators: assembled matrices do not share one sparsity pattern")
        coefs.append(vals)
    grad = np.ascontiguousarray(np.stack(coefs[:gdim], axis=1))
    tens = np.ascontiguousarray(np.stack(coefs[gdim:], axis=1))
    mass = assemble_nodal(v * ufl.dx)
    bnormal = _boundary_weights(mesh, 1, ufl.ds)
    # filter width: (mass-weighted mean volume of the cells around the node)^(1/d)
    dg0 = dolfinx.fem.FunctionSpace(mesh, ("DG", 0))
    vol = dolfinx.fem.Function(dg0)
    vol.x.array[:] = assemble_nodal(ufl.TestFunction(dg0) * ufl.dx)
    width = (assemble_nodal(v * vol * ufl.dx) / mass) ** (1.0 / gdim)
    return NodalOperators(
        Q=Q,
        n_owned=imap.size_local,
        n_local=imap.size_local + imap.num_ghosts,
        indptr=pattern[0],
        indices=pattern[1],
        grad=grad,
        tens=tens,
        mass=mass,
        bnormal=bnormal,
        width=width,
        extension=GhostExtension(imap, extra, mesh.comm),
    )


def _boundary_weights(mesh, order: int, ds) -> np.ndarray:
    """∫ φ_i n ds (order 1: (n_local, gdim)) or ∫ φ_i n⊗n ds (order 2: (n_local, gdim, gdim)) over `ds`.

    One form with a vector (tensor) test function of the nodal element: one JIT compilation per cell type
    gives every component (ranks summed).
    """
    gdim = mesh.geometry.dim
    family = nodal_family(mesh)
    n = ufl.FacetNormal(mesh)
    if order == 1:
        V = dolfinx.fem.VectorFunctionSpace(mesh, (family, 1))
        integrand = ufl.inner(n, ufl.TestFunction(V))
    else:
        V = dolfinx.fem.TensorFunctionSpace(mesh, (family, 1))
        integrand = ufl.inner(ufl.outer(n, n), ufl.TestFunction(V))
    values = assemble_nodal(integrand * ds)
    return values.reshape((-1,) + (gdim,) * order)


def tag_normal_weights(mesh_data, Q, names) -> np.ndarray:
    """(n_local, gdim) array ∫_Γ φ_i n ds over the facets of the named tags (ranks summed)."""
    mesh = mesh_data.mesh
    ds = mesh_data.ds(names)
    if ds is None:
        return np.zeros((Q.dofmap.index_map.size_local + Q.dofmap.index_map.num_ghosts, mesh.geometry.dim))
    return _boundary_weights(mesh, 1, ds)


def normal_tensor_weights(mesh_data, Q, names) -> np.ndarray:
    """(n_local, gdim, gdim) array ∫_Γ φ_i n⊗n ds over the facets of the named tags (ranks summed)."""
    mesh = mesh_data.mesh
    gdim = mesh.geometry.dim
    ds = mesh_data.ds(names)
    if ds is None:
        return np.zeros((Q.dofmap.index_map.size_local + Q.dofmap.index_map.num_ghosts, gdim, gdim))
    return _boundary_weights(mesh, 2, ds)


def global_sum(comm, local_owned: np.ndarray | float) -> float:
    """Sum of owned values over all ranks."""
    return comm.allreduce(float(np.sum(local_owned)), op=MPI.SUM)
