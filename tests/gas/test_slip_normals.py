"""Walls that slip only on the facets normal to given axes (`BoundarySpec.slip_normals`).

A 3D box whose `walls` tag covers x = 0, lx and y = 0, ly: with slip_normals = ("y",) the y-walls (a
pseudo-2D bed's front and back) slip and the x-walls (its sides) are no-slip, edges included.
"""

from mpi4py import MPI

import numpy as np
import pytest

from febed.gas import BoundarySpec, VANSParameters, VANSSolver
from febed.meshing import build_msh, load_msh

LX, LY, LZ = 0.04, 0.015, 0.06


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    comm = MPI.COMM_WORLD
    path = None
    if comm.rank == 0:
        path = tmp_path_factory.mktemp("slipn") / "box.msh"
        build_msh("box", out=path, size=0.005, extent=(LX, LY, LZ))
    return load_msh(comm.bcast(path, root=0), comm)


def _solver(md, walls: BoundarySpec) -> VANSSolver:
    bcs = {"inlet": BoundarySpec("inlet", velocity=1.0), "walls": walls, "outlet": BoundarySpec("outlet")}
    s = VANSSolver(md, VANSParameters(gravity=9.81, boundaries=bcs))
    s.set_void_fraction(0.6)
    for _ in range(20):
        s.step(2e-4, K=1000.0)
    return s


@pytest.mark.mpi
def test_front_back_slip_side_walls_no_slip(box):
    comm = MPI.COMM_WORLD
    s = _solver(box, BoundarySpec("wall", slip=True, slip_normals=("y",)))
    n = s.n_owned
    x, y, z = s.x[:n].T
    q = s.q[:n]
    on_x = np.isclose(x, 0.0) | np.isclose(x, LX)
    on_y = (np.isclose(y, 0.0) | np.isclose(y, LY)) & ~on_x
    mid_height = (z > 0.2 * LZ) & (z < 0.8 * LZ)

    def gmax(a):
        return comm.allreduce(float(np.abs(a).max()) if a.size else 0.0, op=MPI.MAX)

    def gmean(a):
        return comm.allreduce(float(a.sum()), op=MPI.SUM) / max(comm.allreduce(a.size, op=MPI.SUM), 1)

    assert gmax(q[on_x]) == 0.0  # side walls and their edges with the front/back walls: no-slip
    assert gmax(q[on_y, 1]) < 1e-14  # front/back: no normal velocity
    # ... but the gas flows along them: the vertical velocity there is that of the interior
    interior = ~on_x & ~on_y & mid_height
    assert gmean(q[on_y & mid_height, 2]) > 0.5 * gmean(q[interior, 2]) > 0.0
    # all walls strictly no-slip: the same nodes hold no gas
    s0 = _solver(box, BoundarySpec("wall", wall_law="no_slip"))
    assert gmax(s0.q[:n][on_y]) == 0.0


@pytest.mark.mpi
def test_slip_normals_all_axes_is_plain_slip(box):
    """Listing every axis is the plain slip wall: the same fields (to the pressure solver's tolerance)."""
    comm = MPI.COMM_WORLD
    a = _solver(box, BoundarySpec("wall", slip=True, slip_normals=("x", "y", "z")))
    b = _solver(box, BoundarySpec("wall", slip=True))
    diff = comm.allreduce(float(np.abs(a.q[: a.n_owned] - b.q[: b.n_owned]).max()), op=MPI.MAX)
    scale = comm.allreduce(float(np.abs(b.q[: b.n_owned]).max()), op=MPI.MAX)
    assert diff <= 1e-7 * scale  # two fresh solvers of the same walls differ by ~4e-9 (iterative solves)


def test_bad_slip_normals_are_refused():
    with pytest.raises(ValueError, match=r"slip_normals \['w'\] are not axes"):
        BoundarySpec("wall", slip=True, slip_normals=("w",)).validate("walls")
    with pytest.raises(ValueError, match="slip_normals needs type = 'wall' with slip = true"):
        BoundarySpec("wall", slip_normals=("y",)).validate("walls")
