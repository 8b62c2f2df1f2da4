"""A particle whose position turns NaN, or that jumps absurdly far in one step, stops the DEM with a message
naming it (`DEM._blow_up`, checked at each pair-list rebuild), instead of a failure deep inside the pair search;
fast but physical motion does not."""

import json
import math

import numpy as np
import pytest

from febed.dem import DEM, DEMFailure, DEMParams
from febed.dem.contact import contact_time
from febed.dem.solver import BLOW_UP_JUMP

D, RHO, KN = 1e-3, 2500.0, 1000.0


def lattice_dem(integrator: str) -> DEM:
    """27 touching-free spheres on a 1.2 d lattice, at rest without gravity."""
    dem = DEM(DEMParams(stiffness=KN, gravity=0.0, integrator=integrator))
    g = np.arange(3) * 1.2 * D
    pos = np.array(np.meshgrid(g, g, g, indexing="ij")).reshape(3, -1).T
    dem.add_particles(pos, D, RHO)
    return dem


def dt_of(dem):
    return contact_time(KN, dem.params.restitution_pp, RHO * math.pi / 12 * D**3) / 6


@pytest.mark.parametrize("integrator", ["verlet", "rk2"])
def test_a_particle_jumping_absurdly_far_in_one_step_stops_the_dem(integrator):
    dem = lattice_dem(integrator)
    dt = dt_of(dem)
    dem.advance(5, dt)  # a quiet start: no failure
    row = int(np.flatnonzero(dem.particles.gid == 13)[0])  # the centre sphere
    spread = 2.4 * D * math.sqrt(3)  # the lattice's diagonal
    dem.particles.vel[row] = [1.1 * BLOW_UP_JUMP * spread / dt, 0.0, 0.0]
    with pytest.raises(DEMFailure, match=r"particle 13 at .* moved .* more than 1000 times the size of the particle "
                       r"cloud \(0\.00416 m\) in one step"):  # fmt: skip
        dem.advance(5, dt)


@pytest.mark.parametrize("integrator", ["verlet", "rk2"])
def test_a_nan_position_stops_the_dem_naming_the_particle(integrator):
    dem = lattice_dem(integrator)
    dt = dt_of(dem)
    dem.advance(2, dt)
    row = int(np.flatnonzero(dem.particles.gid == 4)[0])
    dem.particles.vel[row, 1] = np.nan
    with pytest.raises(DEMFailure, match=r"particle 4 at \[.*nan.*\] m has a non-finite position"):
        dem.advance(5, dt)


@pytest.mark.parametrize("lone", [False, True])
def test_fast_but_physical_motion_is_no_failure(lone):
    """A sphere flying off at several diameters per step (in free flight, or away from a lattice) rebuilds
    the list at every step, each time checked, and is no blow-up."""
    dem = lattice_dem("verlet")
    dt = dt_of(dem)
    if lone:
        dem.remove_particles(dem.particles.gid != 26)
    row = int(np.flatnonzero(dem.particles.gid == 26)[0])  # a corner: it flies away from the others
    dem.particles.vel[row] = [3.0 * D / dt, 3.0 * D / dt, 3.0 * D / dt]
    dem.advance(1, dt)
    builds = dem.pairs.builds
    dem.advance(50, dt)
    assert dem.pairs.builds >= builds + 49


def test_pure_dem_run_reports_the_blow_up_in_status_and_exit_code(tmp_path, monkeypatch, capsys):
    from febed import cli
    from febed.dem import solver

    case = tmp_path / "case.toml"
    case.write_text(
        "\n".join(
            [
                '[run]\nmode = "dem"\nend_time = 0.002',
                '[mesh]\nbuiltin = "box"\nextent = [0.01, 0.01, 0.02]\nsize = 0.005',
                "[particles]\ncount = 20\ndiameter = 1e-3\ndensity = 2500.0\nregion = [0, 0, 0, 0.01, 0.01, 0.01]",
                f'[output]\nparticle_interval = 0.001\ndirectory = "{tmp_path / "out"}"',
            ]
        )
    )
    advance = solver.DEM.advance
    calls = []

    def kick_then_advance(self, n_steps, dt=None, f_ext=None):  # the second chunk starts with a wild particle
        calls.append(1)
        if len(calls) == 2:
            self.particles.vel[0] = [1e3 / self.dt, 0.0, 0.0]  # 1 km per step in a 1 cm box
        return advance(self, n_steps, dt, f_ext)

    monkeypatch.setattr(solver.DEM, "advance", kick_then_advance)
    assert cli.main(["run", str(case)]) == 3
    err = capsys.readouterr().err
    assert "the run failed: the particles blew up: particle" in err and "times the size of the particle cloud" in err
    status = json.loads((tmp_path / "out" / "status.json").read_text())
    assert status["state"] == "failed" and "times the size of the particle cloud" in status["message"]
