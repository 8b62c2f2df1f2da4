"""A run that compiles the DEM kernels and a run that loads them from Numba's cache give the same bits.

An integrator kernel holds its own copy of the force loop (Numba links the callee into the caller and optimises
the whole again); a run that compiles calls the loop's standalone code, a run from the cache the integrator's
copy. The copies must compute the same numbers, which the fast-math flags of `febed.dem.contact.FAST` ensure by
leaving out reassociation (with it, the seed-000 bed's positions differ in their last bits from the first steps).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = """
import hashlib
import numpy as np
from febed.dem import DEM, DEMParams, Walls
from febed.dem.insertion import load_bed

parts, _ = load_bed({bed!r})
p = DEMParams(contact_model="linear", stiffness=800.0, restitution_pp=0.9, restitution_pw=0.9, friction_pp=0.3,
              friction_pw=0.3, integrator="rk2", dim=2)
dem = DEM(p, particles=parts, walls=Walls.box([0, 0, -0.001], [0.09, 0.5, 0.001]))
dem.particles.vel[:, 0] = 0.05 * np.sin(np.arange(dem.particles.n) * 0.7)  # stir the packed bed
dem.advance(10)
dem.advance(400)
print(hashlib.sha1(dem.particles.pos[: dem.particles.n_owned].tobytes()).hexdigest())
"""


def test_a_run_that_compiles_and_a_run_from_the_cache_agree_bit_for_bit(tmp_path):
    # the seed-000 bed (4,080 spheres, 2D) with the linear law under RK2, the combination that showed it
    script = tmp_path / "run.py"
    script.write_text(SCRIPT.format(bed=str(ROOT / "demos" / "wang2d" / "wang2d-bed.npz")))
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"), PYTHONPATH=str(ROOT))
    hashes = []
    for _ in range(2):  # the first run compiles and fills the empty cache, the second loads from it
        out = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stderr
        hashes.append(out.stdout.strip().splitlines()[-1])
    assert hashes[0] == hashes[1]
