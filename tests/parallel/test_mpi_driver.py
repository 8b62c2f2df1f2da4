"""Pure-DEM mode on several ranks: the same particles as serially, each written once (run under mpirun -n 2).

With the mesh partition and with the default `particle_partition = "auto"` (boxes of equal DEM work in a
pure-DEM run).
"""

import logging
import xml.etree.ElementTree as ET

from mpi4py import MPI

import numpy as np
import pytest

from febed.case import load_case
from febed.io.particles import read_vtp

pytestmark = pytest.mark.mpi

CASE = """
[run]
mode = "dem"
end_time = 0.012
particle_partition = "{partition}"

[mesh]
file = "cylinder.msh"  # built once (gmsh's tetrahedra may differ between two builds in processes with a history)

[gas.boundary.inlet]
type = "inlet"
velocity = 0.0

[gas.boundary.walls]
type = "wall"

[gas.boundary.outlet]
type = "outlet"
particles = false

[particles]
diameter = 0.002
count = 300
region = [-0.02, -0.02, 0.06, 0.02, 0.02, 0.09]  # across the middle of the 0.15 m tall cylinder

[contact]
stiffness = 1e5

[output]
particle_interval = 0.006
directory = "{out}"
"""


@pytest.mark.parametrize("partition", ["mesh", "auto"])
def test_pure_dem_run_on_all_ranks_matches_serial(mpi_tmp_path, partition):
    from febed.bed import build_dem
    from febed.meshing import load_case_mesh
    from febed.runs.dem import run

    comm = MPI.COMM_WORLD
    out = mpi_tmp_path / "out"
    if comm.rank == 0:
        from febed.meshing import build_msh

        build_msh("cylinder", mpi_tmp_path / "cylinder.msh", size=0.008)
        (mpi_tmp_path / "case.toml").write_text(CASE.format(out=out, partition=partition))
    comm.barrier()
    case = load_case(mpi_tmp_path / "case.toml")
    dem = run(case, out, logging.getLogger("test"), comm)
    pvd = ET.parse(out / "particles" / "particles.pvd").getroot()
    files = [e.get("file") for e in pvd.iter("DataSet")]
    assert len(files) == 3
    last = read_vtp(out / "particles" / files[-1])
    gid = last["gid"]
    assert gid.size == 300 and np.unique(gid).size == 300  # every particle once
    assert comm.allreduce(dem.particles.n_owned) == 300
    if partition == "auto" and comm.size > 1:  # the boxes share the cloud out evenly
        assert comm.allreduce(dem.particles.n_owned, op=MPI.MAX) <= 1.1 * 300 / comm.size
    # the serial DEM of the same case on this rank alone
    md = load_case_mesh(case, MPI.COMM_SELF, cache_dir=mpi_tmp_path / f"mesh{comm.rank}")
    ref = build_dem(case, md, logging.getLogger("test"))
    ref.advance(int(round(case.run.end_time / ref.dt)), ref.dt)
    assert ref.dt == dem.dt and ref.steps == dem.steps
    first = read_vtp(out / "particles" / files[0])
    x0 = first["Points"][np.argsort(first["gid"])]
    x = last["Points"][np.argsort(gid)]
    xr = ref.particles.pos[np.argsort(ref.particles.gid)]
    assert np.abs(xr - x0)[:, 2].min() > 0.0005  # every particle fell ...
    assert np.abs(x - xr).max() < 1e-9 * 0.15  # ... along its serial trajectory
