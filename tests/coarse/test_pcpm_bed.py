"""The PCPM 2D bed of seed 000 (`demos/wang2d/coarse/pcpm2.toml`: 1,020 groups of 8 originals, 0.9 m/s)
runs 1 s stably on 1 and 2 ranks, on 2 with the particles by the mesh partition and by work (slow, `make test-all`).

Stable: the run finishes (no particle outside the mesh, no overlap above `run.max_overlap`, no NaN: any of
these stops a run with exit status 3), every original is still in a group, and the energy the events inject
is reported. Each run is a `febed run` process, under `mpirun -n 2` for 2 ranks, as users run it.
"""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from _febed_process import MPIRUN, clean_env

from febed.io.particles import read_vtp
from febed.io.probes import read_probes
from febed.post import list_snapshots

CASE = Path(__file__).parents[2] / "demos" / "wang2d" / "coarse" / "pcpm2.toml"


@pytest.mark.slow
@pytest.mark.parametrize(("ranks", "partition"), [(1, "mesh"), (2, "mesh"), (2, "work")])
def test_pcpm_bed_runs_one_second(tmp_path, ranks, partition):
    if ranks == 2 and shutil.which("mpirun") is None:
        pytest.skip("needs mpirun")
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "febed.cli", "run", str(CASE), "--set", f"output.directory={out}"]
    cmd = (MPIRUN if ranks == 2 else []) + cmd + ["--set", "run.end_time=1.0"]
    cmd += ["--set", f"run.particle_partition={partition}"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=3600, env=clean_env())
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    status = json.loads((out / "status.json").read_text())
    # a run stops at the end of the first gas step at or after end_time (steps are not shortened to meet it):
    # within one gas step (dt_max 2e-4 s) after 1 s
    assert status["state"] == "finished" and 1.0 <= status["time"] <= 1.0 + 2e-4
    t, last = list_snapshots(out)[-1]
    assert 1.0 <= t <= 1.0 + 2e-4
    n_orig = read_vtp(last)["n_orig"]
    assert read_probes(out / "probes.csv")["left_outlet"][-1] == 0
    # 2D at l = 2: 1,020 groups of 8 in a layer two originals deep, i.e. 4,080 x 2 originals (febed/coarse/setup.py)
    assert int(n_orig.sum()) == 8160 and n_orig.min() >= 1  # every original still in exactly one group
    log = (out / "febed.log").read_text()
    assert log.count("energy injected") >= 10  # the groups' events and their energy, at every output
    if ranks == 2:
        assert "load imbalance max/mean" in log
