"""SCG (seed 003 eq 7) in prescribed flows: with Stokes drag, originals and CG particles 2x, 4x, 8x larger follow
the same speed history (1e-8 relative) in the uniform and the vortex flow; without the rule they do not."""

import math
import sys
import types

import numpy as np
import pytest

from febed.coarse.oneway import OneWay, OneWayCase
from febed.coarse.scg import scg_count, scg_density, scg_particles
from febed.dem import DEM, DEMParams
from febed.gas.prescribed import make_prescribed_gas
from febed.runs.oneway import run_oneway

MU, RHO_G = 1.8e-5, 1.2


def _speeds(gas, d0, rho0, pos, rule, t_end, h, drag="stokes", integration="exponential"):
    dem = DEM(DEMParams(stiffness=1.0, gravity=0.0, rotation=False))
    ratios = np.array([1.0, 2.0, 4.0, 8.0])
    d = d0 * ratios
    rho = scg_density(rho0, d0, d) if rule else np.full(4, rho0)
    dem.add_particles(pos, d, rho)
    ow = OneWay(dem, gas, drag, integration)
    hist = []

    def rec(o):
        P = o.dem.particles
        order = np.argsort(P.gid)
        hist.append(np.linalg.norm(P.vel[order], axis=1))

    ow.advance(t_end, h, rec)
    return np.array(hist)


def _rel_spread(s):
    return float(np.max(np.abs(s[:, 1:] - s[:, :1]) / s[:, :1]))


def test_scg_uniform_flow_table1():
    d0, rho0 = 1e-3, 1000.0  # seed 003 Table 1
    tau = rho0 * d0**2 / (18 * MU)
    gas = make_prescribed_gas("uniform", RHO_G, MU, velocity=(1.0, 0.0, 0.0))
    pos = np.array([[0.0, 0.02 * k, 0.0] for k in range(4)])  # in a line across the flow
    s = _speeds(gas, d0, rho0, pos, True, tau, tau / 50)
    assert _rel_spread(s) < 1e-8
    # exponential drag integration is exact for a uniform flow: v = U (1 - exp(-t / tau))
    assert abs(s[-1, 0] - (1 - math.exp(-1.0))) < 1e-12
    s_plain = _speeds(gas, d0, rho0, pos, False, tau, tau / 50)
    assert _rel_spread(s_plain) > 0.5  # without the rule the 8x particle lags far behind


@pytest.mark.parametrize("integration", ["exponential", "explicit"])
def test_scg_vortex_flow_table2(integration):
    d0, rho0 = 10e-6, 1000.0  # seed 003 Table 2, 300 rpm, inflow 10 % of the vortex speed, vessel radius 0.5 mm
    tau = rho0 * d0**2 / (18 * MU)
    gas = make_prescribed_gas("vortex", RHO_G, MU, rpm=300.0, inflow_ratio=0.1)
    pos = np.array([[0.4e-3, 0.0, 0.2e-3 * k] for k in range(4)])  # in a line along the axis (no axial variation)
    s = _speeds(gas, d0, rho0, pos, True, 0.02, tau / 20, integration=integration)
    assert _rel_spread(s[1:]) < 1e-8
    assert s[-1, 0] > 0.5 * 0.4e-3 * 10 * math.pi * 0.5  # it moves with the vortex
    s_plain = _speeds(gas, d0, rho0, pos, False, 0.02, tau / 20, integration=integration)
    assert _rel_spread(s_plain[1:]) > 0.05


def test_scg_helpers_and_errors():
    d, rho = scg_particles(100e-6, 100.0, 2.0)  # seed 003 Table 3
    assert d == pytest.approx(200e-6) and rho == pytest.approx(25.0, rel=1e-14)
    assert scg_count(800, 2.0) == 100
    with pytest.raises(ValueError, match="rho_orig"):
        scg_density(-1.0, 1e-3, 2e-3)
    with pytest.raises(ValueError, match="flow"):
        make_prescribed_gas("swirl")
    with pytest.raises(ValueError, match="rpm"):
        make_prescribed_gas("vortex")
    with pytest.raises(ValueError, match="module:function"):
        make_prescribed_gas("function", function="nocolon")


@pytest.mark.mpi
def test_the_one_way_driver_refuses_a_distributed_dem():
    """Its windows and sub-steps follow this process's particles: a DEM with an exchange is refused."""
    from mpi4py import MPI

    from febed.parallel import BoxExchange

    dem = DEM(DEMParams(stiffness=1.0, gravity=0.0))
    dem.attach_exchange(BoxExchange(MPI.COMM_WORLD))
    with pytest.raises(ValueError, match="runs on one process"):
        OneWay(dem, make_prescribed_gas("uniform", velocity=[0.0, 0.0, 1.0]))


def test_vortex_field_and_user_function(tmp_path):
    gas = make_prescribed_gas("vortex", omega=2.0, inflow_ratio=5.0, center=(1.0, 0.0), outlet_radius=0.1,
                              outlet_velocity=1.0)  # fmt: skip
    x = np.array([[1.5, 0.0, 0.3], [1.0, 0.05, 0.0]])
    u = gas.velocity(x)
    assert np.allclose(u[0], [-5.0 * 2.0 * 0.5, 2.0 * 0.5, 0.0])  # u_r = -a w r, u_theta = w r
    assert u[1, 2] == 1.0  # outlet core flow
    mod = types.ModuleType("febed_test_flow")
    mod.shear = lambda x, t: np.column_stack([x[:, 1], np.zeros(len(x)), np.zeros(len(x))])
    sys.modules["febed_test_flow"] = mod
    g = make_prescribed_gas("function", function="febed_test_flow:shear")
    assert np.array_equal(g.velocity(x)[:, 0], x[:, 1])
    # the driver writes its particle history
    dem = DEM(DEMParams(stiffness=1.0, gravity=0.0))
    dem.add_particles(np.array([[0.0, 0.5, 0.0]]), 1e-4, 1000.0)
    ow = run_oneway(OneWayCase(flow="function", flow_params={"function": "febed_test_flow:shear"}, drag="stokes",
                               end_time=0.1, output_interval=0.05), tmp_path, dem=dem)  # fmt: skip
    data = np.loadtxt(tmp_path / "particles.csv", delimiter=",", skiprows=1)
    assert data.shape[0] == 3 and ow.t == pytest.approx(0.1)
    bad = DEM(DEMParams(stiffness=1.0, gravity=0.0))
    bad.add_particles(np.array([[0.0, 0.5, 0.0], [0.0, 0.6, 0.0]]), 1e-4, 1000.0)
    bad.particles.vel[1, 0] = np.nan
    from febed.solver import RunFailure

    with pytest.raises(RunFailure, match="particle 1 has a non-finite position or velocity at t = 0 s"):
        run_oneway(OneWayCase(end_time=0.1), tmp_path / "bad", dem=bad)
    tau = 1000 * 1e-8 / (18 * MU)
    assert data[-1, 5] == pytest.approx(0.5 * (1 - math.exp(-0.1 / tau)), rel=1e-9)
