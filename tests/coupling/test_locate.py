"""Particle location: walk + grid search against a brute-force search over every cell."""

from mpi4py import MPI

import numpy as np
import pytest
from _coupling_meshes import ALL_MESHES, mesh_and_arrays, random_points
from dolfinx import mesh as dmesh

from febed.coupling.locate import FOUND, OUTSIDE_DOMAIN, OUTSIDE_LOCAL, locate, locate_brute_force
from febed.coupling.weights import compute_weights

MESHES = ALL_MESHES + ("tri-distorted", "tet-distorted", "quad-affine", "hex-affine")


def _map_back(ma, cell, w):
    """Physical point Σ_i ω_i x_i of reference coordinates (exact for P1 and for the Q1 isoparametric map)."""
    return np.einsum("pi,pia->pa", w, ma.x_dofs[ma.cell_dofs[cell]])


@pytest.mark.parametrize("name", MESHES)
def test_locate_matches_brute_force(name):
    _, ma = mesh_and_arrays(name)
    if ma.parallel:
        pytest.skip("serial test (see test_locate_mpi_each_point_owned_once)")
    assert np.all(ma.cell_affine) == (name not in ("quad", "hex"))  # both inverse maps are exercised
    pts = random_points(ma, 1500, seed=1, margin=0.004)
    cell, ref, status, exit_facet, missing = locate(ma, pts, np.full(len(pts), -1, np.int32))
    cb, rb = locate_brute_force(ma, pts)
    assert np.array_equal(cell, cb)
    found = cb >= 0
    assert 0 < missing == np.count_nonzero(~found) < len(pts)
    assert np.all(status[found] == FOUND)
    # the box is convex: every miss left through a domain-boundary facet, which is a boundary facet of the mesh
    assert np.all(status[~found] == OUTSIDE_DOMAIN)
    m, _ = mesh_and_arrays(name)
    exterior = dmesh.exterior_facet_indices(m.topology)
    assert np.all(np.isin(exit_facet[~found], exterior))
    assert np.max(np.abs(ref[found] - rb[found])) < 1e-10
    w = compute_weights(ma, ref, cell)
    assert np.max(np.abs(_map_back(ma, cell[found], w[found]) - pts[found])) < 1e-12 * 0.1
    # the weights filled in the same pass as the walk are those of `compute_weights`, bit for bit (zero if missed)
    w_walk = np.full_like(w, np.nan)
    locate(ma, pts, np.full(len(pts), -1, np.int32), w=w_walk)
    assert np.array_equal(w_walk, w) and np.all(w_walk[~found] == 0.0)

    # move the particles a bit and walk from the previous cell
    rng = np.random.default_rng(2)
    moved = pts + 0.01 * rng.standard_normal(pts.shape)
    if ma.gdim == 2:
        moved[:, 2] = 0.0
    cell2, ref2, status2, _, _ = locate(ma, moved, cell.copy())
    cb2, rb2 = locate_brute_force(ma, moved)
    assert np.array_equal(cell2, cb2)
    ok = cb2 >= 0
    assert np.max(np.abs(ref2[ok] - rb2[ok])) < 1e-10
    assert np.all(status2[ok] == FOUND) and np.all(status2[~ok] == OUTSIDE_DOMAIN)


@pytest.mark.mpi
@pytest.mark.parametrize("name", ["tet-unstructured", "hex"])
def test_locate_mpi_each_point_owned_once(name):
    """Every point inside the mesh lies in an owned cell of exactly one rank; misses are classified."""
    _, ma = mesh_and_arrays(name)
    comm = ma.comm
    pts = random_points(ma, 800, seed=3)
    cell, _, status, _, _ = locate(ma, pts, np.full(len(pts), -1, np.int32))
    owned = ((cell >= 0) & (cell < ma.num_owned_cells)).astype(np.int64)
    total = np.zeros_like(owned)
    comm.Allreduce(owned, total, op=MPI.SUM)
    anywhere = np.zeros_like(owned)
    comm.Allreduce((cell >= 0).astype(np.int64), anywhere, op=MPI.MAX)
    assert np.all(total == anywhere)
    assert anywhere.sum() > 0.9 * len(pts)
    if comm.size > 1:
        assert np.all(np.isin(status[cell < 0], [OUTSIDE_LOCAL, OUTSIDE_DOMAIN]))


def test_exit_facet_names_the_boundary(tmp_path):
    """Particles leaving the seed-000 bed through the top are reported with the outlet tag."""
    from febed.coupling.mesh_arrays import extract_mesh_arrays, facet_tag_lookup
    from febed.meshing import build_msh, load_msh

    md = load_msh(build_msh("wang2d", out=tmp_path / "w.msh"), comm=MPI.COMM_SELF)
    ma = extract_mesh_arrays(md.mesh, depth=1.5e-3)
    lookup = facet_tag_lookup(md.mesh, md.facet_tags)
    x = np.array([[0.045, 0.49, 0.0], [0.01, 0.2, 0.0], [0.03, 0.01, 0.0]])
    cell, _, status, _, _ = locate(ma, x, np.full(3, -1, np.int32))
    assert np.all(status == FOUND)
    x[:, 1] += [0.02, 0.0, -0.02]  # through the outlet, stays inside, through the inlet
    x[1, 0] = -0.003  # through the left wall
    cell, _, status, exit_facet, missing = locate(ma, x, cell)
    assert missing == 3 and np.all(status == OUTSIDE_DOMAIN)
    assert list(lookup[exit_facet]) == [md.tag_id("outlet"), md.tag_id("walls"), md.tag_id("inlet")]
