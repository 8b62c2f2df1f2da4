"""febed: CFD-DEM for gas-solid fluidized beds.

The gas is a volume-averaged Navier-Stokes solver in DOLFINx, the particles a Numba DEM, the coupling
node-based as in YALES2 (Hamidouche et al. 2019, "seed 001"), with the coarse-graining models of Wang et
al. (2020, "seed 000") and Kushimoto et al. (2021, "seed 003"). The equations and their sources are in
docs/theory.md; the README and each module's docstring describe the layout.

The Python API (`import febed`; a whole script is in demos/api/run_api.py)::

    load_case(path=None, overrides=None, data=None)   a validated `Case` from a TOML file and/or a dict
    Case, CaseError                                   the case (`case.gas.density`, ...) and its input error
    prepare_output(case, overwrite=False)             create (lock) the case's output folder; returns it
    get_logger(outdir=None)                           the `febed` logger (console, and `outdir/febed.log`)
    CoupledRun(case, outdir, log)                     mesh + coupled solver + probe, field and particle
                                                      writers; `.solver`, `.output()`, `.checkpoint()`,
                                                      `.advance_to(t)`, `.close()`
    CoupledSolver                                     the coupled time loop: `.step()` one gas step,
                                                      `.check()` health checks, `.t`, `.gas`, `.dem`
    build_solver(case, md, log)                       a `CoupledSolver` on a mesh from `load_case_mesh`
    load_case_mesh(case)                              the case's mesh (built-in or from its .msh file)
    run_coupled(case, outdir, log)                    what `febed run` does for a coupled case: to the end
    RunFailure                                        raised by `.check()` when the run cannot go on
    read_probes(path)                                 `probes.csv` as {column: list of values}

These names are imported on first use, so `import febed` itself loads no DOLFINx, PETSc or Numba.
"""

from importlib import import_module

from febed.kernel_cache import configure as _configure_kernel_cache

__version__ = "0.1.0"
_configure_kernel_cache()  # before any kernel is defined: a Numba cache keyed on the kernels' sources

_API = {
    "load_case": "febed.case",
    "Case": "febed.case",
    "CaseError": "febed.case",
    "prepare_output": "febed.io.rundir",
    "get_logger": "febed.io.rundir",
    "CoupledRun": "febed.runs.coupled",
    "run_coupled": "febed.runs.coupled",
    "CoupledSolver": "febed.solver",
    "build_solver": "febed.solver",
    "RunFailure": "febed.solver",
    "load_case_mesh": "febed.meshing",
    "read_probes": "febed.io.probes",
}
__all__ = ["__version__", *_API]


def __getattr__(name: str):
    """Import a public API name from its module on first use (PEP 562)."""
    if name in _API:
        value = getattr(import_module(_API[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'febed' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_API})
