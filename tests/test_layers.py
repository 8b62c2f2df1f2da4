"""tools/check_layers.py: febed's modules import downwards only, without cycles; a planted upward import fails.

Each planted import goes into a copy of the febed package in a temporary folder.
"""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TOOL = ROOT / "tools" / "check_layers.py"


def check(root: Path, *options: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(TOOL), *options, str(root)], capture_output=True, text=True, timeout=120, cwd=root
    )


def errors(res: subprocess.CompletedProcess) -> list[str]:
    return [line for line in res.stdout.splitlines() if ": note: " not in line]


@pytest.fixture
def tree(tmp_path):
    """A copy of the febed package under tmp_path (the checker's ROOT)."""
    shutil.copytree(ROOT / "febed", tmp_path / "febed", ignore=shutil.ignore_patterns("__pycache__"))
    return tmp_path


def plant(tree: Path, module: str, text: str) -> tuple[str, int]:
    """Append `text` to febed/<module>.py of the copy; returns (the file as printed, the first appended line)."""
    path = tree / "febed" / f"{module}.py"
    old = path.read_text()
    path.write_text(old.rstrip("\n") + "\n\n\n" + text)
    return f"febed/{module}.py", len(old.rstrip("\n").splitlines()) + 3


def test_the_repository_passes():
    res = subprocess.run([sys.executable, str(TOOL)], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert res.returncode == 0, res.stdout + res.stderr
    assert errors(res) == [] and res.stderr == ""


def test_the_copy_passes(tree):
    res = check(tree)
    assert res.returncode == 0 and errors(res) == [], res.stdout + res.stderr


@pytest.mark.parametrize(
    ("module", "text", "message"),
    [
        (
            "dem/walls",
            "import febed.runs.coupled\n",
            "febed.dem.walls imports febed.runs.coupled (layer runs above layer dem)",
        ),
        (
            "io/probes",
            "def later():\n    from febed.study import load_study\n\n    return load_study\n",
            "febed.io.probes imports febed.study (layer study above layer base)",
        ),
        (
            "gas/operators",
            "from febed.coupling import drag\n",
            "febed.gas.operators imports febed.coupling.drag "
            "(layer coupling beside layer gas: neither imports the other)",
        ),  # fmt: skip
        (
            "post/series",
            "from febed.runs.probes import bed_height\n",
            "febed.post.series imports febed.runs.probes (layer runs beside layer post: neither imports the other)",
        ),  # fmt: skip
        (
            "solver",
            "from febed.dem.driver import build_dem\n",
            "febed.solver imports febed.dem.driver, which does not exist",
        ),  # fmt: skip
    ],
    ids=["dem-imports-run", "io-imports-study-in-a-function", "gas-imports-coupling", "post-imports-run", "missing"],
)
def test_a_planted_import_fails_naming_its_line(tree, module, text, message):
    where, line = plant(tree, module, text)
    if text.startswith("def "):
        line += 1  # the import is the function's first line
    res = check(tree)
    assert res.returncode == 1, res.stdout + res.stderr
    # (febed.runs.coupled -> ... -> febed.dem.walls: a cycle too)
    assert f"{where}:{line}: {message}" in errors(res), res.stdout
    assert "import(s) against febed's layers" in res.stderr


def test_an_import_cycle_fails(tree):
    where, line = plant(tree, "coupling/mesh_arrays", "def later():\n    from febed.coupling import exchange\n")
    res = check(tree)
    assert res.returncode == 1, res.stdout + res.stderr
    cycle = "febed.coupling.mesh_arrays -> febed.coupling.exchange -> febed.coupling.mesh_arrays"
    said = f"{where}:{line + 1}: febed.coupling.mesh_arrays imports febed.coupling.exchange (cycle: {cycle})"
    assert said in errors(res), res.stdout


def test_a_module_outside_every_layer_fails(tree):
    (tree / "febed" / "extra.py").write_text('"""A module nobody placed."""\n')
    res = check(tree)
    assert res.returncode == 1
    assert errors(res) == ["febed/extra.py:1: febed.extra is in no layer: add it to LAYERS in tools/check_layers.py"]


def test_type_checking_imports_do_not_count(tree):
    plant(
        tree,
        "dem/walls",
        "from typing import TYPE_CHECKING\n\nif TYPE_CHECKING:\n    from febed.runs.coupled import CoupledRun\n",
    )
    res = check(tree)
    assert res.returncode == 0 and errors(res) == [], res.stdout


def test_a_function_level_import_that_avoids_nothing_is_a_note(tree):
    where, line = plant(tree, "case", "def later():\n    from febed.schema import SCHEMA\n\n    return SCHEMA\n")
    res = check(tree)
    assert res.returncode == 0, res.stdout + res.stderr
    note = f"{where}:{line + 1}: note: febed.case imports febed.schema inside a function, which loads nothing"
    assert any(s.startswith(note) for s in res.stdout.splitlines()), res.stdout
    listed = check(tree, "-v").stdout  # -v: also those that avoid a heavy dependency, with what they avoid
    assert "febed/coarse/setup.py:" in listed and "imports febed.coarse.tm inside a function: avoids numba" in listed


def test_a_folder_without_febed_is_an_error(tmp_path):
    res = check(tmp_path)
    assert res.returncode == 2 and "holds no febed package" in res.stderr
