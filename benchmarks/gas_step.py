"""One gas step on a seed-001 pseudo-2D hex mesh (default the intermediate one, ~28,000 nodes), bed-like ε.

`--mesh wang2d` times it instead on seed 000's 2D bed (1,919 nodes, 18 x 100 quadrilaterals), where the step's
fixed cost (solver calls, Python around the kernels) rather than the node count sets the time.

Run serially or with `mpirun -n 2`; PETSc options through PETSC_OPTIONS, e.g.
PETSC_OPTIONS="-febed_pressure_ksp_type preonly -febed_pressure_pc_type cholesky
-febed_pressure_pc_factor_mat_solver_type mumps" for a direct pressure solve.
Prints ms per step and the breakdown by sub-step (rank 0's timers,
max over ranks of the total). The ε field mimics a bubbling bed: ε ≈ 0.42 below 0.1 m with two bubbles rising
at 0.5 m/s, 1 above, smoothed; K from Ergun/Wen-Yu-like magnitudes with K·v̄ of random particle velocities.

`--solver-counts FILE.json` records, per rank and gas step, what the pressure solver exchanges (PETSc's own
counts of messages, bytes and reductions in its solves and preconditioner set-ups) for the load model of
`scaling_projection.py`; these are counts, not times, so any rank count can be run oversubscribed:
`mpirun -n 16 --oversubscribe python benchmarks/gas_step.py --warmup 10 --steps 5 --solver-counts F.json`.
"""

import json
import os
import platform
import tempfile
import time

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np

from febed.gas import BoundarySpec, VANSParameters, VANSSolver
from febed.meshing import build_msh, load_msh

comm = MPI.COMM_WORLD
# The pressure solver's PETSc events: its solves and its preconditioner set-ups (febed calls KSPSetUp itself,
# so the two do not nest). PETSc counts each message at both ends (numMessages, messageLength): halved below.
SOLVER_EVENTS = ("KSPSolve", "PCSetUp")


def solver_counts() -> np.ndarray:
    """This rank's PETSc totals so far for the pressure solver: flops, messages sent, bytes sent, reductions."""
    total = np.zeros(4)
    for name in SOLVER_EVENTS:
        info = PETSc.Log.Event(name).getPerfInfo()
        total += (info["flops"], info["numMessages"] / 2, info["messageLength"] / 2, info["numReductions"])
    return total


def write_solver_counts(path: str, level: str, counts: np.ndarray, steps: int, nodes: int) -> None:
    """Gather every rank's solver counts per gas step and add them to the JSON file `path` under (level, P)."""
    rows = comm.gather(counts / steps, root=0)
    if comm.rank != 0:
        return
    data = {}
    if os.path.exists(path):
        with open(path) as f:
            data = json.load(f)
    a = np.array(rows)
    data.setdefault(level, {})[str(comm.size)] = {
        "nodes": nodes,
        "steps": steps,
        "flops": a[:, 0].tolist(),
        "messages": a[:, 1].tolist(),
        "bytes": a[:, 2].tolist(),
        "reductions": a[:, 3].tolist(),
    }
    tmp = f"{path}.tmp"
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1)
    os.replace(tmp, path)
    print(
        f"pressure solver per gas step, max over {comm.size} rank(s): {a[:, 1].max():.0f} messages, "
        f"{a[:, 2].max() / 1e3:.1f} kB, {a[:, 3].max():.0f} reductions; "
        f"flops max/mean {a[:, 0].max() / a[:, 0].mean():.3f}"
    )


def machine():
    model = "?"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{platform.node()}: nproc {os.cpu_count()}, {model}"


def bed_eps(x, t=0.0, vertical=2):
    """A bubbling-bed-like void fraction: packed (0.42) below 0.1 m, freeboard above, two rising bubbles."""
    z = x[:, vertical]
    eps = 0.42 + 0.58 / (1 + np.exp(-(z - 0.1) / 0.004))
    for cx, cz, r in ((0.03, 0.03, 0.008), (0.055, 0.06, 0.01)):
        zc = cz + 0.5 * t  # bubbles rise at 0.5 m/s
        eps = np.maximum(eps, 0.42 + 0.5 * np.exp(-((x[:, 0] - cx) ** 2 + (z - zc) ** 2) / r**2))
    return np.minimum(eps, 1.0)


def main(
    warmup=100, steps=20, mass_tolerance=1e-6, level="intermediate", drag_weighted=True, mesh="pseudo2d", counts=None
):
    if counts:
        PETSc.Log.begin()
    path = None
    if mesh == "wang2d":
        level = "default"
    if comm.rank == 0:
        path = os.path.join(tempfile.gettempdir(), f"febed-bench-{mesh}-{level}.msh")
        if not os.path.exists(path):
            build_msh(mesh, out=path, **({"level": level} if mesh == "pseudo2d" else {}))
    path = comm.bcast(path, root=0)
    md = load_msh(path, comm)
    if mesh == "pseudo2d":
        bcs = {
            "inlet": BoundarySpec("inlet", velocity=1.2, cross_section_tags=("bottom_wall",)),
            "bottom_wall": BoundarySpec("wall"),
            "walls": BoundarySpec("wall"),
            "outlet": BoundarySpec("outlet"),
        }
    else:  # seed 000's bed: inlet over the whole bottom at 0.9 m/s
        bcs = {
            "inlet": BoundarySpec("inlet", velocity=0.9),
            "walls": BoundarySpec("wall"),
            "outlet": BoundarySpec("outlet"),
        }
    t0 = time.perf_counter()
    s = VANSSolver(
        md,
        VANSParameters(
            gravity=9.81, boundaries=bcs, mass_tolerance=mass_tolerance, drag_weighted_projection=drag_weighted
        ),
        eps=1.0,
    )
    setup = time.perf_counter() - t0
    vertical = s.gdim - 1
    eps = bed_eps(s.x, vertical=vertical)
    s.set_void_fraction(eps)
    rng = np.random.default_rng(comm.rank)
    d, rho = 1e-3, 1.2
    K = 150 * 1.8e-5 * (1 - eps) ** 2 / (eps**2 * d**2) + 1.75 * rho * (1 - eps) * 1.0 / (eps * d)
    vbar = 0.1 * (rng.random((s.n_local, s.gdim)) - 0.5)
    vbar[eps > 0.99] = 0.0
    for k in range(warmup + steps):
        if k == warmup:
            comm.barrier()
            t_start = time.perf_counter()
            c_start = time.process_time()
            acc = {}
            counts0 = solver_counts() if counts else None
        dt = s.compute_dt()
        e = bed_eps(s.x, s.t + dt, vertical)
        info = s.step(dt, eps=e, K=K, Kv=K[:, None] * vbar)
        if k >= warmup:
            for name, v in info.timings.items():
                acc[name] = acc.get(name, 0.0) + v
    comm.barrier()
    total = comm.allreduce(time.perf_counter() - t_start, op=MPI.MAX) / steps
    cpu = comm.allreduce(time.process_time() - c_start, op=MPI.MAX) / steps
    nodes = comm.allreduce(s.n_owned)
    if counts:
        write_solver_counts(counts, level if mesh == "pseudo2d" else mesh, solver_counts() - counts0, steps, nodes)
    if comm.rank == 0:
        print(machine())
        projection = "drag-weighted" if drag_weighted else "constant-Laplacian"
        print(f"{mesh} {level}: {nodes} nodes, {comm.size} rank(s), {projection} projection, setup {setup:.1f} s")
        print(f"gas step: {1e3 * total:.2f} ms/step wall, {1e3 * cpu:.2f} ms CPU ({steps} steps after {warmup})")
        print(f"  load average {os.getloadavg()[0]:.2f} (other jobs on the machine inflate wall times)")
        for name, v in acc.items():
            print(f"  {name:12s} {1e3 * v / steps:7.2f} ms")
        other = total - sum(acc.values()) / steps
        print(f"  {'dt+records':12s} {1e3 * other:7.2f} ms")
        print(
            f"  last step: dt {info.dt:.3g} s, CFL {info.cfl:.3f}, Poisson its {info.poisson_iterations}, "
            f"mass imbalance / inflow {info.mass_imbalance / (rho * info.inflow):.2e}"
        )


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--warmup", type=int, default=100, help="steps before timing (the flow develops from rest)")
    ap.add_argument("--steps", type=int, default=20, help="timed steps")
    ap.add_argument("--mass-tolerance", type=float, default=1e-6, help="VANSParameters.mass_tolerance")
    ap.add_argument(
        "--level",
        default="intermediate",
        choices=("coarse", "intermediate", "fine"),
        help="seed 001's mesh (Table 2): coarse ~7,000, intermediate ~28,000, fine ~204,000 nodes",
    )
    ap.add_argument(
        "--mesh",
        default="pseudo2d",
        choices=("pseudo2d", "wang2d"),
        help="seed 001's pseudo-2D bed (at --level) or seed 000's 2D bed (1,919 nodes)",
    )
    ap.add_argument(
        "--drag-weighted",
        type=int,
        choices=(0, 1),
        default=1,
        help="gas.drag_weighted_projection (default 1, febed's default; 0: the constant Laplacian)",
    )
    ap.add_argument(
        "--solver-counts",
        metavar="FILE.json",
        help="add the pressure solver's PETSc counts per gas step and rank (messages, bytes, reductions, flops) "
        "to this file, under the mesh level and the rank count (scaling_projection.py reads them)",
    )
    a = ap.parse_args()
    main(a.warmup, a.steps, a.mass_tolerance, a.level, bool(a.drag_weighted), a.mesh, a.solver_counts)
