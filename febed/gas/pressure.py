"""The pressure-increment Poisson solve: a constant stiffness matrix and its factorisation or AMG, set up once.

(With the drag-weighted projection, the default for steps with a drag, the operator is instead L_w of each
step, `febed.gas.weighted`, solved by CG preconditioned with the AMG of L_w of a recent step.)

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

from febed.gas.weighted import WeightedLaplacian

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
# The drag-weighted solve (CG on L_w) is preconditioned by the AMG of L_w of a recent step, rebuilt after a solve
# that needed more than this many iterations. With the AMG of the current L_w CG needs 4-6 iterations on the
# seed-001 meshes, with the constant L's 9-10; one AMG setup costs about as much as 60 iterations.
REFRESH_ITERATIONS = 8
# The multigrid smoothers of the weighted solve use the assembled L_w (the preconditioner's matrix), not the
# matrix-free operator: otherwise every smoothing sweep applies L_w cell by cell once more.
# ML's default estimate of the spectral radius (power iteration from a random vector) draws on a random stream
# shared by every ML setup of the process, so a preconditioner rebuilt after a restart would differ in the last
# bits; the matrix-norm estimate makes each setup a function of its matrix alone.
# A GAMG preconditioner is refreshed by keeping the interpolation of its last full build and recomputing only its
# coarse operators and smoothers from the current L_w (`pc_gamg_reuse_interpolation`): on 2 ranks 10.5 against
# 68 ms on the seed-001 intermediate mesh, with the same iterations after it; on the fine mesh (C3) a 0.01 s window
# of the bubbling bed took 0.77-0.86 of the wall time (9 refreshes in 80 gas steps either way, 7.96 against 7.94
# iterations per solve; docs/performance.md). A refresh whose first solve still needs more
# than REFRESH_ITERATIONS is followed by a full build. The same interpolation and current L_w give the same
# preconditioner whatever refreshes came between, so a restart rebuilds it from the two weights
# (`restore_preconditioner`).
WEIGHTED_OPTIONS = {
    "pc_use_amat": "false",
    "pc_ml_SpectralNormScheme_Anorm": "true",
    "pc_gamg_reuse_interpolation": "true",
}
REUSE_PC_TYPES = ("gamg",)  # the preconditioners refreshed by reusing their interpolation
# One process, a pressure outlet and at most this many nodes: the weighted solve's preconditioner is the
# Cholesky factorisation of L_w of a recent step instead of its AMG. On seed 000's 2D bed (1,919 nodes) the
# factor is rebuilt less often and the gas of benchmarks/coarse.py's TM l = 2 run takes 14 % less (0.55
# against 0.64 s, medians of 3 rounds back to back); on the 7,000-node coarse pseudo-2D mesh both cost the same.
WEIGHTED_DIRECT_MAX_NODES = 5_000


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


class PressureSolver:
    """Solve L φ = b for the scaled pressure increment φ = Δt δP / ρ, b given on the owned nodes.

    With `weighted` the solver can also solve the drag-weighted Laplacian L_w of the weights last given to
    `set_weights` (`febed.gas.weighted`): CG preconditioned by the AMG of L_w assembled at a recent step.
    """

    def __init__(self, Q, dirichlet_dofs: np.ndarray, has_dirichlet: bool, prefix: str, weighted: bool = False):
        comm = Q.mesh.comm
        v, w = ufl.TestFunction(Q), ufl.TrialFunction(Q)
        bcs = [dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), dirichlet_dofs, Q)] if has_dirichlet else []
        self.Q = Q
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
            and imap.size_global <= DIRECT_MAX_NODES
            and not any(
                _user_set(opts, name)
                for name in opts.getAll()
                if name.startswith(prefix) and not name.startswith(prefix + "weighted_")
            )
        )  # any option of the user's for this solver (a type, a tolerance, ...) asks for the iterative one
        if not direct:
            defaults = DEFAULT_OPTIONS if comm.size == 1 else {**DEFAULT_OPTIONS, **FALLBACK_OPTIONS}
            _write_defaults(opts, prefix, defaults)
        self.ksp = PETSc.KSP().create(comm)
        self.ksp.setOptionsPrefix(prefix)
        self.ksp.setOperators(self.A)
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
        self.ksp.setUp()
        self.setup_count = 1  # the preconditioner's matrix never changes: PETSc reuses this setup in every solve
        self.comm = comm
        self._last = self.ksp  # the solver of the last solve
        self.weighted = None  # the drag-weighted operator and its CG solver (`set_weights`)
        if weighted:
            self._set_up_weighted(dirichlet_dofs)

    def _set_up_weighted(self, dirichlet_dofs: np.ndarray) -> None:
        """CG on L_w of the step, preconditioned by the AMG of L_w of a recent step (`_refresh`)."""
        self.weighted = WeightedLaplacian(self.Q, dirichlet_dofs)
        self._pc_vals = np.zeros_like(self.weighted.vals)
        self.Pw = self.weighted.matrix(self._pc_vals)  # the preconditioner's matrix: L_w of `pc_weights`
        if self.nullspace is not None:
            self.weighted.A.setNullSpace(self.nullspace)
            self.Pw.setNullSpace(self.nullspace)
        self.pc_weights = None  # the nodal weights (owned nodes) the preconditioner was built for
        self._w_local = None  # the nodal weights of the current step (`set_weights`)
        opts = PETSc.Options()
        defaults = DEFAULT_OPTIONS if self.comm.size == 1 else {**DEFAULT_OPTIONS, **FALLBACK_OPTIONS}
        small = self.Q.dofmap.index_map.size_global <= WEIGHTED_DIRECT_MAX_NODES
        if self.comm.size == 1 and self.nullspace is None and small:
            defaults = {**defaults, "pc_type": "cholesky"}
        _write_defaults(opts, self.prefix + "weighted_", {**defaults, **WEIGHTED_OPTIONS})
        self.user_pc_w = _user_set(opts, self.prefix + "weighted_pc_type")
        self.ksp_w = self._weighted_ksp()  # checks the options now; `_refresh` makes a new one for each build
        self.pc_setups = 0  # full preconditioner builds of the weighted solve
        self.reuse_setups = 0  # refreshes that kept the interpolation of the last full build
        self.interp_weights = None  # the nodal weights (owned nodes) of the last full build, if refreshed since
        self.fresh_reuse = False  # the preconditioner was refreshed by reuse and has not been used since

    def _weighted_ksp(self) -> PETSc.KSP:
        """A new CG solver of L_w (options under the prefix ..._weighted_), its preconditioner not yet built."""
        prefix = self.prefix + "weighted_"
        ksp = PETSc.KSP().create(self.comm)
        ksp.setOptionsPrefix(prefix)
        ksp.setOperators(self.weighted.A, self.Pw)
        ksp.setFromOptions()
        ksp.setInitialGuessNonzero(True)
        if not PETSc.Options().hasName(prefix + "ksp_norm_type"):
            ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
        if ksp.getType() == PETSc.KSP.Type.PREONLY:
            raise ValueError(
                f"gas.drag_weighted_projection needs an iterative pressure solver: -{prefix}ksp_type preonly "
                "applies a preconditioner built for an earlier step once; remove it"
            )
        return ksp

    def _refresh(self, reuse: bool = False) -> None:
        """Build the weighted solve's preconditioner from L_w of the current weights, kept for later steps.

        Each full build is a new solver object, so that the preconditioner depends on its matrix alone (an AMG
        set up again in place keeps traces of its earlier setups) and a restart rebuilds it bit for bit. With
        `reuse` the last full build's interpolation is kept and the rest set up again from the current L_w
        (`WEIGHTED_OPTIONS`) (collective).
        """
        self._pc_vals[:] = self.weighted.vals
        self.weighted.load(self.Pw, self._pc_vals)
        weights = self._w_local[: self.Q.dofmap.index_map.size_local].copy()
        if reuse:
            pc = self.ksp_w.getPC()
            pc.setReusePreconditioner(False)
            self.Pw.stateIncrease()  # the new values, whatever the fill did
            pc.setUp()
            pc.setReusePreconditioner(True)
            self.interp_weights = self.interp_weights if self.interp_weights is not None else self.pc_weights
            self.reuse_setups += 1
        else:
            self.ksp_w.destroy()
            self.ksp_w = self._weighted_ksp()
            self.ksp_w.setUp()
            self.ksp_w.getPC().setReusePreconditioner(True)  # kept until the next refresh, however L_w changes
            self.interp_weights = None
            self.pc_setups += 1
        self.fresh_reuse = reuse
        self.pc_weights = weights

    def _reusable(self) -> bool:
        """Whether the weighted solve's preconditioner can be refreshed keeping its interpolation."""
        prefix = self.prefix + "weighted_"
        pc_type = self.ksp_w.getPC().getType()
        return pc_type in REUSE_PC_TYPES and PETSc.Options().getBool(f"{prefix}pc_{pc_type}_reuse_interpolation", False)

    def _iterative_settings(self, opts) -> None:
        """Warm start and true-residual tolerances for an iterative solve (unless the user set the norm)."""
        if self.ksp.getType() != PETSc.KSP.Type.PREONLY:
            self.ksp.setInitialGuessNonzero(True)  # warm start from the previous increment
            if not opts.hasName(self.prefix + "ksp_norm_type"):
                self.ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)  # tolerances on the true residual

    def _fall_back(self, weighted: bool) -> None:
        """Replace a preconditioner whose setup failed by CG + GAMG (`FALLBACK_OPTIONS`), from φ = 0 (collective)."""
        opts = PETSc.Options()
        self.fallbacks += 1
        self.x.set(0.0)
        if weighted:
            fallback = {**DEFAULT_OPTIONS, **FALLBACK_OPTIONS, **WEIGHTED_OPTIONS}
            _write_defaults(opts, self.prefix + "weighted_", fallback)
            self._refresh()
            return
        _write_defaults(opts, self.prefix, {**DEFAULT_OPTIONS, **FALLBACK_OPTIONS})
        failed, self.ksp = self.ksp, PETSc.KSP().create(self.comm)  # a new solver: PETSc keeps the failure
        failed.destroy()
        self.ksp.setOptionsPrefix(self.prefix)
        self.ksp.setOperators(self.A)
        self.ksp.setFromOptions()
        self._iterative_settings(opts)
        self.ksp.setUp()
        self.setup_count += 1

    def set_weights(self, w_local: np.ndarray) -> None:
        """Make the weighted operator L_w for the nodal weights `w_local` (owned and ghost nodes)."""
        self.weighted.set_weights(w_local)
        self._w_local = w_local

    def solve(self, rhs_owned: np.ndarray, rtol: float, atol: float, weighted: bool = False) -> tuple[np.ndarray, int]:
        """Write b (owned rows), zero the pressure rows, solve from the last φ; φ over local dofs, iterations.

        Converged when the true residual ||b − Lφ||_2 ≤ max(rtol ||b||_2, atol); L is the weighted operator
        of the last `set_weights` if `weighted` (collective: the same on every rank).
        """
        if weighted and self.pc_weights is None:
            self._refresh()
        self._last = self.ksp_w if weighted else self.ksp
        self.b.array[:] = rhs_owned
        self.b.array[self.bc_rows] = 0.0
        if self.nullspace is not None:
            self.nullspace.remove(self.b)
        # no divergence test: a warm start far from a tiny right-hand side (a nearly steady step) is not divergence
        self._last.setTolerances(rtol=rtol, atol=atol, divtol=1e300)
        self._last.solve(self.b, self.x)
        reason = self._last.getConvergedReason()
        user_pc = self.user_pc_w if weighted else self.user_pc
        if reason == PETSc.KSP.ConvergedReason.DIVERGED_PCSETUP_FAILED and not user_pc and self.fallbacks == 0:
            # the default preconditioner's setup failed (seen rarely with ML on a closed domain's singular L):
            # the same solve with GAMG; a preconditioner the user chose is the user's to change
            self._fall_back(weighted)
            self._last = self.ksp_w if weighted else self.ksp
            self._last.setTolerances(rtol=rtol, atol=atol, divtol=1e300)
            self._last.solve(self.b, self.x)
            reason = self._last.getConvergedReason()
        if reason < 0:
            raise PressureSolveError(
                f"the pressure solve did not converge (PETSc KSP reason {reason}) after "
                f"{self._last.getIterationNumber()} iterations; check the time step and the void fraction"
            )
        its = self._last.getIterationNumber()
        if weighted:
            fresh, self.fresh_reuse = self.fresh_reuse, False
            if its > REFRESH_ITERATIONS:  # for the next step: the preconditioner of this step's L_w
                self._refresh(reuse=not fresh and self._reusable())  # a reuse that did not help: a full build
        self.x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        with self.x.localForm() as loc:
            phi = loc.array.copy()
        return phi, its

    def restore_preconditioner(self, w_local: np.ndarray, interp_local: np.ndarray | None = None, fresh=False) -> None:
        """Build the weighted solve's preconditioner of a checkpoint (`preconditioner_state`) (collective).

        `w_local`: its nodal weights (owned and ghost nodes); `interp_local`: those of the full build whose
        interpolation it kept, if it was refreshed by reuse, and `fresh` if it has not been used since.
        """
        if interp_local is not None and self._reusable():  # the same on every rank
            self.set_weights(interp_local)
            self._refresh()
            self.set_weights(w_local)
            self._refresh(reuse=True)
            self.fresh_reuse = bool(fresh)
            return
        self.set_weights(w_local)  # (on another solver, e.g. after a restart on one rank: a full build)
        self._refresh()

    def preconditioner_state(self) -> dict[str, np.ndarray]:
        """The weighted solve's preconditioner as owned-node arrays for a checkpoint (empty before it is built).

        `pc_weights`: the weights of its L_w; after a refresh by reuse also `pc_interp_weights`, those of the full
        build whose interpolation it kept, and `pc_fresh` (1 at every node) if it has not been used since.
        """
        if self.weighted is None or self.pc_weights is None:
            return {}
        state = {"pc_weights": self.pc_weights.copy()}
        if self.interp_weights is not None:
            state["pc_interp_weights"] = self.interp_weights.copy()
            if self.fresh_reuse:
                state["pc_fresh"] = np.ones(self.pc_weights.size, dtype=np.int8)
        return state

    def residual_sum(self) -> float:
        """Global Σ_i (b − L φ)_i over non-pressure rows: the discrete continuity defect of the last solve."""
        r = self.b.duplicate()
        self._last.getOperators()[0].mult(self.x, r)
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
            for obj in (self.ksp_w, self.Pw):
                obj.destroy()
            self.weighted.destroy()
