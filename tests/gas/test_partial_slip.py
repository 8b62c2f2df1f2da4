"""Navier partial-slip walls (`BoundarySpec.slip_length`): channel flow against the analytic profile.

Between walls at y = 0 and H with u = λ ∂u/∂n, the developed superficial velocity of mean U is
q(y) = U (y (H − y) + λ H) / (H²/6 + λ H) and the pressure gradient −2 μ U / (H²/6 + λ H) whatever ε: it spans
Poiseuille (λ = 0, `test_poiseuille.py`) and plug flow (λ → ∞, free slip).
"""

from mpi4py import MPI

import numpy as np
import pytest
from _gas_cases import channel, owned

from febed.gas import BoundarySpec, VANSParameters, VANSSolver

L, H, U, MU = 3.0, 1.0, 1.0, 0.1


def _solver(md, slip_length, eps=1.0):
    bcs = {
        "inlet": BoundarySpec("inlet", velocity=U),
        "walls": BoundarySpec("wall", slip=True, slip_length=slip_length),
        "outlet": BoundarySpec("outlet", pressure=0.0),
    }
    return VANSSolver(md, VANSParameters(gravity=0.0, density=1.0, viscosity=MU, dt_max=1.0, boundaries=bcs), eps=eps)


def _gather(s, sel, a):
    return MPI.COMM_WORLD.allreduce(float(np.sum(a[sel])))


@pytest.mark.mpi
@pytest.mark.parametrize("lam, eps", [(0.1, 1.0), (0.5, 0.5)])
def test_partial_slip_channel_profile(lam, eps):
    md = channel(L, H, 48, 16)
    s = _solver(md, lam, eps)
    for _ in range(2000):
        s.step(s.compute_dt())
    x, q = owned(s, s.x), owned(s, s.q)
    sel = np.isclose(x[:, 0], 2.5)
    y = x[:, 1]
    denom = H**2 / 6 + lam * H
    exact = U * (y * (H - y) + lam * H) / denom
    err2 = _gather(s, sel, (q[:, 0] - exact) ** 2)
    ref2 = _gather(s, sel, exact**2)
    assert np.sqrt(err2 / ref2) < 0.01
    # the wall nodes slide at the slip velocity and carry no normal velocity
    wall = sel & (np.isclose(y, 0.0) | np.isclose(y, H))
    n_wall = MPI.COMM_WORLD.allreduce(int(wall.sum()))
    assert n_wall == 2
    assert _gather(s, wall, q[:, 0]) / n_wall == pytest.approx(U * lam * H / denom, rel=0.02)
    assert MPI.COMM_WORLD.allreduce(float(np.abs(q[wall, 1]).sum())) < 1e-12
    gp = owned(s, s.grad_p)[sel & (y > 0.2) & (y < 0.8), 0]
    mean_gp = MPI.COMM_WORLD.allreduce(float(gp.sum())) / MPI.COMM_WORLD.allreduce(gp.size)
    assert mean_gp == pytest.approx(-2 * MU * U / denom, rel=0.02)  # εμ∇u = μ∇q: no 1/ε


@pytest.mark.mpi
def test_slip_length_limits():
    """A very small slip length gives Poiseuille's profile, a very large one the free slip's."""
    md = channel(L, H, 48, 16)
    profiles = {}
    for key, spec in {
        "tiny": BoundarySpec("wall", slip=True, slip_length=1e-4 * H),
        "free": BoundarySpec("wall", slip=True),
        "huge": BoundarySpec("wall", slip=True, slip_length=1e6 * H),
    }.items():
        bcs = {"inlet": BoundarySpec("inlet", velocity=U), "walls": spec, "outlet": BoundarySpec("outlet")}
        s = VANSSolver(md, VANSParameters(gravity=0.0, density=1.0, viscosity=MU, dt_max=1.0, boundaries=bcs))
        for _ in range(1500):
            s.step(s.compute_dt())
        x = owned(s, s.x)
        sel = np.isclose(x[:, 0], 2.5)
        profiles[key] = (x[sel, 1], owned(s, s.q)[sel, 0].copy())

    def rel(key, exact):
        y, q = profiles[key]
        d = MPI.COMM_WORLD.allreduce(float(np.sum((q - exact(y)) ** 2)))
        return np.sqrt(d / MPI.COMM_WORLD.allreduce(float(np.sum(exact(y) ** 2))))

    assert rel("tiny", lambda y: 6 * U * y * (H - y) / H**2) < 0.01  # no-slip's Poiseuille profile
    free = dict(zip(*(np.round(a, 12) for a in profiles["free"]), strict=True))
    assert rel("huge", lambda y: np.array([free[v] for v in np.round(y, 12)])) < 1e-4
    assert rel("free", lambda y: 6 * U * y * (H - y) / H**2) > 0.1  # the two limits differ


def test_slip_length_validation():
    with pytest.raises(ValueError, match="slip_length needs type = 'wall' with slip = true"):
        BoundarySpec("wall", slip_length=1e-4).validate("walls")
    with pytest.raises(ValueError, match="slip_length must be > 0"):
        BoundarySpec("wall", slip=True, slip_length=0.0).validate("walls")
