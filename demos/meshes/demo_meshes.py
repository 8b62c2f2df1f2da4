# # The seed meshes of febed
#
# febed's built-in geometries reproduce the beds of its seed papers. This demo builds them, checks the
# numbers the papers give, and draws them.
#
# * Seed 001 (Hamidouche et al. 2019), Table 2: the pseudo-2D bed, $80 \times 15 \times 250$ mm, in
#   structured hexahedra at three levels, with a centred *bottom wall* patch through which no gas enters.
# * Seed 000 (Wang et al. 2020), Table 2: the 2D bed, $90 \times 500$ mm, $18 \times 100$ cells of 5 mm.
#
# Run it with `.venv/bin/python demos/meshes/demo_meshes.py` (or under `mpirun -n 2`: rank 0 builds the
# meshes, every rank holds a part of each, rank 0 draws); the meshes and figures go to `demos/meshes/out/`.

from pathlib import Path

from mpi4py import MPI

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.collections import PolyCollection

from febed.meshing import PSEUDO2D_LEVELS, build_msh, facet_area, global_cell_count, load_msh, mesh_volume

OUT = Path(__file__).parent / "out"
comm = MPI.COMM_WORLD


def build(name: str, path: Path, **options):
    """Build a mesh with gmsh on rank 0 (gmsh is serial) and load it distributed over every rank."""
    error = None
    if comm.rank == 0:
        try:
            OUT.mkdir(exist_ok=True)
            build_msh(name, path, **options)
        except Exception as e:  # every rank raises it below, so that none waits for rank 0
            error = f"{type(e).__name__}: {e}"
    error = comm.bcast(error, root=0)
    if error:
        raise RuntimeError(f"building mesh {name} into {path}: {error}")
    return load_msh(path)


# ## Seed 001: three levels of the pseudo-2D bed
#
# Each level must have exactly the cell counts of Table 2, the bed volume, and the bottom-wall patch of
# Table 2 ($N_x \times N_y$ bottom cells), centred.

fig, axes = plt.subplots(1, 3, figsize=(12, 3.2))
for ax, (level, ((nx, ny, nz), (px, py))) in zip(axes, PSEUDO2D_LEVELS.items(), strict=True):
    md = build("pseudo2d", OUT / f"pseudo2d-{level}.msh", level=level)
    cells = global_cell_count(md)  # these numbers are summed over the ranks: every rank checks them
    patch = facet_area(md, "bottom_wall")
    if comm.rank == 0:
        print(f"pseudo2d {level:12s}: {cells:7d} cells (Table 2: {nx * ny * nz}), patch {patch * 1e6:.1f} mm^2")
    assert cells == nx * ny * nz
    assert abs(mesh_volume(md) / (0.08 * 0.015 * 0.25) - 1) < 1e-12
    assert abs(patch / (px * 0.08 / nx * py * 0.015 / ny) - 1) < 1e-12
    for tag, colour in (("inlet", "#9ecae1"), ("bottom_wall", "#de2d26")):
        quads = md.boundary_facet_coords([tag])[:, :, :2] * 1e3  # the whole mesh's facets, on every rank
        ax.add_collection(PolyCollection(quads, facecolors=colour, edgecolors="k", linewidths=0.3, label=tag))
    ax.set(xlim=(0, 80), ylim=(0, 15), aspect="equal", title=f"{level}: {nx}x{ny}x{nz}", xlabel="x [mm]")
axes[0].set_ylabel("y [mm]")
axes[0].legend(loc="upper left", fontsize=7)
fig.suptitle("Seed 001 bed, bottom face: gas inlet (blue) and bottom-wall patch (red)")
fig.tight_layout()
if comm.rank == 0:
    fig.savefig(OUT / "pseudo2d_bottom.png", dpi=120)

# ## Seed 000: the 2D bed, and the coarse pseudo-2D bed seen from the front

fig, (a, b) = plt.subplots(1, 2, figsize=(6, 8), gridspec_kw={"width_ratios": [1, 1]})
md = build("wang2d", OUT / "wang2d.msh")
assert global_cell_count(md) == 18 * 100
for tag, colour in (("inlet", "b"), ("walls", "k"), ("outlet", "g")):
    segs = md.boundary_facet_coords([tag])[:, :, :2] * 1e3
    for s in segs:
        a.plot(s[:, 0], s[:, 1], colour, lw=2)
a.set(aspect="equal", title="seed 000: 18 x 100 (inlet blue)", xlabel="x [mm]", ylabel="y [mm]")
md = load_msh(OUT / "pseudo2d-coarse.msh")
front = md.boundary_facet_coords(["walls"])
front = front[abs(front[:, :, 1]).max(axis=1) < 1e-12][:, :, [0, 2]] * 1e3
b.add_collection(PolyCollection(front, facecolors="none", edgecolors="k", linewidths=0.3))
b.set(xlim=(0, 80), ylim=(0, 250), aspect="equal", title="seed 001 coarse, y = 0", xlabel="x [mm]", ylabel="z [mm]")
fig.tight_layout()
if comm.rank == 0:
    fig.savefig(OUT / "beds.png", dpi=120)
    print(f"figures written to {OUT}/pseudo2d_bottom.png and {OUT}/beds.png")
