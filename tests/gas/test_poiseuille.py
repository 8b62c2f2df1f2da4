"""Channel Poiseuille flow: fully developed profile within 1 % (relative L2); superficial flux preserved for ε < 1."""

from mpi4py import MPI

import numpy as np
import pytest
from _gas_cases import channel, channel_solver, owned

L, H, U, MU = 3.0, 1.0, 1.0, 0.1  # Re = ρUH/μ = 10: entrance length ~ 0.6 H


@pytest.mark.parametrize("eps", [1.0, 0.5])
def test_poiseuille_profile_and_flux(eps):
    md = channel(L, H, 48, 16)
    s = channel_solver(md, U, mu=MU, eps=eps)
    for _ in range(1500):
        info = s.step(s.compute_dt())
    x, q = owned(s, s.x), owned(s, s.q)
    sel = np.isclose(x[:, 0], 2.5)
    y = x[sel, 1]
    exact = 6 * U * y * (H - y) / H**2  # superficial velocity εu, mean U whatever ε
    err2 = MPI.COMM_WORLD.allreduce(float(np.sum((q[sel, 0] - exact) ** 2)))
    ref2 = MPI.COMM_WORLD.allreduce(float(np.sum(exact**2)))
    assert np.sqrt(err2 / ref2) < 0.01
    # interstitial velocity is q / ε
    assert np.allclose(owned(s, s.u), q / eps)
    # steady: what enters leaves (consistent and direct outlet fluxes), inflow is exactly U H
    assert info.inflow == pytest.approx(U * H, rel=1e-12)
    assert abs(info.outflow - info.inflow) < 1e-6 * info.inflow
    assert abs(info.outflow_direct - info.inflow) < 1e-4 * info.inflow
    # fully developed pressure gradient -12 μ U / H^2
    gp = owned(s, s.grad_p)[sel & (x[:, 1] > 0.2) & (x[:, 1] < 0.8), 0]
    gsum = MPI.COMM_WORLD.allreduce(float(gp.sum()))
    gcount = MPI.COMM_WORLD.allreduce(gp.size)
    assert gsum / gcount == pytest.approx(-12 * MU * U / H**2, rel=0.02)
