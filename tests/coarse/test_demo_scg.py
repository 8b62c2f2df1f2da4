"""The SCG demo runs and passes its own checks (default run, ~35 s: marked slow)."""

import importlib.util
from pathlib import Path

import pytest

DEMO = Path(__file__).resolve().parents[2] / "demos" / "scg" / "scg_demo.py"


@pytest.mark.slow
def test_scg_demo_default_run(tmp_path):
    spec = importlib.util.spec_from_file_location("scg_demo", DEMO)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    res = mod.main(["--out", str(tmp_path)])  # asserts inside
    assert (tmp_path / "fig10_classifier_radial.png").exists()
    assert res["classifier"]["drained_fraction"]["plain"][0] < res["classifier"]["drained_fraction"]["scg"][0]
