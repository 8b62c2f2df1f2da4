"""Coarse-graining and one-way runs from case files: what is inserted, checks, a coupled PCPM run."""

import json
import math
import re
import sys
import types

import numpy as np
import pytest

from febed.case import CaseError, _merge, load_case
from febed.cli import main
from febed.coarse.setup import parcels, particle_depth
from febed.io.probes import read_probes


def case(**sections):
    base = {
        "run": {"mode": "cfd-dem"},
        "mesh": {"builtin": "box", "extent": [0.02, 0.04], "size": 0.004, "cell": "quadrilateral"},
        "gas": {
            "boundary": {
                "inlet": {"type": "inlet", "velocity": 0.5},
                "walls": {"type": "wall"},
                "outlet": {"type": "outlet"},
            }
        },  # fmt: skip
        "particles": {"diameter": 1e-3, "density": 1000.0, "count": 800},
        "contact": {"model": "linear", "stiffness": 200.0},
    }
    return load_case(data=_merge(base, sections))


@pytest.mark.parametrize(
    "model, dim, expect",
    [
        ("none", 3, (1e-3, 1000.0, 800, 1)),
        ("tm", 3, (2e-3, 1000.0, 100, 8)),
        ("tm", 2, (2e-3, 1000.0, 200, 8)),  # a layer one parcel thick: N / l^2 parcels keep the bed's height
        ("pcpm", 2, (2e-3, 1000.0, 200, 8)),
        ("scg", 3, (2e-3, 250.0, 100, 1)),  # seed 003 eq 7: rho d^2 constant
    ],
)
def test_what_each_model_inserts(model, dim, expect):
    spec = parcels(case(coarse_grain={"model": model, "ratio": 2.0}), 800, dim)
    assert (spec.diameter, spec.density, spec.count, spec.n_orig) == pytest.approx(expect)


def test_2d_depth_is_one_inserted_particle_and_bed_weight_per_area_is_kept():
    plain, tm = case(), case(coarse_grain={"model": "tm", "ratio": 3.0})
    assert particle_depth(plain) == 1e-3 and particle_depth(tm) == pytest.approx(3e-3)
    mass = lambda c: (lambda s: s.count * s.n_orig * c.particles.density * math.pi / 6 * 1e-9)(parcels(c, 800, 2))  # noqa: E731
    # weight per unit area of the 2D layer: total mass / depth is the same for plain and TM
    assert mass(tm) / particle_depth(tm) == pytest.approx(mass(plain) / particle_depth(plain), rel=0.02)


def test_bad_coarse_grain_settings_are_named():
    with pytest.raises(CaseError, match=r"ratio = 1.5: a parcel stands for l\^3 whole originals"):
        case(coarse_grain={"model": "tm", "ratio": 1.5})
    with pytest.raises(CaseError, match=r"pcpm.*set \[contact\] model = 'linear'"):
        case(coarse_grain={"model": "pcpm", "ratio": 2.0}, contact={"model": "linear-history"})


@pytest.mark.mpi
def test_coupled_pcpm_run_conserves_originals(mpi_tmp_path):
    from mpi4py import MPI

    tmp_path = mpi_tmp_path
    toml = tmp_path / "pcpm.toml"
    text = """
[run]
end_time = 0.03
[mesh]
builtin = "box"
extent = [0.02, 0.04]
size = 0.004
cell = "quadrilateral"
[gas.boundary.inlet]
type = "inlet"
velocity = 0.6
[gas.boundary.walls]
type = "wall"
[gas.boundary.outlet]
type = "outlet"
[particles]
diameter = 1e-3
density = 1000.0
count = 400
insertion = "lattice"
region = [0.0, 0.0, -inf, 0.02, 0.04, inf]
[contact]
model = "linear"
stiffness = 200.0
[coarse_grain]
model = "pcpm"
ratio = 2.0
[output]
probe_interval = 2e-3
"""
    if MPI.COMM_WORLD.rank == 0:
        toml.write_text(text)
    MPI.COMM_WORLD.Barrier()
    assert main(["run", str(toml), "--set", f"output.directory={tmp_path / 'out'}"]) == 0
    p = read_probes(tmp_path / "out" / "probes.csv")
    assert p["groups"][0] == 100 and set(p["originals"]) == {800.0}  # 100 groups of 8 originals, kept
    assert all(math.isfinite(e) for e in p["event_energy"])


def test_one_way_uniform_flow_relaxes_as_stokes(tmp_path):
    """A Stokes particle released at rest in a uniform gas: v(t) = U (1 - exp(-t / tau)), tau = rho d^2 / 18 mu."""
    toml = tmp_path / "oneway.toml"
    toml.write_text(
        """
[run]
mode = "one-way"
end_time = 0.02
gravity = 0.0
[mesh]
builtin = "box"
extent = [0.02, 0.02, 0.02]
size = 0.005
[gas]
density = 1.2
viscosity = 1.8e-5
[particles]
diameter = 5e-5
density = 2500.0
count = 1
region = [0.002, 0.009, 0.009, 0.004, 0.011, 0.011]
[contact]
stiffness = 1e-4  # a lone particle: soft contacts keep the DEM step (T_C / 6) long
[coupling]
drag = "stokes"
[prescribed_gas]
flow = "uniform"
velocity = [0.1, 0.0, 0.0]
output_interval = 0.002
"""
    )
    out = tmp_path / "out"
    assert main(["run", str(toml), "--set", f"output.directory={out}", "--set", "output.progress_interval=1e-9"]) == 0
    data = np.loadtxt(out / "particles.csv", delimiter=",", skiprows=1, ndmin=2)
    t, vx = data[:, 0], data[:, 5]
    tau = 2500.0 * 5e-5**2 / (18 * 1.8e-5)
    assert t[-1] == pytest.approx(0.02, rel=1e-6) and t.size >= 10
    np.testing.assert_allclose(vx, 0.1 * (1 - np.exp(-t / tau)), rtol=1e-6, atol=1e-9)
    assert json.loads((out / "status.json").read_text())["state"] == "finished"
    log = (out / "febed.log").read_text()
    assert re.search(
        r"t = 0.02 / 0.02 s  \d+ drag windows  1 particles  0 removed  .* min wall per simulated s  ETA", log
    )
    # a gas velocity that turns into NaN stops the run with the particle and time named, status failed
    mod = types.ModuleType("febed_test_nan_flow")
    mod.flow = lambda x, t: np.full(x.shape, np.nan if t > 0.01 else 0.1)
    sys.modules["febed_test_nan_flow"] = mod
    flow = ["--set", "prescribed_gas.flow=function", "--set", "prescribed_gas.function=febed_test_nan_flow:flow"]
    assert main(["run", str(toml), "--set", f"output.directory={out}", "--overwrite", *flow]) == 3
    status = json.loads((out / "status.json").read_text())
    assert status["state"] == "failed"
    # found by the run's check at an output or by the DEM at its next pair-list rebuild, whichever comes first
    assert re.search(r"particle 0 (at \[nan nan nan\] m )?has a non-finite position", status["message"])
    rows = np.loadtxt(out / "particles.csv", delimiter=",", skiprows=1, ndmin=2)
    assert rows[-1, 0] == pytest.approx(0.01, abs=2.1e-3) and np.isfinite(rows).all()  # the rows up to the failure
