"""Where an inlet meets walls: the open area of the inlet with wall-law walls, and `BoundarySpec.wins_over`.

A 2D channel whose inlet (x = 0) holds a wall `patch` over 0.015 ≤ y ≤ 0.025 (two cells, three nodes).
With the default porous wall law the inlet takes the nodes it shares with the walls, each with the inlet
facets' share of its boundary weight (1/2 at the patch's edges): the gas enters through exactly the inlet's
facets on any mesh, except at the corners with the channel walls across it, which move as those walls
slide: not at all in clear gas (5 cells of 8 open), nearly fully in a packed bed (nearly 6 of 8). With
strict no-slip walls (`wall_law = "no_slip"`) no-slip wins at the patch's two edge nodes and at the corners,
and the gas enters through four cells' worth; with `wins_over = ("patch",)` the patch's edge nodes take the
inlet's velocity and only the middle node is held still. In every case the discrete inflow is U_f over the
whole cross-section (`cross_section_tags`), exactly. Where the patch is a second inlet, the nodes the two
share carry both inlets' gas, each by its facets' share.
"""

from mpi4py import MPI

import numpy as np
import pytest
from _gas_cases import channel

from febed.gas import BoundarySpec, VANSParameters, VANSSolver
from febed.meshing import MeshError

H, U = 0.04, 0.5


def _solver(md, law="brinkman", **inlet) -> VANSSolver:
    bcs = {
        "inlet": BoundarySpec("inlet", velocity=U, cross_section_tags=("patch",), **inlet),
        "patch": BoundarySpec("wall", wall_law=law),
        "walls": BoundarySpec("wall", wall_law=law),
        "outlet": BoundarySpec("outlet"),
    }
    return VANSSolver(
        md, VANSParameters(gravity=0.0, density=1.0, viscosity=1e-3, dt_max=1e-3, boundaries=bcs), eps=1.0
    )


@pytest.fixture(scope="module")
def mesh():
    return channel(0.1, H, 20, 8, patch=(0.015, 0.025))


@pytest.mark.mpi
@pytest.mark.parametrize("law, wins", [("brinkman", False), ("no_slip", False), ("no_slip", True)])
def test_patch_edge_nodes_and_the_inflow(mesh, law, wins):
    comm = MPI.COMM_WORLD
    s = _solver(mesh, law, wins_over=("patch",) if wins else ())
    n = s.n_owned
    x, y = s.x[:n, 0], s.x[:n, 1]
    on_inlet = np.isclose(x, 0.0)

    def at(yy):  # qx at the inlet node at height yy, from whichever rank owns it
        m = on_inlet & np.isclose(y, yy)
        return comm.allreduce(float(s.q[:n, 0][m][0]) if m.any() else -np.inf, op=MPI.MAX)

    def check(slide):
        if law == "brinkman":  # the inlet's facets, the corners' half cells as far as the side walls slide
            speed = U * 8 / (5 + slide)
            edge, corner = 0.5 * speed, slide * speed
        else:  # no gas over the patch's two cells ∓ one, half a cell at each wall
            speed = U * 8 / (8 - (1 if wins else 3) - 1)
            edge, corner = (speed if wins else 0.0), 0.0
        assert at(0.02) == 0.0  # the patch's middle node: no gas
        assert at(0.015) == pytest.approx(edge, rel=1e-12)
        assert at(0.025) == pytest.approx(edge, rel=1e-12)
        assert at(0.0) == pytest.approx(corner, rel=1e-12) and at(H) == pytest.approx(corner, rel=1e-12)
        assert at(0.005) == pytest.approx(speed, rel=1e-12)
        inflow = comm.allreduce(float(-(s.ops.bnormal[:n][on_inlet] * s.q[:n][on_inlet]).sum()), op=MPI.SUM)
        assert inflow == pytest.approx(U * H, rel=1e-12)  # U_f over the whole cross-section, always

    check(0.0)  # clear gas: the wall law is no-slip, and so are the corners with the channel walls
    K = 2.0e4  # a packed bed's drag: δ = √(ε μ/K) ≈ 0.22 mm against cells of 5 mm
    info = s.step(1e-4, K=K)
    kappa_h = np.sqrt(K / 1e-3) * H / 8
    check(1.0 - 2.0 / np.sqrt(4.0 + kappa_h**2) if law == "brinkman" else 0.0)  # they slide as the walls do
    assert info.inflow == pytest.approx(U * H, rel=1e-12)
    assert abs(info.mass_imbalance) < 1e-6 * info.inflow


@pytest.mark.mpi
@pytest.mark.parametrize("ratio", [1.0, 2.0])
def test_two_inlets_share_their_edge_nodes(mesh, ratio):
    """The patch is a second inlet at `ratio` U, the channel walls slip (the corners carry the inlet's gas): the
    nodes the two inlets share carry both, half each, so each inlet's gas enters through its own facets. With
    one speed the inflow is uniform, U at every inlet node (an inlet that took the shared nodes whole would give
    6/7 U beside the patch and 2 U over it)."""
    comm = MPI.COMM_WORLD
    bcs = {
        "inlet": BoundarySpec("inlet", velocity=U),
        "patch": BoundarySpec("inlet", velocity=ratio * U),
        "walls": BoundarySpec("wall", slip=True),
        "outlet": BoundarySpec("outlet"),
    }
    s = VANSSolver(mesh, VANSParameters(gravity=0.0, density=1.0, viscosity=1e-3, boundaries=bcs), eps=1.0)
    n = s.n_owned
    x, y = s.x[:n, 0], s.x[:n, 1]
    on_inlet = np.isclose(x, 0.0)

    def at(yy):
        m = on_inlet & np.isclose(y, yy)
        return comm.allreduce(float(s.q[:n, 0][m][0]) if m.any() else -np.inf, op=MPI.MAX)

    for yy in (0.0, 0.005, 0.01, 0.03, H):
        assert at(yy) == pytest.approx(U, rel=1e-12), yy
    assert at(0.02) == pytest.approx(ratio * U, rel=1e-12)
    for yy in (0.015, 0.025):
        assert at(yy) == pytest.approx(0.5 * (1.0 + ratio) * U, rel=1e-12), yy
    assert np.all(np.abs(s.q[:n, 1][on_inlet]) < 1e-15)  # along the inward normal only
    inflow = comm.allreduce(float(-(s.ops.bnormal[:n][on_inlet] * s.q[:n][on_inlet]).sum()), op=MPI.SUM)
    assert inflow == pytest.approx(U * (H - 0.01) + ratio * U * 0.01, rel=1e-12)


def test_wins_over_needs_an_inlet_and_a_no_slip_wall(mesh):
    with pytest.raises(ValueError, match=r"boundary 'walls': wins_over is for an inlet"):
        BoundarySpec("wall", wins_over=("patch",)).validate("walls")
    bcs = {
        "inlet": BoundarySpec("inlet", velocity=U, wins_over=("walls",)),
        "walls": BoundarySpec("wall", slip=True),
        "outlet": BoundarySpec("outlet"),
    }
    with pytest.raises(ValueError, match=r"boundary 'inlet': wins_over 'walls' is not a no-slip wall"):
        VANSSolver(mesh, VANSParameters(boundaries=bcs), eps=1.0)
    bcs["walls"] = BoundarySpec("wall")  # the porous wall law: the inlet shares its nodes by facet already
    with pytest.raises(ValueError, match=r"boundary 'inlet': wins_over 'walls' needs wall_law = 'no_slip'"):
        VANSSolver(mesh, VANSParameters(boundaries=bcs), eps=1.0)
    bcs["inlet"] = BoundarySpec("inlet", velocity=U, wins_over=("nozzle",))
    with pytest.raises(MeshError, match=r"an inlet's wins_over names facet tag\(s\) 'nozzle'"):
        VANSSolver(mesh, VANSParameters(boundaries=bcs), eps=1.0)
