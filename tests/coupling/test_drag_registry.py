"""Drag laws reached through the registry: by name, in the batched kernels, and as `coupling.drag` choices."""

import json
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from test_drag import HAND, MU_G, RHO_G

from febed.coupling.drag import AtParticles, DragLaw, GasForces, NodalGas, drag_forces, gas_forces_kernel, get_drag_law
from febed.schema import DRAG_LAWS, param

D = 1.0e-3
# (eps, particle Reynolds number ε ρ_g |u - v| d / μ): packed, intermediate, dilute, and one above Re = 1000
POINTS = [(0.4, 0.5), (0.45, 30.0), (0.62, 5.0), (0.8, 120.0), (0.97, 2.0), (0.97, 1500.0)]
REPO = Path(__file__).resolve().parents[2]


def slip_of(eps, re):
    return re * MU_G / (eps * RHO_G * D)


@pytest.mark.parametrize("name", DRAG_LAWS.names())
def test_every_registered_law_reached_by_name_matches_its_formula(name):
    law = get_drag_law(name)
    assert isinstance(law, DragLaw) and law.name == name
    n = len(POINTS)
    eps = np.array([e for e, _ in POINTS])
    v = np.zeros((n, 3))
    u = np.zeros((n, 3))
    u[:, 2] = [slip_of(e, re) for e, re in POINTS]
    d = np.full(n, D)
    K, F = drag_forces(name, eps, u, v, d, np.ones(n), RHO_G, MU_G)
    for p, (e, _) in enumerate(POINTS):
        expect = HAND[name](e, u[p, 2], D)
        assert K[p] == pytest.approx(expect, rel=1e-12), (name, POINTS[p])
        assert K[p] == law(e, u[p, 2], D, RHO_G, MU_G)  # the batched kernel calls the same law
        assert F[p, 2] == K[p] * u[p, 2] and F[p, 0] == F[p, 1] == 0.0

    # the fused interpolation + forces kernel reaches the same law: one cell whose nodes carry the state
    cell_dofs = np.arange(4 * n, dtype=np.int32).reshape(n, 4)
    w = np.full((n, 4), 0.25)
    u_nodes = np.repeat(u, 4, axis=0)
    eps_nodes = np.repeat(eps, 4)
    K2, F_d, F_p, eps_p = np.empty(n), np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
    at = AtParticles(cell_dofs, np.arange(n, dtype=np.int32), w, v, d, np.ones(n))
    gas = NodalGas(u_nodes, eps_nodes, np.zeros((4 * n, 3)), RHO_G, MU_G, True)
    gas_forces_kernel(law, at, gas, GasForces.of(K2, F_d, F_p, eps_p))
    np.testing.assert_allclose(K2, K, rtol=1e-14)


def test_the_registry_gives_coupling_drag_its_choices():
    par = param("coupling.drag")
    assert par.choices is DRAG_LAWS
    assert par.choice_names() == DRAG_LAWS.names()
    value, err = par.check("gidaspow")
    assert value is None and "'gidaspow-blend'" in err and "'emms'" in err
    with pytest.raises(ValueError, match="unknown drag law 'gidaspow'; choose one of .*gidaspow-blend"):
        drag_forces("gidaspow", np.ones(1), np.zeros((1, 3)), np.zeros((1, 3)), np.ones(1), np.ones(1), 1.0, 1.0)


def test_a_function_passed_instead_of_a_law_must_be_registered():
    with pytest.raises(ValueError, match="not a registered drag law"):
        drag_forces(math.hypot, np.ones(1), np.zeros((1, 3)), np.zeros((1, 3)), np.ones(1), np.ones(1), 1.0, 1.0)


TOY = """
import json

import numpy as np
from numba import njit

from febed.coupling.drag import drag_forces, drag_law
from febed.schema import param


@drag_law("toy-linear")
@njit(cache=True)
def toy_linear(eps, slip, d, rho_g, mu_g):
    return 7.0 * mu_g * d * (1.0 + slip) / eps


par = param("coupling.drag")
assert "toy-linear" in par.choice_names(), par.choice_names()
assert par.check("toy-linear") == ("toy-linear", None)
eps = np.array([0.5, 0.8])
u = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 0.0]])
K, F = drag_forces("toy-linear", eps, u, np.zeros((2, 3)), np.full(2, 1e-3), np.array([1.0, 3.0]), 1.2, 2e-5)
print(json.dumps([K.tolist(), F.tolist()]))
"""


def test_a_new_law_is_one_function_and_one_decorator(tmp_path):
    """A law registered outside febed (in a fresh process with its own kernel cache) is a valid case choice and
    runs in the batched kernel with no other edit."""
    script = tmp_path / "toy_law.py"
    script.write_text(textwrap.dedent(TOY))
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"), PYTHONPATH=str(REPO))
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    K, F = json.loads(out.stdout.strip().splitlines()[-1])
    k0 = 7.0 * 2e-5 * 1e-3 * (1.0 + 2.0) / 0.5
    k1 = 3.0 * 7.0 * 2e-5 * 1e-3 * (1.0 + 1.0) / 0.8
    assert K == pytest.approx([k0, k1], rel=1e-14)
    np.testing.assert_allclose(F, [[0.0, 0.0, 2.0 * k0], [k1, 0.0, 0.0]], rtol=1e-14)
