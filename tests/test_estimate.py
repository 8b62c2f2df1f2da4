"""The pre-flight estimate's gas step (`febed.preflight`): a fluidized bed's gas speed sets its CFL limit.

A box of 2 mm cells with 1 mm glass beads (U_mf = 0.54 m/s by Wen and Yu): at U_f = 1.2 m/s the bed is
fluidized and the estimate's gas step is the CFL limit at BED_GAS_SPEED U_f; at 0.3 m/s (a fixed bed) and
without particles it is the CFL limit at U_f or dt_max, whichever is smaller.
"""

from __future__ import annotations

import pytest

from febed.case import load_case
from febed.coarse.pcpm import u_mf_wen_yu
from febed.preflight import BED_GAS_SPEED, preflight

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


def case(tmp_path, velocity, count=300, mode="cfd-dem"):
    path = tmp_path / f"case-{mode}-{velocity}.toml"
    path.write_text(CASE.format(mode=mode, velocity=velocity, count=count))
    return load_case(path)


def estimate(tmp_path, velocity, count=300, mode="cfd-dem"):
    return preflight(case(tmp_path, velocity, count, mode)).estimate


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
