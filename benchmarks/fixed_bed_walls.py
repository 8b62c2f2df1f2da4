"""Gas through a frozen random packed bed between walls: the pressure gradient against Ergun on 3, 6, 12 cells.

A square duct 15 mm x 15 mm (the depth of seed 001's bed) holds a random packed bed of 10,000 glass beads of
1 mm (about 40 mm high), packed once by the DEM under gravity and then frozen (`particles.fixed`). Air flows
up through it at a superficial 0.3 m/s (below minimum fluidization). The duct is meshed with cubes of 5, 2.5
and 1.25 mm: 3, 6 and 12 cells across. The pressure gradient over the middle half of the bed is compared with
Ergun's at the void fraction of the same slab, measured from the particles (exact sphere-slab volumes).

A wall that holds its nodes at rest makes the gas of half a cell next to it stand still, so the bed resists
more the coarser the mesh (strict no-slip: 2.4x Ergun on 3 cells); the porous wall law (`wall_law =
"brinkman"`, the default) and slip walls should give Ergun on every mesh. The printed lines:

    fixed bed: dp/Ergun 3 cells X, 6 cells Y, 12 cells Z          (walls with the default wall law)
    fixed bed, strict no-slip walls: dp/Ergun ...                 (wall_law = "no_slip")
    fixed bed, slip walls: dp/Ergun ...

The gas receives the particles' pressure-gradient force as febed's default does, `coupling.pressure_gradient_reaction
= "nodal"` (it carries −ε∇p node by node); `--reaction projected` runs the three with the projected, filtered
reaction of seed 001 instead.

The bed is `tests/data/fixed-bed-15mm.npz` (made by this script with `--repack`; tests/gas/test_fixed_bed_walls.py
uses it). Serial, about a minute.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from pathlib import Path

import numpy as np

from febed.case import load_case
from febed.meshing import load_case_mesh
from febed.runs.probes import SectionAverage
from febed.schema import SCHEMA
from febed.solver import build_solver

ROOT = Path(__file__).resolve().parents[1]
BED = ROOT / "tests" / "data" / "fixed-bed-15mm.npz"
WIDTH, HEIGHT, D, RHO_P, COUNT = 0.015, 0.06, 1e-3, 2500.0, 10000
RHO_G, MU, U = 1.2, 1.8e-5, 0.3
CELLS = (3, 6, 12)
FILTER = 1
LOG = logging.getLogger("febed.bench.fixed_bed")
REACTION = SCHEMA["coupling"]["pressure_gradient_reaction"].default  # febed's default


def case_data(cells: int, walls: dict, out: Path, pack: bool = False, reaction: str = REACTION) -> dict:
    """The case of the duct meshed with `cells` cubes across, walls given as a [gas.boundary.walls] table."""
    return {
        "run": {"mode": "cfd-dem", "gravity": 9.81 if pack else 0.0, "end_time": 1.0},
        "mesh": {"builtin": "box", "extent": [WIDTH, WIDTH, 2 * HEIGHT if pack else HEIGHT], "size": WIDTH / cells},
        "gas": {
            "density": RHO_G,
            "viscosity": MU,
            "dt_max": 2e-4,
            "boundary": {
                "inlet": {"type": "inlet", "velocity": U},
                "walls": {"type": "wall", **walls},
                "outlet": {"type": "outlet"},
            },
        },
        "particles": {
            "diameter": D,
            "density": RHO_P,
            "count": COUNT,
            "insertion": "random",
            "bed_file": str(BED),
            "pack_if_missing": pack,
            "pack_restitution": 0.3,
            "settle_energy": 1e-10,
            "fixed": not pack,
        },
        "contact": {"stiffness": 1000.0, "friction_pp": 0.3, "friction_pw": 0.3},
        "coupling": {"drag": "gidaspow-blend", "filter_passes": FILTER, "pressure_gradient_reaction": reaction},
        "output": {"directory": str(out)},
    }


def ergun_gradient(eps: float) -> float:
    """Ergun's −dp/dz at superficial speed U through beads of D at void fraction eps [Pa/m]."""
    return 150 * MU * (1 - eps) ** 2 * U / (eps**3 * D**2) + 1.75 * RHO_G * (1 - eps) * U**2 / (eps**3 * D)


def slab_solid_fraction(pos: np.ndarray, radius: np.ndarray, z1: float, z2: float, area: float) -> float:
    """Solid volume fraction of the slab z1 < z < z2 from exact sphere-slab intersection volumes."""

    def below(z):  # volume of each sphere below the plane z: π (R h² − h³/3) with h = clip(z − z_c + R, 0, 2R)
        h = np.clip(z - pos[:, 2] + radius, 0.0, 2 * radius)
        return math.pi * (radius * h**2 - h**3 / 3)

    return float((below(z2) - below(z1)).sum()) / (area * (z2 - z1))


def pack(workdir: Path) -> None:
    """Pour and settle the bed with the DEM (gravity, damped contacts) and save it as BED."""
    BED.parent.mkdir(parents=True, exist_ok=True)
    if BED.exists():
        BED.unlink()
    case = load_case(data=case_data(6, {}, workdir / "pack", pack=True))
    md = load_case_mesh(case, cache_dir=workdir / "mesh")
    build_solver(case, md, LOG)
    data = dict(np.load(BED))  # the bed at rest, compressed: it is kept in the repository
    for name in ("vel", "omega", "force", "torque"):
        data[name] = np.zeros_like(data[name])
    np.savez_compressed(BED, **data)


def dp_ratio(
    cells: int, walls: dict, workdir: Path, steps: int = 1000, reaction: str = REACTION
) -> tuple[float, float]:
    """(−dp/dz over the middle half of the bed) / Ergun at the slab's measured ε, and that ε."""
    case = load_case(data=case_data(cells, walls, workdir / f"run{cells}", reaction=reaction))
    md = load_case_mesh(case, cache_dir=workdir / "mesh")
    s = build_solver(case, md, LOG)
    P = s.dem.particles
    n = P.n_owned
    top = float(np.quantile(P.pos[:n, 2] + 0.5 * P.diameter[:n], 0.99))
    z1, z2 = 0.25 * top, 0.75 * top
    lo, hi = np.zeros(3), np.array([WIDTH, WIDTH, HEIGHT])
    probes = [SectionAverage(s.ma, 2, z, lo, hi) for z in (z1, z2)]
    grads = []
    for _ in range(steps):
        s.step()
        grads.append((probes[0](s.gas.p) - probes[1](s.gas.p)) / (z2 - z1))
    if abs(grads[-1] / grads[-100] - 1) > 2e-3:  # the bed's pressure is settled; the freeboard still creeps
        raise RuntimeError(f"{cells} cells, walls {walls}: the pressure gradient is not steady after {steps} steps")
    eps = 1.0 - slab_solid_fraction(P.pos[:n], 0.5 * P.diameter[:n], z1, z2, WIDTH * WIDTH)
    return grads[-1] / ergun_gradient(eps), eps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repack", action="store_true", help="pack the bed again (overwrites tests/data's bed)")
    ap.add_argument("--cells", type=int, nargs="+", default=list(CELLS), help="cells across the 15 mm depth")
    ap.add_argument("--reaction", choices=("projected", "nodal"), default=REACTION,
                    help="coupling.pressure_gradient_reaction")  # fmt: skip
    args = ap.parse_args()
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if args.repack or not BED.exists():
            t0 = time.perf_counter()
            pack(work)
            print(f"packed {COUNT} beads into {BED} in {time.perf_counter() - t0:.0f} s")
        for label, walls in (
            ("", {}),
            (", strict no-slip walls", {"wall_law": "no_slip"}),
            (", slip walls", {"slip": True}),
        ):
            t0 = time.perf_counter()
            res = [dp_ratio(c, walls, work, reaction=args.reaction) for c in args.cells]
            cells = ", ".join(f"{c} cells {r:.3f}" for c, (r, _) in zip(args.cells, res, strict=True))
            eps = ", ".join(f"{e:.3f}" for _, e in res)
            print(f"fixed bed{label}: dp/Ergun {cells}  (slab eps {eps}; {time.perf_counter() - t0:.0f} s)")
            sys.stdout.flush()


if __name__ == "__main__":
    main()
