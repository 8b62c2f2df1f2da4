"""DEM.get_state / set_state: a DEM rebuilt from a checkpoint continues bit for bit."""

import numpy as np
import pytest

from febed.dem import DEM, DEMParams, Walls
from febed.dem.insertion import insert

D, RHO = 1e-3, 2500.0
BOX = [6 * D, 6 * D, 30 * D]


def make(integrator):
    p = DEMParams(contact_model="linear-history", stiffness=1000.0, restitution_pp=0.5, restitution_pw=0.5,
                  friction_pp=0.3, friction_pw=0.3, integrator=integrator, sort_every=3)  # fmt: skip
    return DEM(p, walls=Walls.box([0, 0, 0], BOX))


def bed(integrator):
    dem = make(integrator)
    insert(dem, 300, [0, 0, 0], [6 * D, 6 * D, 20 * D], D, RHO, how="random", seed=3)
    dem.advance(3000)  # falling and piling up: many sliding contacts with history
    return dem


def assert_same(a: DEM, b: DEM):
    pa, pb = a.particles, b.particles
    for name in ("pos", "vel", "omega", "force", "torque", "gid", "diameter", "mass"):
        assert np.array_equal(getattr(pa, name), getattr(pb, name)), name
    assert np.array_equal(a.pairs.hist[: a.pairs.size], b.pairs.hist[: b.pairs.size])
    assert np.array_equal(a.whist[: a.wstart[-1]], b.whist[: b.wstart[-1]])
    assert (a.time, a.steps, a.max_overlap, a.dt) == (b.time, b.steps, b.max_overlap, b.dt)


@pytest.mark.parametrize("integrator", ["rk2", "verlet"])
def test_checkpoint_continues_bit_for_bit(integrator, tmp_path):
    n = 400
    straight = bed(integrator)
    straight.advance(n)
    a = bed(integrator)
    a.advance(n // 2)
    state = a.get_state()
    assert all(isinstance(v, (np.ndarray, int, float)) for v in state.values())
    assert int(np.any(a.pairs.hist[: a.pairs.size] != 0, axis=1).sum()) > 20  # the history matters
    np.savez(tmp_path / "s.npz", **state)
    b = make(integrator)
    with np.load(tmp_path / "s.npz") as f:
        b.set_state(dict(f))
    b.advance(n - n // 2)
    a.advance(n - n // 2)
    assert_same(a, b)
    # the split itself changes nothing (time aside: n dt vs n/2 dt + n/2 dt may differ in the last bit)
    b.time = straight.time
    assert_same(straight, b)


def test_set_state_refuses_garbage():
    with pytest.raises(ValueError, match="get_state"):
        make("rk2").set_state({"pos": np.zeros((1, 3))})
