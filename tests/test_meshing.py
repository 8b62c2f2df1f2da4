"""Seed meshes: Table 2 cell counts, exact volumes and patch areas, named tags, 1 vs N ranks."""

from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest

from febed.meshing import (
    PSEUDO2D_LEVELS,
    MeshError,
    _gmsh,
    build_msh,
    facet_area,
    global_cell_count,
    load_case_mesh,
    load_msh,
    mesh_volume,
)

pytestmark = pytest.mark.mpi

VOLUME = 0.08 * 0.015 * 0.25  # seed 001 bed, m^3


@pytest.mark.parametrize("level", ["coarse", "intermediate"])
def test_pseudo2d_table2(seed_meshes, level):
    md = load_msh(seed_meshes[f"pseudo2d-{level}"])
    (nx, ny, nz), (px, py) = PSEUDO2D_LEVELS[level]
    assert global_cell_count(md) == nx * ny * nz  # independent of the number of ranks
    assert md.mesh.topology.cell_type.name == "hexahedron"
    assert abs(mesh_volume(md) / VOLUME - 1) < 1e-12
    assert set(md.tags) == {"inlet", "bottom_wall", "walls", "outlet"}
    patch = px * (0.08 / nx) * py * (0.015 / ny)
    assert abs(facet_area(md, "bottom_wall") / patch - 1) < 1e-12
    assert abs((facet_area(md, "inlet") + patch) / (0.08 * 0.015) - 1) < 1e-12
    assert abs(facet_area(md, "outlet") / (0.08 * 0.015) - 1) < 1e-12
    assert abs(facet_area(md, "walls") / (2 * (0.08 + 0.015) * 0.25) - 1) < 1e-12


@pytest.mark.slow
def test_pseudo2d_fine_table2(tmp_path):
    if MPI.COMM_WORLD.size > 1:
        pytest.skip("serial check of the 184,800-cell mesh")
    md = load_msh(build_msh("pseudo2d", tmp_path / "fine.msh", level="fine"), comm=MPI.COMM_SELF)
    assert global_cell_count(md) == 70 * 12 * 220
    assert abs(facet_area(md, "bottom_wall") / (10 * 0.08 / 70 * 8 * 0.015 / 12) - 1) < 1e-12


def test_patch_is_centred(seed_meshes):
    md = load_msh(seed_meshes["pseudo2d-intermediate"])
    quads = md.boundary_facet_coords(["bottom_wall"])
    lo, hi = quads.reshape(-1, 3).min(axis=0), quads.reshape(-1, 3).max(axis=0)
    assert np.allclose([lo[0] + hi[0], lo[1] + hi[1]], [0.08, 0.015], atol=1e-14)
    assert np.allclose(lo[2], 0) and np.allclose(hi[2], 0)


def test_tetrahedral_variant(seed_meshes):
    md = load_msh(seed_meshes["pseudo2d-tet"])
    assert md.mesh.topology.cell_type.name == "tetrahedron"
    assert abs(mesh_volume(md) / VOLUME - 1) < 1e-12
    assert set(md.tags) == {"inlet", "bottom_wall", "walls", "outlet"}


@pytest.mark.parametrize("variant,cell,ncells", [("wang2d", "quadrilateral", 1800), ("wang2d-tri", "triangle", 3600)])
def test_wang2d(seed_meshes, variant, cell, ncells):
    md = load_msh(seed_meshes[variant])
    assert md.gdim == 2
    assert md.mesh.topology.cell_type.name == cell
    assert global_cell_count(md) == ncells
    assert abs(mesh_volume(md) / (0.09 * 0.5) - 1) < 1e-12
    assert abs(facet_area(md, "inlet") / 0.09 - 1) < 1e-12
    assert abs(facet_area(md, "walls") / 1.0 - 1) < 1e-12


def test_cylinder(seed_meshes):
    md = load_msh(seed_meshes["cylinder"])
    assert set(md.tags) == {"inlet", "walls", "outlet"}
    exact = np.pi * 0.025**2 * 0.15
    assert abs(mesh_volume(md) / exact - 1) < 0.02  # polyhedral approximation of a cylinder


def test_boundary_facet_coords_whole_mesh_once(seed_meshes):
    """Every tagged facet appears exactly once on every rank; quads are cyclic (their areas add up)."""
    md = load_msh(seed_meshes["pseudo2d-coarse"])
    quads = md.boundary_facet_coords(["walls"])
    assert quads.shape == (2 * (17 + 3) * 55, 4, 3)
    a, b, c, d = (quads[:, k] for k in range(4))
    area = 0.5 * np.linalg.norm(np.cross(c - a, d - b), axis=1)
    assert abs(area.sum() / (2 * (0.08 + 0.015) * 0.25) - 1) < 1e-12
    centres = np.round(quads.mean(axis=1), 12)
    assert len(np.unique(centres, axis=0)) == len(quads)


def test_missing_tag_lists_available(seed_meshes):
    md = load_msh(seed_meshes["wang2d"])
    with pytest.raises(MeshError, match="mesh has: inlet, outlet, walls"):
        md.require_tags(["inlet", "distributor"])


def test_case_mesh_checks_the_tags_a_boundary_names(tmp_path):
    """cross_section_tags and wins_over name facet tags: a missing one is reported before anything runs."""
    from febed.case import load_case

    for key in ("cross_section_tags", "wins_over"):
        data = {
            "run": {"mode": "cfd-dem"},
            "mesh": {"builtin": "wang2d"},
            "gas": {
                "boundary": {
                    "inlet": {"type": "inlet", "velocity": 0.9, key: ["nozzle"]},
                    "outlet": {"type": "outlet"},
                }
            },
        }
        with pytest.raises(MeshError, match=rf"\[gas.boundary.inlet\] {key} names facet tag\(s\) 'nozzle'"):
            load_case_mesh(load_case(data=data), cache_dir=tmp_path)


def test_bad_requests(tmp_path):
    with pytest.raises(MeshError, match="unknown built-in mesh"):
        build_msh("sphere", tmp_path / "x.msh")
    with pytest.raises(MeshError, match="comes in"):
        build_msh("wang2d", tmp_path / "x.msh", cell="hexahedron")
    with pytest.raises(MeshError, match="mesh file not found"):
        load_msh(tmp_path / "missing.msh")


GEO = Path(__file__).parents[1] / "meshes"


@pytest.mark.parametrize("geo,builtin", [("pseudo2d", "pseudo2d-coarse"), ("wang2d", "wang2d")])
def test_geo_sources_match_builders(seed_meshes, mpi_tmp_path, geo, builtin):
    """The gmsh sources in meshes/ and the Python builders describe the same mesh."""
    out = mpi_tmp_path / f"{geo}.msh"
    if MPI.COMM_WORLD.rank == 0:
        gmsh = _gmsh()
        gmsh.clear()
        gmsh.open(str(GEO / f"{geo}.geo"))
        gmsh.model.mesh.generate(gmsh.model.getDimension())
        gmsh.write(str(out))
        gmsh.clear()
    MPI.COMM_WORLD.barrier()
    a, b = load_msh(out), load_msh(seed_meshes[builtin])
    assert global_cell_count(a) == global_cell_count(b)
    assert set(a.tags) == set(b.tags)
    for tag in a.tags:
        assert abs(facet_area(a, tag) / facet_area(b, tag) - 1) < 1e-12, tag


@pytest.mark.parametrize("variant", ["pseudo2d-coarse", "wang2d-tri"])
def test_cells_are_shared_by_coordinate_bisection_across_gravity(seed_meshes, variant):
    """load_msh distributes the cells by `rcb_owners` of their centroids, cutting only across gravity (the last
    axis): the ranks own equal shares to one cell, each share spans the mesh's whole height, and loading again
    gives the same partition."""
    comm = MPI.COMM_WORLD
    md = load_msh(seed_meshes[variant])
    again = load_msh(seed_meshes[variant]).mesh.topology
    t = md.mesh.topology
    n = t.index_map(t.dim).size_local
    x = md.mesh.geometry.x
    gdim = md.mesh.geometry.dim
    dofs = md.mesh.geometry.dofmap.array.reshape(-1, md.mesh.geometry.dofmap.links(0).size)[:n]
    height = x[dofs, gdim - 1].mean(axis=1)  # cell centroids along gravity
    lo, hi = comm.allreduce(height.min(), op=MPI.MIN), comm.allreduce(height.max(), op=MPI.MAX)
    counts, total = comm.allgather(n), global_cell_count(md)  # (every collective call before any assert)
    assert max(counts) - min(counts) <= 1 and sum(counts) == total
    tol = 1e-9 * (hi - lo)  # (centroids are means in each rank's node order)
    assert height.min() < lo + tol and height.max() > hi - tol  # every rank's cells reach the bottom and the top
    assert np.array_equal(again.original_cell_index[:n], t.original_cell_index[:n])


def test_a_measure_over_named_tags_integrates_them_and_compiles_once(seed_meshes):
    """MeshData.ds(names): ∫ ds is the sum of the tags' areas; the form is the same for any tags (one JIT)."""
    import dolfinx.fem
    import ufl

    md = load_msh(seed_meshes["pseudo2d-coarse"])
    one = dolfinx.fem.Constant(md.mesh, 1.0)

    def area(names):
        local = dolfinx.fem.assemble_scalar(dolfinx.fem.form(one * md.ds(names)))
        return md.comm.allreduce(local, op=MPI.SUM)

    pair = area(["walls", "bottom_wall"])
    assert abs(pair / (facet_area(md, "walls") + facet_area(md, "bottom_wall")) - 1) < 1e-12
    assert abs(area(["inlet", "bottom_wall", "inlet"]) / (0.08 * 0.015) - 1) < 1e-12  # a tag named twice counts once
    assert md.ds([]) is None
    with pytest.raises(MeshError, match="no facet tag 'lid'"):
        md.ds(["lid"])
    forms = [one * md.ds(names) for names in (["walls"], ["outlet"], ["inlet", "bottom_wall"])]
    assert len({f.signature() for f in forms}) == 1
    assert (one * ufl.ds).signature() != forms[0].signature()


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="one process: a fresh interpreter that has not imported gmsh")
def test_a_mesh_is_built_from_a_worker_thread(tmp_path):
    """gmsh's module sets the SIGINT handler on import, which Python refuses outside the main thread."""
    import subprocess
    import sys

    script = (
        "import signal, threading\n"
        "from mpi4py import MPI\n"
        "from febed.meshing import build_msh, load_msh\n"
        "before = signal.getsignal(signal.SIGINT)\n"
        "out = []\n"
        "def work():\n"
        f"    path = build_msh('pseudo2d', {str(tmp_path / 'x.msh')!r})\n"
        "    out.append(load_msh(path, comm=MPI.COMM_SELF).mesh.topology.index_map(3).size_global)\n"
        "t = threading.Thread(target=work)\n"
        "t.start(); t.join()\n"
        "assert out and signal.getsignal(signal.SIGINT) is before, out\n"
        "print('built', out[0])\n"
    )
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and "built" in run.stdout, run.stderr
