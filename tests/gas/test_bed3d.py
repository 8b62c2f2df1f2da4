"""Seed 001's pseudo-2D bed (coarse, hexahedra and tetrahedra): inlet with the bottom-wall patch, bed-like ε."""

from mpi4py import MPI

import numpy as np
import pytest

from febed.gas import BoundarySpec, VANSParameters, VANSSolver
from febed.meshing import build_msh, load_msh


@pytest.mark.mpi
@pytest.mark.parametrize("cell", ["hexahedron", "tetrahedron"])
def test_pseudo2d_bed_inflow_and_balance(mpi_tmp_path, cell):
    comm = MPI.COMM_WORLD
    path = mpi_tmp_path / f"p2d-{cell}.msh"
    if comm.rank == 0:
        build_msh("pseudo2d", out=path, level="coarse", cell=cell, size=0.008)
    comm.barrier()
    md = load_msh(path, comm)
    bcs = {
        "inlet": BoundarySpec("inlet", velocity=1.2, ramp_time=0.002, cross_section_tags=("bottom_wall",)),
        "bottom_wall": BoundarySpec("wall"),
        "walls": BoundarySpec("wall"),
        "outlet": BoundarySpec("outlet"),
    }
    s = VANSSolver(md, VANSParameters(gravity=9.81, boundaries=bcs, les="smagorinsky"))
    z = s.x[:, 2]

    def eps_at(t):
        return 0.42 + 0.58 / (1 + np.exp(-(z - 0.1 - 0.2 * t) / 0.005))

    s.set_void_fraction(eps_at(0.0))
    K = 3000.0 * (1 - s.eps)
    worst = 0.0
    for _ in range(40):
        dt = s.compute_dt()
        info = s.step(dt, eps=eps_at(s.t + dt), K=K)
        worst = max(worst, abs(info.mass_imbalance) / (1.2 * info.inflow))
    area = 0.08 * 0.015  # U_f is superficial over the whole cross-section, patch included
    assert info.inflow == pytest.approx(1.2 * area, rel=1e-10)
    assert worst < 1e-6
    assert info.storage_rate < 0.0  # the dense region rises: the gas volume in the column falls
    umax = comm.allreduce(float(np.abs(s.u[: s.n_owned]).max()), op=MPI.MAX)
    assert np.isfinite(umax) and umax < 20.0
