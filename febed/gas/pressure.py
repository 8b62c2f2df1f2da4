"""The pressure-increment Poisson solve: a constant stiffness matrix and its AMG preconditioner, set up once.

Following YALES2 (DESIGN.md "Data flow" step 3), the gas momentum carries −∇P and the particles −V_p∇P,
so the operator of seed 001 eq 39 is the constant Laplacian L_ij = ∫ ∇φ_i·∇φ_j dx. It is assembled once,
with unit rows at the outlet (pressure) nodes, and its KSP (default CG + hypre BoomerAMG) is set up once;
every step only writes the right-hand side and solves from the previous solution. Without any pressure
node the constant null space is attached and removed from the right-hand side.

Solver options come from the PETSc options database under the prefix given (default `febed_pressure_`),
e.g. `-febed_pressure_pc_type gamg`; the defaults below apply only to options the user did not set.
"""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx.fem
import dolfinx.fem.petsc
import dolfinx.la
import numpy as np
import ufl

DEFAULT_OPTIONS = {
    "ksp_type": "cg",
    "pc_type": "hypre",
    "pc_hypre_type": "boomeramg",
    "pc_hypre_boomeramg_coarsen_type": "HMIS",
    "pc_hypre_boomeramg_interp_type": "ext+i",
    "pc_hypre_boomeramg_strong_threshold": 0.5,
    "pc_hypre_boomeramg_agg_nl": 1,
}


class PressureSolver:
    """Solve L φ = b for the scaled pressure increment φ = Δt δP / ρ, b given on the owned nodes."""

    def __init__(self, Q, dirichlet_dofs: np.ndarray, has_dirichlet: bool, prefix: str, rtol: float):
        comm = Q.mesh.comm
        v, w = ufl.TestFunction(Q), ufl.TrialFunction(Q)
        bcs = [dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), dirichlet_dofs, Q)] if has_dirichlet else []
        self.A = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(ufl.inner(ufl.grad(w), ufl.grad(v)) * ufl.dx), bcs)
        self.A.assemble()
        self.nullspace = None
        if not has_dirichlet:
            self.nullspace = PETSc.NullSpace().create(constant=True, comm=comm)
            self.A.setNullSpace(self.nullspace)
        imap = Q.dofmap.index_map
        self.bc_rows = np.asarray(dirichlet_dofs)[np.asarray(dirichlet_dofs) < imap.size_local]
        self.b = dolfinx.la.create_petsc_vector(imap, 1)
        self.x = dolfinx.la.create_petsc_vector(imap, 1)
        opts = PETSc.Options()
        for key, val in DEFAULT_OPTIONS.items():
            if not opts.hasName(prefix + key):
                opts[prefix + key] = val
        if not opts.hasName(prefix + "ksp_rtol"):
            opts[prefix + "ksp_rtol"] = rtol
        self.ksp = PETSc.KSP().create(comm)
        self.ksp.setOptionsPrefix(prefix)
        self.ksp.setOperators(self.A)
        self.ksp.setFromOptions()
        self.ksp.setInitialGuessNonzero(True)
        self.ksp.setUp()
        self.setup_count = 1  # the operator never changes: PETSc reuses this setup in every solve
        self.comm = comm

    def solve(self, rhs_owned: np.ndarray) -> tuple[np.ndarray, int]:
        """Write b (owned rows), zero the pressure rows, solve from the last φ; φ over local dofs, iterations."""
        self.b.array[:] = rhs_owned
        self.b.array[self.bc_rows] = 0.0
        if self.nullspace is not None:
            self.nullspace.remove(self.b)
        self.ksp.solve(self.b, self.x)
        reason = self.ksp.getConvergedReason()
        if reason < 0:
            raise RuntimeError(f"pressure solve diverged (KSP reason {reason}); check the time step and ε")
        self.x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        with self.x.localForm() as loc:
            phi = loc.array.copy()
        return phi, self.ksp.getIterationNumber()

    def residual_sum(self) -> float:
        """Global Σ_i (b − L φ)_i over non-pressure rows: the discrete continuity defect of the last solve."""
        r = self.b.duplicate()
        self.A.mult(self.x, r)
        r.aypx(-1.0, self.b)
        r.array[self.bc_rows] = 0.0
        s = self.comm.allreduce(float(r.array.sum()), op=MPI.SUM)
        r.destroy()
        return s

    def destroy(self) -> None:
        """Free the PETSc objects (collective)."""
        for obj in (self.ksp, self.A, self.b, self.x):
            obj.destroy()
