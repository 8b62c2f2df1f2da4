"""Facet walls: closest points, one push on coplanar facets, every push at concave corners, no leaks."""

import numpy as np
import pytest

from febed.dem import DEM, DEMParams, Walls
from febed.dem.insertion import random_positions
from febed.dem.walls import EDGE, FACE, VERTEX, closest_on_facet

D, RHO, KN = 1e-3, 2500.0, 1000.0


def test_closest_point_on_triangle_vs_sampling():
    rng = np.random.default_rng(0)
    u, v = np.meshgrid(np.linspace(0, 1, 301), np.linspace(0, 1, 301))
    keep = u + v <= 1
    u, v = u[keep], v[keep]
    for _ in range(20):
        tri = rng.normal(size=(3, 3))
        pts = tri[0] + u[:, None] * (tri[1] - tri[0]) + v[:, None] * (tri[2] - tri[0])
        p = rng.normal(size=3) * 2
        qx, qy, qz, kind = closest_on_facet(p[0], p[1], p[2], tri, 3)
        best = np.min(np.linalg.norm(pts - p, axis=1))
        got = np.linalg.norm(np.array([qx, qy, qz]) - p)
        assert got <= best + 1e-12
        assert got >= best - 0.01 * np.max(np.linalg.norm(tri[1:] - tri[0], axis=1))
        assert kind in (FACE, EDGE, VERTEX)


def grid_quads(n, h, z=0.0):
    """An n x n grid of quads of side h in the plane z (coplanar facets sharing edges and vertices)."""
    quads = []
    for i in range(n):
        for j in range(n):
            x0, y0 = (i - n / 2) * h, (j - n / 2) * h
            quads.append([[x0, y0, z], [x0 + h, y0, z], [x0 + h, y0 + h, z], [x0, y0 + h, z]])
    return np.array(quads)


def force_on(walls, pos, law="linear"):
    dem = DEM(DEMParams(contact_model=law, stiffness=KN, gravity=0.0), walls=walls)
    dem.add_particles(np.atleast_2d(pos), D, RHO)
    dem.compute_forces()
    return dem.particles.force[0].copy()


@pytest.mark.parametrize(
    "xy",
    [
        (0.3e-3, 0.2e-3),
        (0.0, 0.0),
        (1e-3, 0.0),
        (0.5e-3, 0.5e-3),
        (1e-3, 1e-3),
        (0.25e-3, 1e-3),
        (1e-3 - 1e-15, 0.3e-3),
    ],
)
def test_coplanar_facets_push_once(xy):
    """On a face, a shared edge, a quad diagonal or a vertex shared by up to 8 triangles: exactly one push."""
    delta = 1e-5
    f = force_on(Walls(facets=grid_quads(6, 1e-3)), [xy[0], xy[1], D / 2 - delta])
    assert f == pytest.approx([0.0, 0.0, KN * delta], rel=1e-9, abs=1e-12)


def test_concave_corner_pushes_from_both_faces_and_convex_edge_once():
    big = 0.01
    floor = [[-big, -big, 0], [big, -big, 0], [big, big, 0], [-big, big, 0]]
    side = [[0, -big, 0], [0, big, 0], [0, big, big], [0, -big, big]]
    walls = Walls(facets=np.array([floor, side]))
    d1, d2 = 1e-5, 2e-5
    f = force_on(walls, [D / 2 - d1, 0.0, D / 2 - d2])
    assert f == pytest.approx([KN * d1, 0.0, KN * d2], rel=1e-9)
    # a cube's convex edge seen from outside, along the diagonal: one push from the edge
    cube = Walls(facets=np.array([[[0, -big, 0], [0, big, 0], [0, big, -big], [0, -big, -big]],
                                  [[0, -big, 0], [-big, -big, 0], [-big, big, 0], [0, big, 0]]]))  # fmt: skip
    delta = 1e-5
    s = (D / 2 - delta) / np.sqrt(2)
    f = force_on(cube, [s, 0.0, s])
    assert f == pytest.approx([KN * delta / np.sqrt(2), 0.0, KN * delta / np.sqrt(2)], rel=1e-6)


def closed_cube(side, n):
    """The six faces of [0, side]^3, each an n x n grid of triangles (12 n^2 facets)."""
    h = side / n
    quads = []
    for i in range(n):
        for j in range(n):
            a, b = i * h, j * h
            sq = np.array([[a, b], [a + h, b], [a + h, b + h], [a, b + h]])
            for axis in range(3):
                for val in (0.0, side):
                    q = np.zeros((4, 3))
                    others = [k for k in range(3) if k != axis]
                    q[:, others[0]] = sq[:, 0]
                    q[:, others[1]] = sq[:, 1]
                    q[:, axis] = val
                    quads.append(q)
    return np.array(quads)


def test_fast_particles_never_leak_from_a_faceted_cube():
    side = 8e-3
    walls = Walls(facets=closed_cube(side, 4))
    p = DEMParams(contact_model="linear-history", stiffness=1e5, restitution_pp=1.0, restitution_pw=1.0, gravity=0.0,
                  friction_pp=0.2, friction_pw=0.2, integrator="verlet")  # fmt: skip
    dem = DEM(p, walls=walls)
    n = 60
    dem.add_particles(random_positions(n, [0] * 3, [side] * 3, D, seed=2), D, RHO,
                      vel=np.random.default_rng(1).normal(0, 1.0, (n, 3)))  # fmt: skip
    for _ in range(40):
        dem.advance(100)
        x = dem.particles.pos
        assert np.all(x > 0) and np.all(x < side)
    assert dem.max_overlap < 0.05


def cylinder_facets(tmp_path):
    from mpi4py import MPI

    from febed.meshing import build_msh, load_msh

    path = build_msh("cylinder", size=0.008, out=tmp_path / "cyl.msh")
    md = load_msh(path, comm=MPI.COMM_SELF)
    return md.boundary_facet_coords(["walls", "inlet", "outlet"])


def pour_into_cylinder(tmp_path, n, d, t_end):
    facets = cylinder_facets(tmp_path)
    assert facets.shape[1] == 3 and facets.shape[0] > 500
    p = DEMParams(contact_model="linear-history", stiffness=1e5, restitution_pp=0.5, restitution_pw=0.5,
                  friction_pp=0.3, friction_pw=0.3, integrator="rk2")  # fmt: skip
    dem = DEM(p, walls=Walls(facets=facets))
    h = 0.025 / np.sqrt(2) - 1e-3
    dem.add_particles(random_positions(n, [-h, -h, 0.01], [h, h, 0.1], d, seed=7), d, RHO)
    while dem.time < t_end:
        dem.advance(500)
        x = dem.particles.pos
        rxy = np.hypot(x[:, 0], x[:, 1])
        # the mesh is a polygonal approximation of the cylinder: inside the circle and the end caps
        assert np.all(rxy < 0.025) and np.all(x[:, 2] > 0) and np.all(x[:, 2] < 0.15)
    return dem


def test_spheres_poured_in_cylinder_mesh_stay_inside(tmp_path):
    dem = pour_into_cylinder(tmp_path, 150, 2e-3, 0.12)
    assert dem.particles.pos[:, 2].max() < 0.03  # they reached the bottom
    assert dem.max_overlap < 0.05


@pytest.mark.slow
def test_many_spheres_poured_in_cylinder_mesh_stay_inside(tmp_path):
    dem = pour_into_cylinder(tmp_path, 2000, 2e-3, 0.3)
    assert dem.max_overlap < 0.05


def test_box_faces_covered_by_facets_become_planes():
    side = 8e-3
    quads = closed_cube(side, 4)
    walls = Walls.from_facets(quads, box=([0.0] * 3, [side] * 3))
    assert walls.plane_p.shape[0] == 6 and walls.facets.shape[0] == 0
    assert np.allclose(np.abs(walls.plane_n).sum(axis=1), 1.0)
    centre = np.full(3, side / 2)  # every normal points into the box
    assert np.all(np.einsum("ij,ij->i", centre - walls.plane_p, walls.plane_n) > 0)
    top = np.flatnonzero(np.all(np.isclose(quads[:, :, 2], side), axis=1))
    holed = Walls.from_facets(np.delete(quads, top[0], axis=0), box=([0.0] * 3, [side] * 3))
    assert holed.plane_p.shape[0] == 5  # the top face misses a facet: its 15 quads stay (30 triangles)
    assert holed.facets.shape[0] == 2 * (top.size - 1)
    assert not np.any(np.all(np.isclose(holed.plane_p, [0, 0, side]) & (holed.plane_n[:, 2:] < 0), axis=1))


@pytest.mark.parametrize("pos", [[4e-3, 4e-3, 0.45e-3], [0.4e-3, 4e-3, 0.3e-3], [0.45e-3, 0.35e-3, 0.4e-3],
                                 [7.6e-3, 3e-3, 7.55e-3], [4e-3, 4e-3, 4e-3]])  # fmt: skip
def test_planes_of_a_box_push_as_its_facets(pos):
    """Face, concave edge, concave corner and no contact: the same force from the planes as from the facets."""
    side = 8e-3
    quads = closed_cube(side, 4)
    f_facets = force_on(Walls(facets=quads), pos)
    f_planes = force_on(Walls.from_facets(quads, box=([0.0] * 3, [side] * 3)), pos)
    assert np.allclose(f_planes, f_facets, rtol=1e-12, atol=1e-15 * KN * D)


def test_segments_of_a_2d_box_become_lines():
    """2D walls: the sides of a rectangle, each split in segments, become four lines; a gap keeps its side."""
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([0.02, 0.05, 0.0])
    segs = []
    for a, m in ((0, 4), (1, 10)):  # sides x = const (split along y) and y = const (split along x)
        b = 1 - a
        for val in (lo[a], hi[a]):
            t = np.linspace(lo[b], hi[b], m + 1)
            for k in range(m):
                s = np.zeros((2, 3))
                s[:, a] = val
                s[:, b] = t[k : k + 2]
                segs.append(s)
    segs = np.array(segs)
    assert Walls.from_facets(segs, box=(lo, hi)).plane_p.shape[0] == 4
    part = Walls.from_facets(segs[1:], box=(lo, hi))
    assert part.plane_p.shape[0] == 3 and part.facets.shape[0] == 3


def test_state_restored_with_other_walls_drops_only_the_wall_history():
    """A checkpoint's wall ids mean its own walls: restored into a DEM whose walls differ (e.g. a checkpoint
    from before the bounding-box planes), the wall lists and history are dropped, the pair history kept."""
    side = 8e-3
    quads = closed_cube(side, 4)
    p = DEMParams(contact_model="linear-history", stiffness=1e4, friction_pp=0.5, friction_pw=0.5, integrator="verlet",
                  restitution_pp=0.1, restitution_pw=0.1)  # fmt: skip
    a = DEM(p, walls=Walls(facets=quads))
    vel = np.random.default_rng(4).normal(0, 0.3, (30, 3))
    a.add_particles(random_positions(30, [0] * 3, [side, side, 2 * D], D, seed=3), D, RHO, vel=vel)
    a.advance(2000)  # sliding on the floor and into each other: wall and pair contacts with tangential history
    state = a.get_state()
    assert np.any(a.whist != 0) and np.any(a.pairs.hist[: a.pairs.size] != 0)
    same = DEM(p, walls=Walls(facets=quads))
    same.set_state(state)
    assert np.array_equal(same.whist, a.whist) and not same._dirty
    planes = DEM(p, walls=Walls.from_facets(quads, box=([0.0] * 3, [side] * 3)))
    planes.set_state(state)
    assert planes._dirty and planes._saved[1][0].size == 0
    keys, vals = a.pairs.saved_history(a.particles.gid)
    assert np.array_equal(planes._saved[0][0], keys) and np.array_equal(planes._saved[0][1], vals)
    planes.advance(200)  # rebuilds its wall lists against the planes
    assert np.all(planes.particles.pos > 0) and np.all(planes.particles.pos < side)
    assert np.all(planes.wid[: planes.wstart[-1]] < planes.walls.count)


def test_state_restored_with_another_skin_rebuilds_the_lists_and_keeps_the_history():
    """A restart may change the pair-list skin (a performance setting): the restored lists are rebuilt with the
    new skin, the contact history carried by keys, and the particles move exactly as without the change."""
    side = 8e-3
    quads = closed_cube(side, 4)
    kw = dict(contact_model="linear-history", stiffness=1e4, friction_pp=0.5, friction_pw=0.5, integrator="verlet",
              restitution_pp=0.1, restitution_pw=0.1)  # fmt: skip
    a = DEM(DEMParams(skin=0.1, **kw), walls=Walls(facets=quads))
    vel = np.random.default_rng(4).normal(0, 0.3, (30, 3))
    a.add_particles(random_positions(30, [0] * 3, [side, side, 2 * D], D, seed=3), D, RHO, vel=vel)
    a.advance(2000)
    state = a.get_state()
    wide = DEM(DEMParams(skin=0.5, **kw), walls=Walls(facets=quads))
    wide.set_state(state)
    assert wide._dirty and not wide._lists_valid
    keys, vals = a.pairs.saved_history(a.particles.gid)
    assert np.array_equal(wide._saved[0][0], keys) and np.array_equal(wide._saved[0][1], vals)
    same = DEM(DEMParams(skin=0.1, **kw), walls=Walls(facets=quads))
    same.set_state(state)
    assert same._lists_valid and not same._dirty
    for dem in (a, wide, same):
        dem.advance(500)
    assert wide.pairs.skin == pytest.approx(5 * a.pairs.skin, rel=1e-12)

    def by_gid(dem):  # the rebuild may sort the rows
        return dem.particles.pos[np.argsort(dem.particles.gid)]

    assert np.allclose(by_gid(wide), by_gid(a), rtol=0.0, atol=1e-12 * side)
    assert np.array_equal(by_gid(same), by_gid(a))
