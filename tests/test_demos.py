"""Every demo runs (briefly), passes its own checks and writes only under its own `out/` folder.

Each demo is run as a user runs it, a separate `python demos/<name>/<script>.py` process with its shortest
options; the demo's folder (all but `out/`) must be unchanged afterwards. The Python API demo is run by
tests/test_demo_api.py (serially and on 2 ranks).
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest
from _febed_process import clean_env

DEMOS = Path(__file__).parents[1] / "demos"


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    """(size, mtime) of every file under `folder` except in `out/` and `__pycache__/` folders."""
    files = {}
    for root, dirs, names in os.walk(folder):
        dirs[:] = [d for d in dirs if d not in ("out", "__pycache__")]
        for n in names:
            st = os.stat(os.path.join(root, n))
            files[os.path.relpath(os.path.join(root, n), folder)] = (st.st_size, st.st_mtime_ns)
    return files


def run_demo(script: Path, *args: str, timeout: int = 1800) -> str:
    """Run a demo script; assert it succeeds and leaves its folder (but `out/`) as it was; return its stdout."""
    before = snapshot(script.parent)
    res = subprocess.run(
        [sys.executable, str(script), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=script.parent,
        env=clean_env(),
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    after = snapshot(script.parent)
    changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
    assert not changed, f"{script.name} wrote outside {script.parent / 'out'}: {changed}"
    return res.stdout


def test_meshes_demo():
    assert "figures written" in run_demo(DEMOS / "meshes" / "demo_meshes.py")


def test_wang2d_demo_short():
    out = run_demo(DEMOS / "wang2d" / "demo_wang2d.py", "--end-time", "0.03")
    assert "figures:" in out


# The pseudo-2D bed (57,296 particles) is packed on first use, which takes minutes: slow until it exists.
PSEUDO2D_BED = DEMOS / "pseudo2d" / "pseudo2d-75g.npz"


@pytest.mark.parametrize("end_time", [pytest.param("0.004", marks=[] if PSEUDO2D_BED.exists() else [pytest.mark.slow])])
def test_pseudo2d_demo_short(end_time):
    out = run_demo(DEMOS / "pseudo2d" / "demo_pseudo2d.py", "--end-time", end_time)
    assert "checks passed: solid volume conserved" in out
    assert list((DEMOS / "pseudo2d" / "out" / "figures").glob("C1_*.png"))


def test_scg_demo():
    out_dir = DEMOS / "scg" / "out"
    run_demo(DEMOS / "scg" / "scg_demo.py", "--out", str(out_dir))
    assert (out_dir / "results.json").exists() and (out_dir / "fig3_uniform_speed.png").exists()


@pytest.mark.slow
def test_wang2d_bed_fluidizes():
    """Seed-000 bed at 0.9 m/s: time-averaged pressure drop over 1 s after start-up within 5 % of W/A."""
    out = run_demo(DEMOS / "wang2d" / "demo_wang2d.py", "--end-time", "1.3")
    assert "time-averaged bed pressure drop / weight" in out
