"""The pre-flight estimate's gas step (`febed.preflight`): a fluidized bed's gas speed sets its CFL limit.

A box of 2 mm cells with 1 mm glass beads (U_mf = 0.54 m/s by Wen and Yu): at U_f = 1.2 m/s the bed is
fluidized and the estimate's gas step is the CFL limit at BED_GAS_SPEED U_f; at 0.3 m/s (a fixed bed) and
without particles it is the CFL limit at U_f or dt_max, whichever is smaller. With convective sub-steps the
gas step spans as many CFL steps as dt_max allows, up to k, and each extra sub-step costs a predictor. With
the particles shared by work a coupled run holds the whole mesh's coupling arrays on every rank.
"""

from __future__ import annotations

import pytest

from febed.case import load_case
from febed.coarse.pcpm import u_mf_wen_yu
from febed.preflight import (
    BED_GAS_SPEED,
    DEM_SECONDS,
    GAS_SECONDS,
    NODE_BYTES,
    PARTICLE_BYTES,
    PREDICTOR_SHARE,
    RANK_BYTES,
    WHOLE_MESH_BYTES,
    preflight,
)

CASE = """
[run]
mode = "{mode}"
end_time = 0.1

[mesh]
builtin = "box"
extent = [0.02, 0.06]
size = 0.002
cell = "quadrilateral"

[gas]
dt_max = 2e-4
cfl = 0.2
convection_substeps = {k}

[gas.boundary.inlet]
type = "inlet"
velocity = {velocity}
[gas.boundary.walls]
type = "wall"
[gas.boundary.outlet]
type = "outlet"

[particles]
diameter = 1e-3
density = 2500.0
count = {count}
insertion = "lattice"

[contact]
stiffness = 800.0
"""


def case(tmp_path, velocity, count=300, mode="cfd-dem", k=1):
    path = tmp_path / f"case-{mode}-{velocity}-{k}.toml"
    path.write_text(CASE.format(mode=mode, velocity=velocity, count=count, k=k))
    return load_case(path)


def estimate(tmp_path, velocity, count=300, mode="cfd-dem", k=1):
    return preflight(case(tmp_path, velocity, count, mode, k)).estimate


def test_a_fluidized_bed_takes_its_gas_step_at_the_bed_gas_speed(tmp_path):
    c = case(tmp_path, 1.2)
    u_mf = u_mf_wen_yu(1e-3, 2500.0, c.gas.density, c.gas.viscosity, c.run.gravity)
    assert 0.5 < u_mf < 0.6
    h = 0.002  # the mean cell size of the box
    bed = estimate(tmp_path, 1.2)
    assert bed.bed_cfl and bed.dt_gas == pytest.approx(0.2 * h / (BED_GAS_SPEED * 1.2), rel=1e-12)
    assert "CFL at a fluidized bed's gas speed" in bed.text()
    fixed = estimate(tmp_path, 0.3)  # below U_mf: the CFL step at U_f (3.3e-4 s) is above dt_max
    assert not fixed.bed_cfl and fixed.dt_gas == pytest.approx(2e-4, rel=1e-12)
    gas = estimate(tmp_path, 1.2, count=0, mode="gas")
    assert not gas.bed_cfl and gas.dt_gas == pytest.approx(2e-4, rel=1e-12)


def test_convective_substeps_lengthen_the_gas_step_up_to_dt_max_and_cost_predictors(tmp_path):
    # the bed's CFL step is 0.2 h / (5 x 1.2 m/s) = 6.7e-5 s: k = 4 would span 2.7e-4 s, so dt_max = 2e-4 s
    # holds the step to 3 sub-steps; without particles the CFL step at U_f (3.3e-4 s) is above dt_max: one
    h = 0.002
    single = 0.2 * h / (BED_GAS_SPEED * 1.2)
    one, four = estimate(tmp_path, 1.2), estimate(tmp_path, 1.2, k=4)
    assert one.convective == 1 and one.dt_gas == pytest.approx(single, rel=1e-12)
    assert four.convective == 3 and four.dt_gas == pytest.approx(2e-4, rel=1e-12)
    assert "3 convective sub-steps per gas step" in four.text()
    for est, subs in ((one, 1), (four, 3)):
        gas = est.wall - est.particles * est.dem_steps * DEM_SECONDS / est.ranks
        expected = est.nodes * (0.1 / est.dt_gas) * GAS_SECONDS * (1 + PREDICTOR_SHARE * (subs - 1)) / est.ranks
        assert gas == pytest.approx(expected, rel=1e-9)
    gas_only = estimate(tmp_path, 1.2, count=0, mode="gas", k=4)
    assert gas_only.convective == 1 and gas_only.dt_gas == pytest.approx(2e-4, rel=1e-12)


@pytest.mark.mpi
def test_particles_by_work_count_the_whole_mesh_on_every_rank(mpi_tmp_path):
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    text = CASE.format(mode="cfd-dem", velocity=1.2, count=300, k=1)
    paths = {p: mpi_tmp_path / f"by-{p}.toml" for p in ("mesh", "work")}
    if comm.rank == 0:  # one writer: the folder is every rank's
        for p, path in paths.items():
            path.write_text(text.replace("[run]\n", f'[run]\nparticle_partition = "{p}"\n', 1))
    comm.barrier()
    by_mesh, by_work = (preflight(load_case(paths[p])).estimate for p in ("mesh", "work"))
    per_rank = comm.size * RANK_BYTES
    assert by_mesh.memory == pytest.approx(per_rank + by_mesh.particles * PARTICLE_BYTES + by_mesh.nodes * NODE_BYTES)
    whole = by_work.nodes * WHOLE_MESH_BYTES * comm.size if comm.size > 1 else 0.0  # one rank: no second copy
    assert by_work.nodes == by_mesh.nodes == 341  # 10 x 30 cells of the box
    assert by_work.memory - by_mesh.memory == pytest.approx(whole, rel=1e-12, abs=1e-6)
