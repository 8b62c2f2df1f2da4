"""The Numba cache of febed's kernels cannot go stale: an edited contact law reaches the cached force loops."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# The contact power of two overlapping spheres at rest under the `linear` law: k_n delta times their
# approach speed, computed by `contact_power`, a kernel of febed/dem/forces.py that inlines the law from
# febed/dem/contact.py. Prints the power and the cache folder in use.
SNIPPET = """
import os
import numpy as np
import febed
from febed.dem.contact import LinearParams
from febed.dem.forces import contact_power
from febed.dem.records import Bodies, Lists
pos = np.array([[0.0, 0.0, 0.0], [0.9e-3, 0.0, 0.0]])
vel = np.array([[0.1, 0.0, 0.0], [0.0, 0.0, 0.0]])
z = np.zeros((2, 3))
bodies = Bodies(pos, vel, z, z, z, z, np.full(2, 1e-3), np.full(2, 1e-6), np.full(2, 1e-13), 2, 2)
lists = Lists(np.array([0, 1, 1]), np.array([1]), np.zeros((1, 3)), np.zeros(3, dtype=np.int64),
              np.zeros(0, dtype=np.int64), np.zeros((0, 3)))
out = np.zeros(2)
contact_power(bodies, lists, LinearParams(1000.0, 0.0, 0.0), out)
print(repr(float(out[0])), os.environ["NUMBA_CACHE_DIR"])
"""


def run_copy(tree: Path, cache: Path) -> tuple[float, str]:
    env = dict(os.environ, PYTHONPATH=str(tree), NUMBA_CACHE_DIR=str(cache))
    out = subprocess.run(
        [sys.executable, "-c", SNIPPET], env=env, cwd=tree, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-2000:]
    power, folder = out.stdout.split()
    return float(power), folder


def test_an_edited_contact_law_reaches_the_cached_force_kernels(tmp_path):
    tree = tmp_path / "src"
    shutil.copytree(ROOT / "febed", tree / "febed", ignore=shutil.ignore_patterns("__pycache__"))
    cache = tmp_path / "cache"
    before, folder1 = run_copy(tree, cache)
    again, folder2 = run_copy(tree, cache)  # loaded from the cache: same folder, same number
    assert folder1 == folder2 and again == before
    assert before == pytest.approx(-1000.0 * 0.1e-3 * 0.1 / 1e-6, rel=1e-12)  # -k_n delta v / m (W/kg)
    law = tree / "febed" / "dem" / "contact.py"
    text = law.read_text()
    edited = text.replace("fn = -p.stiffness * delta -", "fn = -2.0 * p.stiffness * delta -")
    assert edited != text, "the normal force line of the linear law moved: update this test"
    law.write_text(edited)
    after, folder3 = run_copy(tree, cache)
    assert folder3 != folder1 and Path(folder3).parent == cache
    assert after == pytest.approx(2.0 * before, rel=1e-12)  # the kernel was recompiled with the edited law


def test_the_cache_folder_is_keyed_on_the_kernel_sources_and_not_nested(tmp_path, monkeypatch):
    import numba.core.config

    from febed import kernel_cache

    monkeypatch.setattr(numba.core.config, "CACHE_DIR", numba.core.config.CACHE_DIR)  # restored afterwards
    files = kernel_cache.kernel_sources()
    names = {p.relative_to(kernel_cache.PACKAGE).as_posix() for p in files}
    assert {"dem/forces.py", "dem/contact.py", "dem/integrate.py", "schema.py"} <= names
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    folder = kernel_cache.configure()
    assert folder.parent == tmp_path and kernel_cache.KEYED.match(folder.name)
    assert kernel_cache.configure() == folder  # a child process's environment: the same folder, not a nested one
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert kernel_cache.configure().parent == tmp_path / "xdg" / "febed" / "numba"
