"""Poured spheres settle to a random packing; insertion, settling and the bed file."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from febed.dem import DEM, DEMParams, Walls
from febed.dem.insertion import count_from_mass, insert, lattice_positions, load_bed, save_bed, settle

D, RHO = 1e-3, 2500.0


def solid_fraction(pos, lo, hi, samples=200_000, seed=0):
    """Monte Carlo solid fraction of monodisperse spheres of diameter D inside the box [lo, hi]."""
    pts = np.random.default_rng(seed).uniform(lo, hi, (samples, 3))
    dist, _ = cKDTree(pos).query(pts)
    return float(np.mean(dist < D / 2))


def pour(n, width):
    p = DEMParams(contact_model="linear-history", stiffness=1000.0, restitution_pp=0.5, restitution_pw=0.5,
                  friction_pp=0.3, friction_pw=0.3, integrator="verlet")  # fmt: skip
    height = n * np.pi / 6 * D**3 / 0.25 / width**2
    box_hi = [width, width, 2 * height]
    dem = DEM(p, walls=Walls.box([0, 0, 0], box_hi))
    insert(dem, n, [0, 0, 0], [width, width, height], D, RHO, how="random", seed=11)
    settle(dem, energy=1e-12, max_time=1.0)
    x = dem.particles.pos
    assert np.all(x > 0) and np.all(x < np.array(box_hi))  # none outside
    dem.max_overlap = 0.0  # impacts while pouring overlap more; the settled bed must not
    dem.advance(200)
    assert dem.max_overlap < 0.01
    top = np.percentile(x[:, 2], 97)
    lo = [1.5 * D, 1.5 * D, 2 * D]
    hi = [width - 1.5 * D, width - 1.5 * D, top - 3 * D]
    return solid_fraction(x, lo, hi), dem


def test_small_pour_settles_to_random_packing():
    phi, dem = pour(800, 8 * D)
    assert 0.56 <= phi <= 0.64, phi
    assert dem.mean_kinetic_energy() < 1e-12


@pytest.mark.slow
def test_5000_spheres_settle_to_random_packing():
    phi, _ = pour(5000, 14 * D)
    assert 0.56 <= phi <= 0.64, phi


def test_insertion_by_mass_lattice_and_bed_file(tmp_path):
    n = count_from_mass(1e-3, D, RHO)
    assert n == round(1e-3 / (RHO * np.pi / 6 * D**3))
    pos = lattice_positions(n, [0, 0, 0], [0.01, 0.01, 0.1], D, rng=np.random.default_rng(0))
    assert pos.shape == (n, 3)
    dmin = cKDTree(pos).query(pos, k=2)[0][:, 1].min()
    assert dmin >= D
    with pytest.raises(ValueError, match="holds"):
        lattice_positions(10_000, [0, 0, 0], [0.01, 0.01, 0.01], D)
    dem = DEM(DEMParams(), walls=Walls.box([0, 0, 0], [0.01, 0.01, 0.1]))
    dem.add_particles(pos, D, RHO)
    path = save_bed(tmp_path / "bed.npz", dem.particles, diameter=D)
    assert not list(tmp_path.glob(".*tmp*"))
    bed, meta = load_bed(path)
    assert np.array_equal(bed.pos, dem.particles.pos) and np.array_equal(bed.gid, dem.particles.gid)
    assert float(meta["diameter"]) == D
    with pytest.raises(ValueError, match="does not exist"):
        load_bed(tmp_path / "missing.npz")
