"""`DEM.layout` moves whenever the particle rows may have changed (the coupled solver's `located` relies on
it), and not when the DEM is only read."""

import numpy as np

from febed.dem import DEM, DEMParams, Walls


def test_layout_moves_with_every_change_of_rows_and_not_on_reads():
    lo, hi = np.zeros(3), np.full(3, 0.01)
    dem = DEM(DEMParams(gravity=9.81, stiffness=800.0), walls=Walls.box(lo, hi))
    dem.add_particles(np.array([[0.002, 0.002, 0.002], [0.006, 0.006, 0.006]]), 1e-3, 2500.0)
    seen = [dem.layout]

    def moved(what):
        assert dem.layout != seen[-1], f"{what} left DEM.layout unchanged"
        seen.append(dem.layout)

    dem.advance(3)
    moved("advance")
    dem.kinetic_energy(), dem.critical_time(), dem.elastic_energy(), dem.get_state()
    assert dem.layout == seen[-1], "reading the DEM moved its layout"
    dem.advance(0)
    assert dem.layout == seen[-1], "advance(0) moved nothing"
    dem.rebuild()
    moved("rebuild")
    dem.add_particles(np.array([[0.004, 0.008, 0.004]]), 1e-3, 2500.0)
    moved("add_particles")
    dem.remove_particles(np.array([0]))
    moved("remove_particles")
    state = dem.get_state()
    dem.touch()
    moved("touch")
    dem.set_state(state)
    moved("set_state")
