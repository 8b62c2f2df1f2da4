"""The seed-000 bed over its first 0.05 s against a stored reference: a change of behaviour shows here.

`tests/data/wang2d-probes-0.05s.csv` holds the probes (every 1e-3 s) of `demos/wang2d/wang2d.toml` run on one
process to t = 0.05 s, and on its first line the CPU (as Numba compiles for it) and library versions that wrote
them. A change of code that is not meant to change the results (a refactor, a faster kernel with the same
arithmetic) must reproduce them bit for bit on such a machine: febed's runs are deterministic on one process
(the restart tests rely on it too).

The bits are not portable: Numba compiles for the CPU it runs on, and the force loop's fast-math products may
be contracted differently on another one. The bed is chaotic even over 0.05 s: the gas viscosity changed in its
last bit moves the probes by up to about 1e-3 of their range (`test_round_off_growth_stays_within_the_tolerance`).
On another machine the probes are therefore compared within `RTOL_OTHER`, which catches a changed model but not
a change at round-off. When the results change on purpose, write the file again (on the machine that checks
refactors):

    FEBED_WRITE_REFERENCE=1 .venv/bin/python -m pytest tests/test_reference_run.py -k stored
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from febed.io.probes import read_probes

ROOT = Path(__file__).resolve().parents[1]
CASE = ROOT / "demos" / "wang2d" / "wang2d.toml"
REFERENCE = ROOT / "tests" / "data" / "wang2d-probes-0.05s.csv"
RTOL_OTHER = 2e-2  # relative to each column's largest magnitude, on a machine other than the reference's
COLUMNS = ("kinetic_energy", "bed_height", "dp_bed", "p_bottom", "p_top", "p_0.045", "cfl", "gas_inflow")


def machine() -> str:
    """The CPU Numba compiles for (LLVM's name and a hash of its features) and the libraries the bits depend on."""
    import llvmlite.binding as llvm

    llvm.initialize()
    llvm.initialize_native_target()
    features = hashlib.sha256(llvm.get_host_cpu_features().flatten().encode()).hexdigest()[:8]
    cpu = f"{platform.machine()} {llvm.get_host_cpu_name()} features {features}"
    libs = []
    for name in ("numba", "llvmlite", "numpy", "petsc4py", "fenics-dolfinx", "mpi4py"):
        try:
            libs.append(f"{name} {importlib.metadata.version(name)}")
        except importlib.metadata.PackageNotFoundError:
            libs.append(f"{name} ?")
    return f"{cpu}; python {platform.python_version()}; " + ", ".join(libs)


def run_case(out: Path, *extra: str) -> dict[str, np.ndarray]:
    """The probes of the wang2d case run to 0.05 s in a fresh process (one rank) into `out`."""
    cmd = [sys.executable, "-m", "febed.cli", "run", str(CASE), "--set", f"output.directory={out}",
           "--set", "run.end_time=0.05", "--set", "output.field_interval=1", "--set", "output.particle_interval=1",
           *extra]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    return {k: np.asarray(v) for k, v in read_probes(out / "probes.csv").items()}


def differences(a: dict, b: dict) -> dict[str, float]:
    """Largest difference of each compared column, relative to the column's largest magnitude in `a`."""
    assert np.array_equal(a["time"], b["time"]) and np.array_equal(a["step"], b["step"])
    return {k: float(np.max(np.abs(b[k] - a[k])) / max(np.max(np.abs(a[k])), 1e-300)) for k in COLUMNS}


def write_reference(probes: dict) -> None:
    names = ["time", "step", *COLUMNS]
    data = np.column_stack([probes[k] for k in names])
    np.savetxt(REFERENCE, data, delimiter=",", header=f"{machine()}\n" + ",".join(names), fmt="%.17g")


def read_reference() -> tuple[str, dict[str, np.ndarray]]:
    """(machine line, columns) of the stored reference."""
    with open(REFERENCE) as f:
        written_on = f.readline()[2:].strip()
        names = f.readline()[2:].strip().split(",")
    data = np.loadtxt(REFERENCE, delimiter=",", comments="#", ndmin=2)
    return written_on, {k: data[:, i] for i, k in enumerate(names)}


def test_the_seed000_bed_reproduces_its_stored_probes(tmp_path):
    probes = run_case(tmp_path / "run")
    if os.environ.get("FEBED_WRITE_REFERENCE"):
        write_reference(probes)
    written_on, ref = read_reference()
    worst = differences(ref, probes)
    if written_on == machine():
        assert max(worst.values()) == 0.0, f"not bit for bit on the reference's machine ({written_on}): {worst}"
    else:
        assert max(worst.values()) <= RTOL_OTHER, f"written on {written_on}, run on {machine()}: {worst}"


@pytest.mark.slow
def test_round_off_growth_stays_within_the_tolerance(tmp_path):
    """The gas viscosity changed in its last bit moves the probes by less than RTOL_OTHER / 10 over 0.05 s."""
    base = run_case(tmp_path / "base")
    mu = 1.7e-5  # demos/wang2d/wang2d.toml's
    ulp = run_case(tmp_path / "ulp", "--set", f"gas.viscosity={float(np.nextafter(mu, 1.0))!r}")
    worst = differences(base, ulp)
    assert 0.0 < max(worst.values()) <= RTOL_OTHER / 10, worst
