"""Seed 001 C1 (slow): a run of the pseudo-2D bed circulates solid up the centre, down the walls.

C1 as Table 3 gives it (the gas walls with febed's default porous wall law, `C1.toml`, a 20 s run averaged over
1-5 s, its start-up, and over 15-20 s, its steady regime), and variants that keep the bottom patch strictly
no-slip: the front and back walls slipping (`C1-slip-front-back.toml`), with Navier partial slip there
(`C1-partial-slip-front-back.toml`), or on every wall with the inlet taking the patch's edge nodes
(`C1-partial-slip-edges.toml`).

`FEBED_C1_END` sets the simulated time of the variants (default 3 s; the last 2/3 are averaged). On a 2-core
machine the 75 g bed (57,296 particles) runs at 7-10 min per simulated second serially (C1's 20 s: about
2.5 hours): this is a `make test-all` test.
"""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from febed.post import post_run

DEMO = Path(__file__).parents[2] / "demos" / "pseudo2d"


# seed 001 runs every case 20 s "to reach a steady regime" before averaging; so does C1 here. Its loops start
# the other way and turn seed 001's way at a time that is chance (2-14 s in six runs, docs/examples/pseudo2d.md):
# the steady regime is checked over the last 5 s, and no circulation is asserted over the start-up
C1_END = 20.0
STEADY = (15.0, C1_END)


def _run_only(tmp_path_factory, case: str, end: float) -> Path:
    """The output folder of a run of `case` for `end` seconds."""
    out = tmp_path_factory.mktemp("pseudo2d") / case
    cmd = [sys.executable, "-m", "febed.cli", "run", str(DEMO / f"{case}.toml")]
    cmd += ["--set", f"run.end_time={end}", "--set", f"output.directory={out}"]
    subprocess.run(cmd, check=True, capture_output=True)
    return out


def _run(tmp_path_factory, case: str, end: float | None = None):
    """A run of `case` for `end` (default FEBED_C1_END) seconds, post-processed over its last 4/5 or 2/3."""
    end = float(os.environ.get("FEBED_C1_END", "3.0")) if end is None else end
    out = _run_only(tmp_path_factory, case, end)
    return post_run(out, window=(end / (5 if end >= 5 else 3), end), figures=False)


@pytest.fixture(scope="module")
def c1_run(tmp_path_factory):
    return _run_only(tmp_path_factory, "C1", C1_END)


@pytest.fixture(scope="module")
def c1(c1_run):
    """C1 over 1-5 s: its start-up, from the first bubbles on."""
    return post_run(c1_run, window=(1.0, 5.0), figures=False)


@pytest.fixture(scope="module")
def c1_steady(c1_run):
    """C1 over 15-20 s: its steady regime."""
    return post_run(c1_run, window=STEADY, figures=False, out=c1_run / "post-steady")


@pytest.fixture(scope="module")
def c1_slip_front_back(tmp_path_factory):
    return _run(tmp_path_factory, "C1-slip-front-back")


@pytest.mark.slow
def test_c1_pressure_drop_carries_the_bed(c1):
    """C1 as given, over 1-5 s (measured with either pressure-gradient reaction: dp 0.957-0.961 W, the bottom's
    contacts 0.058-0.059 W)."""
    avg, v = c1.fields, c1.values
    # the gas carries the bed: time-averaged pressure drop within 5 % of the bed weight per cross-section
    assert abs(v["dp_bed_over_weight"] - 1.0) < 0.05, v["dp_bed_over_weight"]
    # with the wall law the gas's wall shear is the Brinkman layer's: little surplus force
    surplus = v["dp_bed_over_weight"] + v["bottom_support/W"] - 1.0
    assert abs(surplus) < 0.03, (v["dp_bed_over_weight"], v["bottom_support/W"])
    # and the deposited volume is the bed's
    assert np.isclose(avg.alpha_p.sum() * avg.grid.bin_volume, avg.solid_volume, rtol=1e-10)


@pytest.mark.slow
def test_c1_bubbles_and_is_two_dimensional(c1):
    """With the wall law the coarse bed bubbles (measured over 1-5 s: 0.252-0.256; strict no-slip walls: 0.03)."""
    v = c1.values
    assert v["bubble_fraction"] > 0.1, v["bubble_fraction"]
    assert v["depth_zH0.16_spread_all/Uf"] < 0.03, v["depth_zH0.16_spread_all/Uf"]


@pytest.mark.slow
def test_c1_after_its_start_up_circulates_up_the_centre_down_the_walls(c1_steady):
    """C1 as given, over 15-20 s: seed 001's double loop with the gas carrying the bed (measured with the current
    defaults: +54 / -63 rho U_f, dp 0.965 W, bottom 0.049 W; in the run whose loops turned last, at 14 s, with
    the pressure's share lagged: +49.5 / -68.4, 0.961 W, 0.055 W)."""
    v = c1_steady.values
    centre, walls = v["bed_flux_centre/rhoUf"], v["bed_flux_walls/rhoUf"]
    assert centre > 20.0 and walls < -20.0, (centre, walls)
    assert abs(v["dp_bed_over_weight"] - 1.0) < 0.05, v["dp_bed_over_weight"]
    surplus = v["dp_bed_over_weight"] + v["bottom_support/W"] - 1.0
    assert abs(surplus) < 0.03, (v["dp_bed_over_weight"], v["bottom_support/W"])


@pytest.mark.slow
def test_c1_with_slipping_front_and_back_walls_circulates_seed_001s_way(c1_slip_front_back):
    """The gas slips along the front and back walls (side walls with the wall law): the bed bubbles and the double
    loop turns up the centre, down the side walls (measured over 1-3 s: +45 / -65 rho U_f, bubble fraction 0.30;
    with the projected reaction over 1.0-2.5 s: +53 / -75, 0.29)."""
    v = c1_slip_front_back.values
    centre, walls = v["bed_flux_centre/rhoUf"], v["bed_flux_walls/rhoUf"]
    assert centre > 0.0 > walls, (centre, walls)
    assert v["bubble_fraction"] > 0.1, v["bubble_fraction"]


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="with the front and back walls slipping the gas carries 0.924 of the bed weight over 1-3 s (0.905 with "
    "the projected reaction): the bottom holds 0.104 by contact, a heap on the coarse mesh's patch (17.6 % of "
    "the bottom); docs/examples/pseudo2d.md",
)
def test_c1_with_slipping_front_and_back_walls_pressure_drop(c1_slip_front_back):
    assert abs(c1_slip_front_back.values["dp_bed_over_weight"] - 1.0) < 0.05


@pytest.mark.slow
def test_c1_with_slipping_front_and_back_walls_force_balance(c1_slip_front_back):
    """Without gas shear on the front and back walls, the pressure drop and the bottom's contacts carry the weight
    but for the side walls' shear (measured over 1-3 s: 0.924 + 0.104 = 1.028; with the projected reaction
    0.912 + 0.099 = 1.011; about 20 min)."""
    v = c1_slip_front_back.values
    held = v["dp_bed_over_weight"] + v["bottom_support/W"]
    assert abs(held - 1.0) < 0.03, (v["dp_bed_over_weight"], v["bottom_support/W"])
    assert v["bottom_support/W"] > 0.05  # the heap on the patch


@pytest.mark.slow
def test_c1_with_slipping_front_and_back_walls_is_two_dimensional(c1_slip_front_back):
    """Seed 001's depth averaging assumes a bed that hardly varies across the depth (its Fig 11, for C2): with
    the front and back walls slipping C1 is such a bed (measured over 1.0-2.5 s: U_p,z spread 0.001 U_f over
    the width, 0.007 U_f at the side walls, solid asymmetry 0.000), where C1 with no-slip walls circulates
    across the depth (0.099 and 0.227 U_f) or, at converged gas steps, splits (asymmetry 0.36-0.40)."""
    v = c1_slip_front_back.values
    assert v["depth_zH0.16_spread_all/Uf"] < 0.03, v["depth_zH0.16_spread_all/Uf"]
    assert v["depth_zH0.16_spread_walls/Uf"] < 0.05, v["depth_zH0.16_spread_walls/Uf"]
    assert abs(v["depth_zH0.16_front_back_asymmetry"]) < 0.05, v["depth_zH0.16_front_back_asymmetry"]


@pytest.fixture(scope="module")
def c1_partial_slip_front_back(tmp_path_factory):
    return _run(tmp_path_factory, "C1-partial-slip-front-back")


@pytest.mark.slow
def test_c1_with_partial_slip_front_and_back_walls_circulates_seed_001s_way(c1_partial_slip_front_back):
    """Navier partial slip (slip length 1 mm) on the front and back walls, side walls no-slip: the
    bed bubbles, stays two-dimensional and turns seed 001's way, and the walls' shear carries part of the
    weight that free slip leaves to the pressure drop alone (measured over 1-3 s: +27 / -57 rho U_f, bubble
    fraction 0.32, spreads 0.004 / 0.003 U_f, dp 0.919 W + bottom 0.101 W = 1.020; with the projected reaction
    +53 / -67, 0.248, 0.932 W + 0.092 W = 1.024)."""
    v = c1_partial_slip_front_back.values
    centre, walls = v["bed_flux_centre/rhoUf"], v["bed_flux_walls/rhoUf"]
    assert centre > 0.0 > walls, (centre, walls)
    assert v["bubble_fraction"] > 0.1, v["bubble_fraction"]
    assert v["depth_zH0.16_spread_all/Uf"] < 0.03, v["depth_zH0.16_spread_all/Uf"]
    held = v["dp_bed_over_weight"] + v["bottom_support/W"]
    assert 0.99 <= held < 1.06, (v["dp_bed_over_weight"], v["bottom_support/W"])  # + the walls' shear


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="with partial slip (1 mm) on the front and back walls the gas carries 0.919 of the bed weight over "
    "1-3 s (0.932 with the projected reaction): the bottom still holds 0.101 by contact, the heap on the coarse "
    "patch; "
    "docs/examples/pseudo2d.md",
)
def test_c1_with_partial_slip_front_and_back_walls_pressure_drop(c1_partial_slip_front_back):
    assert abs(c1_partial_slip_front_back.values["dp_bed_over_weight"] - 1.0) < 0.05


@pytest.fixture(scope="module")
def c1_partial_slip_edges(tmp_path_factory):
    return _run(tmp_path_factory, "C1-partial-slip-edges")


@pytest.mark.slow
def test_c1_with_every_wall_partial_slip_and_the_inlet_over_the_patch_edges(c1_partial_slip_edges):
    """Every wall partial slip (1 mm) and the inlet taking the patch's edge nodes (`wins_over`), with the
    projected pressure-gradient reaction the case file keeps:
    the heap on the bottom halves and, over 1-3 s, the bed circulates seed 001's way with the pressure drop
    within 5 % of its weight (measured: +23 / -36 rho U_f, dp 0.956 W + bottom 0.048 W = 1.004). Narrowly:
    its first 1.5 s circulate the other way, and over 1.5-3 s dp is 0.942 W; continued to 5 s, 0.951-0.954 W over
    2-5, 3-5 and 1-5 s (docs/examples/pseudo2d.md). This test takes about 30 min."""
    v = c1_partial_slip_edges.values
    centre, walls = v["bed_flux_centre/rhoUf"], v["bed_flux_walls/rhoUf"]
    assert centre > 0.0 > walls, (centre, walls)
    assert abs(v["dp_bed_over_weight"] - 1.0) < 0.05, v["dp_bed_over_weight"]
    assert v["bottom_support/W"] < 0.07, v["bottom_support/W"]  # the front/back-slip variants: 0.08-0.11
    held = v["dp_bed_over_weight"] + v["bottom_support/W"]
    assert 0.98 <= held < 1.04, (v["dp_bed_over_weight"], v["bottom_support/W"])
    assert v["bubble_fraction"] > 0.1 and v["depth_zH0.16_spread_all/Uf"] < 0.03
