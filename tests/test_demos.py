"""Every demo runs (briefly) and passes its own physics checks (STYLE.md item 1)."""

import subprocess
import sys
from pathlib import Path

import pytest

DEMOS = Path(__file__).parents[1] / "demos"


def run_demo(script: Path, *args: str, timeout: int = 1800) -> str:
    res = subprocess.run(
        [sys.executable, str(script), *args], capture_output=True, text=True, timeout=timeout, cwd=script.parent
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return res.stdout


def test_meshes_demo():
    assert "figures written" in run_demo(DEMOS / "meshes" / "demo_meshes.py")


def test_wang2d_demo_short():
    out = run_demo(DEMOS / "wang2d" / "demo_wang2d.py", "--end-time", "0.03")
    assert "figures:" in out


@pytest.mark.slow
def test_wang2d_bed_fluidizes():
    """Seed-000 bed at 0.9 m/s: time-averaged pressure drop over 1 s after start-up within 5 % of W/A."""
    out = run_demo(DEMOS / "wang2d" / "demo_wang2d.py", "--end-time", "1.3")
    assert "time-averaged bed pressure drop / weight" in out
