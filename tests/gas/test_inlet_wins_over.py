"""An inlet that wins over a no-slip wall patch at their shared nodes (`BoundarySpec.wins_over`).

A 2D channel whose inlet (x = 0) holds a no-slip `patch` over 0.015 ≤ y ≤ 0.025 (two cells, three nodes).
By default no-slip wins at the patch's two edge nodes; with `wins_over = ("patch",)` they take the inlet's
velocity and only the middle node is held still. Either way the discrete inflow is U_f over the whole
cross-section (`cross_section_tags`), exactly.
"""

from mpi4py import MPI

import numpy as np
import pytest
from _gas_cases import channel

from febed.gas import BoundarySpec, VANSParameters, VANSSolver
from febed.meshing import MeshError

H, U = 0.04, 0.5


def _solver(md, **inlet) -> VANSSolver:
    bcs = {
        "inlet": BoundarySpec("inlet", velocity=U, cross_section_tags=("patch",), **inlet),
        "walls": BoundarySpec("wall"),
        "outlet": BoundarySpec("outlet"),
    }
    return VANSSolver(md, VANSParameters(density=1.0, viscosity=1e-3, dt_max=1e-3, boundaries=bcs), eps=1.0)


@pytest.fixture(scope="module")
def mesh():
    return channel(0.1, H, 20, 8, patch=(0.015, 0.025))


@pytest.mark.mpi
@pytest.mark.parametrize("wins", [False, True])
def test_patch_edge_nodes_and_the_inflow(mesh, wins):
    comm = MPI.COMM_WORLD
    s = _solver(mesh, wins_over=("patch",) if wins else ())
    n = s.n_owned
    x, y = s.x[:n, 0], s.x[:n, 1]
    qx = s.q[:n, 0]
    on_inlet = np.isclose(x, 0.0)

    def at(yy):  # qx at the inlet node at height yy, from whichever rank owns it
        m = on_inlet & np.isclose(y, yy)
        return comm.allreduce(float(qx[m][0]) if m.any() else -np.inf, op=MPI.MAX)

    open_cells = 8 - (1 if wins else 3) - 1  # no gas over the patch's two cells ∓ one, half a cell at each wall
    speed = U * 8 / open_cells  # the inlet's nodal speed: U over the whole height, through the open part
    assert at(0.02) == 0.0  # the patch's middle node: no gas
    assert at(0.015) == pytest.approx(speed if wins else 0.0, rel=1e-12)
    assert at(0.025) == pytest.approx(speed if wins else 0.0, rel=1e-12)
    assert at(0.0) == 0.0 and at(H) == 0.0  # the corners with the channel's walls stay no-slip
    assert at(0.005) == pytest.approx(speed, rel=1e-12)
    inflow = comm.allreduce(float(-(s.ops.bnormal[:n][on_inlet] * s.q[:n][on_inlet]).sum()), op=MPI.SUM)
    assert inflow == pytest.approx(U * H, rel=1e-12)  # U_f over the whole cross-section, either way


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
    bcs["inlet"] = BoundarySpec("inlet", velocity=U, wins_over=("nozzle",))
    with pytest.raises(MeshError, match=r"an inlet's wins_over names facet tag\(s\) 'nozzle'"):
        VANSSolver(mesh, VANSParameters(boundaries=bcs), eps=1.0)
