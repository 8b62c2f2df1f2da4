"""The pressure-increment Poisson solve: a constant stiffness matrix and its factorisation or AMG, set up once.

(Optionally the operator is the drag-weighted Laplacian of each step, `_WeightedOperator`, still
preconditioned by the constant matrix's AMG; `VANSParameters.drag_weighted_projection`.)

Following YALES2 (docs/theory.md, data flow, the gas step), the gas momentum carries −∇P and the particles −V_p∇P,
so the operator of seed 001 eq 39 is the constant Laplacian L_ij = ∫ ∇φ_i·∇φ_j dx. It is assembled once,
with unit rows at the outlet (pressure) nodes, and its KSP (default CG + algebraic multigrid) is set up once;
every step only writes the right-hand side and solves from the previous solution. Without any pressure
node the constant null space is attached and removed from the right-hand side.

On one process, with a pressure outlet and at most `DIRECT_MAX_NODES` nodes, the default is a sparse Cholesky
factorisation of L made once (two triangular solves per step); otherwise CG with algebraic multigrid.
Solver options come from the PETSc options database under the prefix given (default `febed_pressure_`),
e.g. `-febed_pressure_pc_type gamg`, or a direct factorisation set up once (fast on small meshes):
`-febed_pressure_ksp_type preonly -febed_pressure_pc_type cholesky -febed_pressure_pc_factor_mat_solver_type
mumps`. The defaults below apply only to options the user did not set. The tolerances are set by the gas
solver at each solve (see `VANSParameters.mass_tolerance`).
"""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx.fem
import dolfinx.fem.petsc
import dolfinx.la
import numpy as np
import ufl

from febed.gas import kernels

# CG + smoothed-aggregation AMG (Trilinos ML through PETSc) with one smoothing sweep per level: the
# fastest of hypre BoomerAMG (several settings), GAMG and ML on the seed-001 intermediate mesh with a
# bubbling-bed right-hand-side sequence (benchmarks/gas_step.py; ~23 ms vs ~39 ms GAMG, ~55 ms BoomerAMG
# per warm-started solve on this machine). Falls back to GAMG when PETSc was built without ML. On more
# than one rank the default is GAMG (19-21 ms per gas step on 2 ranks against 17 ms with ML): with Debian's
# PETSc 3.18 and ML, a process under `mpirun -n 2` that sets up a few ML solvers corrupts its heap and
# aborts (SEGV or "malloc(): invalid size" at the 2nd to 10th solver kept alive; serially 60 are fine).
# GAMG without the squared graph on the first level (`pc_gamg_square_graph 0`) coarsens less aggressively:
# fewer iterations; on 2 ranks the fluidized C2's gas took 4.30 instead of 4.80 min per simulated second
# (ML: 4.01), the start-up window 2.08 instead of 2.26.
DEFAULT_OPTIONS = {
    "ksp_type": "cg",
    "pc_type": "ml",
    "mg_levels_ksp_max_it": 1,
}
FALLBACK_OPTIONS = {"pc_type": "gamg", "pc_gamg_square_graph": 0}
# One process and at most this many nodes with a pressure outlet: a sparse Cholesky factorisation (PETSc's own,
# nested-dissection ordering) of the constant L, made once; every step is then two triangular solves, exact
# whatever the tolerance. On seed 000's 2D bed (1,900 nodes) the pressure solve costs a fifth of CG + ML's; on
# the seed-001 intermediate mesh (28,000 nodes, hexahedra) about the same (14-17 against 16-20 ms,
# benchmarks/gas_step.py), for ~40 MB more memory. Larger meshes, parallel runs, closed domains (singular L)
# and the drag-weighted projection keep CG + AMG.
DIRECT_MAX_NODES = 50_000
DIRECT_OPTIONS = {"ksp_type": "preonly", "pc_type": "cholesky"}


_DEFAULTS_WRITTEN: set[str] = set()  # option names febed (not the user) put into PETSc's options database


def _user_set(opts, name: str) -> bool:
    """Whether the user gave the PETSc option `name` (not a default a solver of this process wrote)."""
    return opts.hasName(name) and name not in _DEFAULTS_WRITTEN


def _write_defaults(opts, prefix: str, defaults: dict) -> None:
    """Put `defaults` into the options database under `prefix`, leaving alone every option the user gave."""
    for key, val in defaults.items():
        if not _user_set(opts, prefix + key):
            opts[prefix + key] = val
            _DEFAULTS_WRITTEN.add(prefix + key)


class PressureSolveError(RuntimeError):
    """The pressure Poisson solve did not converge (raised on every rank: the solve is collective)."""


class _WeightedOperator:
    """PETSc Python-matrix context: the edge-weighted Laplacian L_w (`kernels.weighted_laplacian`).

    It has L's Dirichlet rows (unit) and columns (dropped) and is applied with the CSR rows of `NodalOperators`.
    """

    def __init__(self, ops, dirichlet_dofs: np.ndarray):
        self.ops = ops
        self.vals = ops.laplacian.copy()
        imap = ops.Q.dofmap.index_map
        self.xg = dolfinx.la.create_petsc_vector(imap, 1)
        self.xl = np.empty(ops.n_local)
        keep = dolfinx.la.create_petsc_vector(imap, 1)
        with keep.localForm() as loc:
            loc.set(1.0)
            loc.array[np.asarray(dirichlet_dofs, dtype=np.int64)] = 0.0
        keep.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        with keep.localForm() as loc:
            local = loc.array.copy()
        self.keep = ops.extension.extend("keep", keep, local).copy()
        keep.destroy()

    def set_weights(self, w_ext: np.ndarray) -> None:
        kernels.weighted_laplacian(self.ops.indptr, self.ops.indices, self.ops.laplacian, w_ext, self.vals)

    def extended(self, x: PETSc.Vec) -> np.ndarray:
        """The values of `x` (owned) over the owned, ghost and extra columns (collective)."""
        self.xg.array[:] = x.array_r
        self.xg.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        with self.xg.localForm() as loc:
            self.xl[:] = loc.array_r
        return self.ops.extension.extend("weighted", self.xg, self.xl)

    def mult(self, mat, x, y):  # PETSc callback: y = A_w x
        kernels.apply_dirichlet_rows(self.ops.indptr, self.ops.indices, self.vals, self.extended(x), self.keep, y.array)


class PressureSolver:
    """Solve L φ = b for the scaled pressure increment φ = Δt δP / ρ, b given on the owned nodes.

    With `ops` (the gas step's `NodalOperators`) the operator can be the drag-weighted Laplacian instead
    (`set_weights`), solved by CG preconditioned with the constant L's AMG, which is still set up once.
    """

    def __init__(self, Q, dirichlet_dofs: np.ndarray, has_dirichlet: bool, prefix: str, ops=None):
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
        user_pc = _user_set(opts, prefix + "pc_type")
        direct = (
            comm.size == 1
            and has_dirichlet
            and ops is None
            and imap.size_global <= DIRECT_MAX_NODES
            and not any(_user_set(opts, name) for name in opts.getAll() if name.startswith(prefix))
        )  # any option of the user's for this solver (a type, a tolerance, ...) asks for the iterative one
        if not direct:
            defaults = DEFAULT_OPTIONS if comm.size == 1 else {**DEFAULT_OPTIONS, **FALLBACK_OPTIONS}
            _write_defaults(opts, prefix, defaults)
        self.ksp = PETSc.KSP().create(comm)
        self.ksp.setOptionsPrefix(prefix)
        self.weighted = None
        self.op = self.A  # the operator of the solve
        if ops is not None:
            self.weighted = _WeightedOperator(ops, dirichlet_dofs)
            n, N = imap.size_local, imap.size_global
            self.op = PETSc.Mat().createPython(((n, N), (n, N)), context=self.weighted, comm=comm)
            self.op.setUp()
            if self.nullspace is not None:
                self.op.setNullSpace(self.nullspace)
        self.ksp.setOperators(self.A)
        self._current = self.A
        try:
            self.ksp.setFromOptions()
        except PETSc.Error:
            if user_pc:
                raise
            _write_defaults(opts, prefix, FALLBACK_OPTIONS)
            self.ksp.setFromOptions()
        if direct:  # set on this solver only: the options database keeps what another solver may need
            self.ksp.setType(DIRECT_OPTIONS["ksp_type"])
            self.ksp.getPC().setType(DIRECT_OPTIONS["pc_type"])
        self.prefix = prefix
        self.user_pc = user_pc
        self.fallbacks = 0  # times a failed preconditioner setup was replaced by the fallback (`solve`)
        self._iterative_settings(opts)
        if self.weighted is not None and self.ksp.getType() == PETSc.KSP.Type.PREONLY:
            raise ValueError(
                "gas.drag_weighted_projection needs an iterative pressure solver: the PETSc options set "
                f"-{prefix}ksp_type preonly (one preconditioner application solves the constant Laplacian, not "
                "the weighted one); remove it or set drag_weighted_projection = false"
            )
        self.ksp.setUp()
        self.setup_count = 1  # the preconditioner's matrix never changes: PETSc reuses this setup in every solve
        self.comm = comm

    def _iterative_settings(self, opts) -> None:
        """Warm start and true-residual tolerances for an iterative solve (unless the user set the norm)."""
        if self.ksp.getType() != PETSc.KSP.Type.PREONLY:
            self.ksp.setInitialGuessNonzero(True)  # warm start from the previous increment
            if not opts.hasName(self.prefix + "ksp_norm_type"):
                self.ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)  # tolerances on the true residual

    def _fall_back(self) -> None:
        """Replace a preconditioner whose setup failed by CG + GAMG (`FALLBACK_OPTIONS`), from φ = 0 (collective)."""
        opts = PETSc.Options()
        _write_defaults(opts, self.prefix, {**DEFAULT_OPTIONS, **FALLBACK_OPTIONS})
        failed, self.ksp = self.ksp, PETSc.KSP().create(self.comm)  # a new solver: PETSc keeps the failure
        failed.destroy()
        self.ksp.setOptionsPrefix(self.prefix)
        self.ksp.setOperators(self._current, self.A)
        self.ksp.setFromOptions()
        self._iterative_settings(opts)
        self.ksp.setUp()
        self.setup_count += 1
        self.fallbacks += 1
        self.x.set(0.0)

    def set_weights(self, w_ext: np.ndarray) -> None:
        """Make the operator the edge-weighted Laplacian L_w for the weights `w_ext` (extended nodal array)."""
        self.weighted.set_weights(w_ext)

    def solve(self, rhs_owned: np.ndarray, rtol: float, atol: float, weighted: bool = False) -> tuple[np.ndarray, int]:
        """Write b (owned rows), zero the pressure rows, solve from the last φ; φ over local dofs, iterations.

        Converged when the true residual ||b − Lφ||_2 ≤ max(rtol ||b||_2, atol); L is the weighted operator
        of the last `set_weights` if `weighted` (collective: the same on every rank).
        """
        op = self.op if weighted else self.A
        if op is not self._current:
            self.ksp.setOperators(op, self.A)  # the preconditioner stays the constant L's: no new setup
            self._current = op
        self.ksp.setTolerances(rtol=rtol, atol=atol)
        self.b.array[:] = rhs_owned
        self.b.array[self.bc_rows] = 0.0
        if self.nullspace is not None:
            self.nullspace.remove(self.b)
        self.ksp.solve(self.b, self.x)
        reason = self.ksp.getConvergedReason()
        if reason == PETSc.KSP.ConvergedReason.DIVERGED_PCSETUP_FAILED and not self.user_pc and self.fallbacks == 0:
            # the default preconditioner's setup failed (seen rarely with ML on a closed domain's singular L):
            # the same solve with GAMG; a preconditioner the user chose is the user's to change
            self._fall_back()
            self.ksp.setTolerances(rtol=rtol, atol=atol)
            self.ksp.solve(self.b, self.x)
            reason = self.ksp.getConvergedReason()
        if reason < 0:
            raise PressureSolveError(
                f"the pressure solve did not converge (PETSc KSP reason {reason}) after "
                f"{self.ksp.getIterationNumber()} iterations; check the time step and the void fraction"
            )
        self.x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        with self.x.localForm() as loc:
            phi = loc.array.copy()
        return phi, self.ksp.getIterationNumber()

    def residual_sum(self) -> float:
        """Global Σ_i (b − L φ)_i over non-pressure rows: the discrete continuity defect of the last solve."""
        r = self.b.duplicate()
        self._current.mult(self.x, r)
        r.aypx(-1.0, self.b)
        r.array[self.bc_rows] = 0.0
        s = self.comm.allreduce(float(r.array.sum()), op=MPI.SUM)
        r.destroy()
        return s

    def destroy(self) -> None:
        """Free the PETSc objects (collective)."""
        for obj in (self.ksp, self.A, self.b, self.x):
            obj.destroy()
        if self.weighted is not None:
            self.op.destroy()
            self.weighted.xg.destroy()
