"""Shared pytest fixtures: MPI-safe temporary folders and collective teardown."""

import gc
import logging
import shutil
import sys
import tempfile
from pathlib import Path

from mpi4py import MPI

import pytest


@pytest.fixture
def mpi_tmp_path():
    """A temporary folder shared by all ranks (made on rank 0, broadcast), removed after the test."""
    comm = MPI.COMM_WORLD
    path = tempfile.mkdtemp(prefix="febed-test-") if comm.rank == 0 else None
    path = Path(comm.bcast(path, root=0))
    yield path
    comm.barrier()
    if comm.rank == 0:
        shutil.rmtree(path, ignore_errors=True)


def pytest_collection_modifyitems(config, items):
    """No pytest-timeout limit for the `slow` tests (hours for the longest), unless one sets its own."""
    for item in items:
        if item.get_closest_marker("slow") and not item.get_closest_marker("timeout"):
            item.add_marker(pytest.mark.timeout(0))


def pytest_runtest_logreport(report):
    """Under mpirun, a test that fails stops every rank at once (MPI Abort) with its report.

    A failure on some ranks only would leave the others waiting in their next collective call until the job's
    time limit; the whole run stops instead, naming the test and the rank.
    """
    comm = MPI.COMM_WORLD
    if comm.size > 1 and report.failed:
        sys.stderr.write(
            f"\n{report.nodeid} failed ({report.when}) on rank {comm.rank} of {comm.size}: stopping every rank\n"
            f"{report.longrepr}\n"
        )
        sys.stderr.flush()
        comm.Abort(1)


@pytest.fixture(autouse=True)
def _collective_teardown():
    """PETSc destructors are collective: collect garbage on every rank, then wait for all of them.

    Also undoes `febed.io.rundir.get_logger` (runs through the CLI set up the `febed` logger with its own
    handlers and no propagation), so each test sees log records through pytest's caplog again.

    What survives the collection is then frozen (`gc.freeze`): the next test's collection only looks at the
    objects made since, instead of the whole heap of DOLFINx, PETSc and Numba (0.2 s per test otherwise). A
    frozen object that later becomes cyclic garbage is never collected, so never destroyed out of step.
    """
    yield
    reset_febed_logger()
    gc.collect()
    gc.freeze()
    MPI.COMM_WORLD.barrier()


def reset_febed_logger():
    """Give the `febed` logger back to pytest: no handlers of its own, records propagated to caplog."""
    log = logging.getLogger("febed")
    for h in list(log.handlers):
        log.removeHandler(h)
        h.close()
    log.propagate = True


@pytest.fixture(scope="session")
def seed_meshes(tmp_path_factory):
    """Built-in meshes (.msh) built once per session on rank 0: name -> path."""
    from febed.meshing import build_msh

    comm = MPI.COMM_WORLD
    specs = {
        "pseudo2d-coarse": dict(name="pseudo2d", level="coarse"),
        "pseudo2d-intermediate": dict(name="pseudo2d", level="intermediate"),
        "pseudo2d-tet": dict(name="pseudo2d", cell="tetrahedron", size=0.01),
        "wang2d": dict(name="wang2d"),
        "wang2d-tri": dict(name="wang2d", cell="triangle"),
        "cylinder": dict(name="cylinder", size=0.008),
    }
    root = Path(comm.bcast(str(tmp_path_factory.mktemp("meshes")) if comm.rank == 0 else None, root=0))
    paths = {k: root / f"{k}.msh" for k in specs}
    if comm.rank == 0:
        for k, spec in specs.items():
            build_msh(out=paths[k], **spec)
    comm.barrier()
    return paths
