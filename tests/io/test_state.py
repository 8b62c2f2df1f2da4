"""A checkpoint's DEM state made portable (gid order, for a restart on another number of ranks)."""

import numpy as np

from febed.dem import DEM, DEMParams
from febed.io.state import portable


def test_auxiliary_rows_follow_their_particles_into_gid_order():
    """A one-rank DEM's rows are in linked-cell order; portable puts them in gid order, each aux row with its own."""
    dem = DEM(DEMParams(gravity=0.0))
    rng = np.random.default_rng(4)
    dem.add_particles(rng.uniform(0.0, 0.02, (50, 3)), 1e-3, 2500.0)
    dem.advance(1)  # the first rebuild sorts the rows by linked cell
    P = dem.particles
    tag = P.attach("fluid", 2)
    tag[:, 0] = P.gid[: P.n_owned]
    tag[:, 1] = P.pos[: P.n_owned, 2]
    state = dem.get_state()
    assert not np.all(np.diff(state["p_gid"]) > 0)  # not in gid order to begin with
    out = portable(state)
    assert np.array_equal(out["p_gid"], np.arange(50))
    assert np.array_equal(out["aux_fluid"][:, 0], out["p_gid"]) and np.array_equal(
        out["aux_fluid"][:, 1], out["p_pos"][:, 2]
    )
