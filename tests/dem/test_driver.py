"""Pure-DEM case from a case file: walls from the cylinder mesh, insertion, output ParaView opens."""

import logging
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from febed.case import load_case
from febed.dem import DEM, DEMParams, Particles
from febed.io.particles import ParticleWriter, read_vtp

CASE = """
[run]
mode = "dem"
end_time = 0.02

[mesh]
builtin = "cylinder"
cell = "tetrahedron"
size = 0.008

[gas.boundary.inlet]
type = "inlet"
velocity = 0.0

[gas.boundary.walls]
type = "wall"

[gas.boundary.outlet]
type = "outlet"
particles = false

[particles]
diameter = 0.002
count = 100
region = [-0.02, -0.02, 0.01, 0.02, 0.02, 0.06]
{extra}

[contact]
stiffness = 1e5

[output]
particle_interval = 0.01
directory = "{out}"
"""


def test_pure_dem_case_runs_and_writes_particles(tmp_path):
    from febed.runs.dem import run

    (tmp_path / "case.toml").write_text(CASE.format(out=tmp_path / "out", extra=""))
    case = load_case(tmp_path / "case.toml")
    dem = run(case, tmp_path / "out", logging.getLogger("test"))
    assert dem.time == pytest.approx(0.02, abs=dem.dt)
    pvd = ET.parse(tmp_path / "out" / "particles" / "particles.pvd").getroot()
    files = [e.get("file") for e in pvd.iter("DataSet")]
    assert len(files) == 3
    last = read_vtp(tmp_path / "out" / "particles" / files[-1])
    assert last["Points"].shape == (100, 3)
    assert np.array_equal(np.sort(last["gid"]), np.arange(100))
    assert np.all(np.hypot(last["Points"][:, 0], last["Points"][:, 1]) < 0.025)
    assert np.all(last["Points"][:, 2] > 0)
    assert last["velocity"][:, 2].mean() < -0.05  # falling


def test_bed_file_packed_once_then_loaded(tmp_path):
    from febed.runs.dem import run

    extra = 'bed_file = "bed.npz"\nsettle_energy = 2e-8'
    text = CASE.format(out=tmp_path / "out", extra=extra).replace("0.01, 0.02, 0.02, 0.06]", "0.003, 0.02, 0.02, 0.02]")
    text = text.replace("stiffness = 1e5", "stiffness = 1e5\nrestitution_pp = 0.3\nrestitution_pw = 0.3")
    (tmp_path / "case.toml").write_text(text)
    case = load_case(tmp_path / "case.toml")
    run(case, tmp_path / "out", logging.getLogger("test"))
    assert (tmp_path / "bed.npz").exists()
    stamp = (tmp_path / "bed.npz").stat().st_mtime_ns
    dem = run(case, tmp_path / "out", logging.getLogger("test"))
    assert (tmp_path / "bed.npz").stat().st_mtime_ns == stamp  # loaded, not packed again
    assert dem.particles.pos[:, 2].max() < 0.02  # the packed bed lies at the bottom


def test_pack_restitution_applies_to_the_packing_only(tmp_path):
    """A bed packed with pack_restitution = 0.3 is the bed a case with e = 0.3 packs; the run keeps e = 0.97."""
    from febed.runs.dem import run

    beds = {}
    runs = [("damped", "restitution_pp = 0.3\nrestitution_pw = 0.3", ""),
            ("case", "restitution_pp = 0.97\nrestitution_pw = 0.97", "pack_restitution = 0.3")]  # fmt: skip
    for name, contact, particles in runs:
        extra = f'bed_file = "{name}.npz"\nsettle_energy = 2e-8\n{particles}'
        text = CASE.format(out=tmp_path / name, extra=extra)
        text = text.replace("0.01, 0.02, 0.02, 0.06]", "0.003, 0.02, 0.02, 0.02]").replace(
            "end_time = 0.02", "end_time = 1e-3"
        )
        text = text.replace("stiffness = 1e5", f"stiffness = 1e5\n{contact}")
        (tmp_path / f"{name}.toml").write_text(text)
        dem = run(load_case(tmp_path / f"{name}.toml"), tmp_path / name, logging.getLogger("test"))
        beds[name] = np.load(tmp_path / f"{name}.npz")["pos"]
        assert dem.params.restitution_pp == dem.params.restitution_pw == (0.3 if name == "damped" else 0.97)
    assert np.array_equal(beds["case"], beds["damped"])


def test_vtp_round_trip_and_pvd(tmp_path):
    p = Particles()
    p.add(np.random.default_rng(0).random((7, 3)), 1e-3, 2500.0, vel=np.ones((7, 3)))
    w = ParticleWriter(tmp_path)
    w.write(0.0, p)
    w.write(0.5, p)
    data = read_vtp(tmp_path / "particles_000001.vtp")
    assert np.array_equal(data["Points"], p.pos) and np.array_equal(data["gid"], p.gid)
    assert np.array_equal(data["diameter"], p.diameter) and np.array_equal(data["n_orig"], p.n_orig)
    assert np.array_equal(data["connectivity"], np.arange(7))
    steps = [float(e.get("timestep")) for e in ET.parse(tmp_path / "particles.pvd").getroot().iter("DataSet")]
    assert steps == [0.0, 0.5]
    assert not list(tmp_path.glob(".*"))  # no temporary files left


def test_two_dimensional_mode_keeps_particles_in_plane():
    from febed.dem import Walls

    dem = DEM(DEMParams(dim=2, integrator="verlet"), walls=Walls.box([0, 0, 0], [0.01, 0.02, 0], dim=2))
    rng = np.random.default_rng(0)
    pos = np.zeros((40, 3))
    pos[:, 0] = 0.001 + 0.008 * rng.random(40)
    pos[:, 1] = 0.001 + 0.0015 * np.arange(40) / 2
    pos[:, 0] = 0.001 + 0.0012 * (np.arange(40) % 7)
    pos[:, 1] = 0.001 + 0.0012 * (np.arange(40) // 7)
    vel = rng.normal(0, 0.1, (40, 3))
    dem.add_particles(pos, 1e-3, 2500.0, vel=vel)
    dem.advance(3000)
    P = dem.particles
    assert np.all(P.pos[:, 2] == 0) and np.all(P.vel[:, 2] == 0) and np.all(P.omega[:, :2] == 0)
    assert P.pos[:, 1].max() < 0.01  # gravity along -y
    assert np.all(P.pos[:, 0] > 0) and np.all(P.pos[:, 0] < 0.01) and np.all(P.pos[:, 1] > 0)
