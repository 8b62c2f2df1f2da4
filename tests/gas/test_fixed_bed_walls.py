"""The porous wall law (`wall_law = "brinkman"`, the default for walls without slip).

A wall node held at rest makes half a cell of gas stand still; in a packed bed the real wall layer (the
Brinkman layer, δ = √(ε μ / K) ≈ 40 µm) is far thinner than a cell. The wall law lets the wall nodes slide
against the Brinkman layer's shear (`febed.gas.boundary.porous_slip_inverse`). Checked here:

* the slip length against the discrete 1D problem it is derived from (exact flow deficit U δ for any h/δ);
* a 2D porous channel 15 mm wide (Ergun's K, ε = 0.45, 0.3 m/s) on 3, 6 and 12 cells across: the pressure
  gradient is Ergun's to within the real Brinkman layers' 1-2 % (strict no-slip: 1.72x, 1.27x, 1.12x);
* clear gas: the wall-law walls give Poiseuille's profile with the wall nodes at rest;
* the random packed bed of `benchmarks/fixed_bed_walls.py` (10,000 frozen beads in a 15 mm duct) on 6 cells
  across: the pressure gradient is Ergun's at the bed's measured void fraction within 2 %.
"""

import importlib.util
import logging
from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest
from _gas_cases import channel, owned

from febed.gas import BoundarySpec, VANSParameters, VANSSolver
from febed.gas.boundary import porous_slip_inverse

RHO, MU, D, EPS, U = 1.2, 1.8e-5, 1e-3, 0.45, 0.3
ROOT = Path(__file__).resolve().parents[2]


def ergun_gradient(U, eps):
    """Ergun's -dp/dx for superficial velocity U [Pa/m]."""
    return 150 * MU * (1 - eps) ** 2 * U / (eps**3 * D**2) + 1.75 * RHO * (1 - eps) * U**2 / (eps**3 * D)


def ergun_K(u, eps):
    """Momentum-exchange coefficient K with K u = Ergun's -dp/dx, u the interstitial speed [kg/(m^3 s)]."""
    return 150 * MU * (1 - eps) ** 2 / (eps**2 * D**2) + 1.75 * RHO * (1 - eps) * np.abs(u) / (eps * D)


@pytest.mark.parametrize("h_over_delta", [0.05, 0.5, 2.0, 20.0, 300.0])
def test_slip_length_gives_the_brinkman_layer_deficit_on_a_lumped_1d_mesh(h_over_delta):
    # ε μ u'' = K u − G on y > 0, nodes y_j = j h, lumped drag, 3-point viscous term, the wall node with the
    # Navier condition of slip length λ: the discrete flow deficit Σ_j w_j (U − u_j) must be U δ exactly
    eps_mu, K, G = 0.45 * 1.8e-5, 5000.0, 3.0
    delta = np.sqrt(eps_mu / K)
    h = h_over_delta * delta
    lam = 1.0 / porous_slip_inverse(np.array([K]), np.array([eps_mu]), np.array([h]))[0]
    n = int(60 * delta / h) + 200  # far beyond the layer
    A = np.zeros((n, n))
    b = np.full(n, G * h)
    for j in range(1, n - 1):
        A[j, j - 1 : j + 2] = eps_mu / h * np.array([1.0, -2.0, 1.0])
        A[j, j] -= K * h
    A[0, 0:2] = eps_mu / h * np.array([-1.0, 1.0])
    A[0, 0] -= K * h / 2 + eps_mu / lam
    b[0] = G * h / 2
    A[-1, -1], b[-1] = 1.0, -G / K  # the far field: u = U = G/K
    u = np.linalg.solve(A, -b)
    w = np.full(n, h)
    w[0] = h / 2
    deficit = float(np.sum(w * (G / K - u)))
    assert deficit == pytest.approx(G / K * delta, rel=1e-9)
    # the wall node slides at λ/δ of the bed's speed (what an inlet's corner with such a wall carries)
    assert u[0] / (G / K) == pytest.approx(lam / delta, rel=1e-9)
    # the limits: the Brinkman length in a packed bed, no-slip (λ → 0) in clear gas
    if h_over_delta >= 20:
        assert lam == pytest.approx(delta, rel=2.5 / h_over_delta**2 + 2 / h_over_delta)
    if h_over_delta <= 0.05:
        assert lam == pytest.approx(h * h_over_delta / 8, rel=0.01)


def _porous_channel(ny, law, slip=False):
    md = channel(0.06, 0.015, 4 * ny, ny)
    wall = BoundarySpec("wall", slip=True) if slip else BoundarySpec("wall", wall_law=law)
    bcs = {"inlet": BoundarySpec("inlet", velocity=U), "walls": wall, "outlet": BoundarySpec("outlet", pressure=0.0)}
    s = VANSSolver(md, VANSParameters(gravity=0.0, density=RHO, viscosity=MU, dt_max=2e-4, boundaries=bcs), eps=EPS)
    s.q[:, 0] = U
    for _ in range(300):
        info = s.step(s.compute_dt(), K=ergun_K(np.linalg.norm(s.u, axis=1), s.eps))
    x = owned(s, s.x)
    inner = (x[:, 0] > 0.02) & (x[:, 0] < 0.04)
    gp = owned(s, s.grad_p)[inner, 0]
    comm = MPI.COMM_WORLD
    mean = comm.allreduce(float(gp.sum())) / comm.allreduce(gp.size)
    assert abs(info.mass_imbalance) < 1e-6 * RHO * info.inflow
    return -mean / ergun_gradient(U, EPS)


@pytest.mark.mpi
def test_porous_channel_between_walls_gives_ergun_on_every_mesh():
    ratios = {ny: _porous_channel(ny, "brinkman") for ny in (3, 6, 12)}
    # the real Brinkman layers add 2 δ/W ≈ 0.5 %; the 3-cell channel adds Forchheimer's share of the slip
    for r in ratios.values():
        assert 1.0 < r < 1.02, ratios
    assert abs(ratios[12] - ratios[6]) < 0.002, ratios
    # strict no-slip: the first-order error the law removes
    strict = _porous_channel(3, "no_slip")
    assert strict == pytest.approx(1.72, abs=0.02)
    assert _porous_channel(3, "brinkman", slip=True) == pytest.approx(1.0, abs=2e-3)


@pytest.mark.mpi
def test_clear_gas_wall_law_is_no_slip():
    # no drag: λ → 0, the law is no-slip; Poiseuille's profile with the wall nodes at rest to round-off
    L, H, Um, mu = 3.0, 1.0, 1.0, 0.1
    md = channel(L, H, 48, 16)
    bcs = {"inlet": BoundarySpec("inlet", velocity=Um), "walls": BoundarySpec("wall"), "outlet": BoundarySpec("outlet")}
    s = VANSSolver(md, VANSParameters(gravity=0.0, density=1.0, viscosity=mu, dt_max=1.0, boundaries=bcs))
    comm = MPI.COMM_WORLD
    law_nodes = comm.allreduce(int((s.bc.law_nodes < s.n_owned).sum()))
    assert law_nodes == 2 * 47  # every wall node but the inlet's and the outlet's corners
    for _ in range(2000):
        s.step(s.compute_dt())
    x, q = owned(s, s.x), owned(s, s.q)
    sel = np.isclose(x[:, 0], 2.5)
    y = x[sel, 1]
    exact = 6 * Um * y * (H - y) / H**2
    err = comm.allreduce(float(np.sum((q[sel, 0] - exact) ** 2)))
    assert np.sqrt(err / comm.allreduce(float(np.sum(exact**2)))) < 0.01
    wall = (np.isclose(x[:, 1], 0.0) | np.isclose(x[:, 1], H)) & (x[:, 0] > 0.0)  # the inlet's corners are its own
    assert comm.allreduce(float(np.abs(q[wall]).max(initial=0.0)), op=MPI.MAX) < 1e-10 * Um


def _benchmark():
    spec = importlib.util.spec_from_file_location("fixed_bed_walls", ROOT / "benchmarks" / "fixed_bed_walls.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_random_packed_bed_between_walls_on_six_cells_is_ergun(tmp_path):
    fb = _benchmark()
    fb.LOG.setLevel(logging.WARNING)
    ratio, eps = fb.dp_ratio(6, {}, tmp_path)
    assert 0.40 < eps < 0.45  # a random close packing with the duct's wall layers
    assert ratio == pytest.approx(1.0, abs=0.02)


def test_random_packed_bed_on_three_cells_is_ergun(tmp_path):
    # the gas carries −ε_i∇p_i at each node (`coupling.pressure_gradient_reaction = "nodal"`, the default):
    # consistent with the ε and K it is given, so even a 5 mm mesh under a 40 mm bed's surface gives Ergun's
    # gradient; the projected reaction smooths the gradient over two cells and gives 0.968 with slip walls
    fb = _benchmark()
    fb.LOG.setLevel(logging.WARNING)
    slip, _ = fb.dp_ratio(3, {"slip": True}, tmp_path / "slip")
    law, _ = fb.dp_ratio(3, {}, tmp_path / "law")
    projected, _ = fb.dp_ratio(3, {"slip": True}, tmp_path / "projected", reaction="projected")
    assert slip == pytest.approx(1.0, abs=0.01)
    assert law == pytest.approx(1.0, abs=0.02)
    assert projected < slip - 0.015
