"""Coupling cost per particle and step: location, weights, projection, filter, ε, interpolation, drag.

Cases: the seed-000 2D bed (4,080 particles, 18 x 100 quadrilaterals, `build_msh("wang2d")`) and the
seed-001 intermediate pseudo-2D mesh (35 x 6 x 110 hexahedra) with 57,300 particles. Particles are spread
uniformly in the lower part of the bed and moved by a DEM-sized random step before each coupling step,
so the walk from the previous cell is what is timed (a cold start from unknown cells is timed once).

Run: /work/main/.venv/bin/python benchmarks/coupling.py [--steps 50]
"""

import argparse
import os
import platform
import tempfile
import time

from mpi4py import MPI

import numpy as np

from febed.coupling.drag import (
    RECORD_COLUMNS,
    RECORD_FP,
    RECORD_K,
    AtParticles,
    GasForces,
    NodalGas,
    drag_forces,
    gas_forces_kernel,
    get_drag_law,
)
from febed.coupling.exchange import Coupler
from febed.coupling.interpolate import interpolate
from febed.coupling.locate import locate
from febed.coupling.mesh_arrays import extract_mesh_arrays
from febed.coupling.projection import neighbour_filter, project, solid_fraction
from febed.coupling.weights import compute_weights
from febed.meshing import build_msh, load_msh


def machine() -> str:
    cpu = "?"
    with open("/proc/cpuinfo") as f:
        for line in f:
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    return f"{platform.node()}: nproc={os.cpu_count()}, CPU {cpu}"


def run_case(label, msh, n, box, d, steps, depth=1.0):
    md = load_msh(msh, comm=MPI.COMM_SELF)
    t0 = time.perf_counter()
    ma = extract_mesh_arrays(md.mesh, depth=depth)
    t_setup = time.perf_counter() - t0
    g = ma.gdim
    rng = np.random.default_rng(0)
    lo, hi = np.array(box[0]), np.array(box[1])
    x = lo + (hi - lo) * rng.random((n, 3))
    if g == 2:
        x[:, 2] = 0.0
    cell = np.full(n, -1, np.int32)
    ref = np.zeros((n, 3))
    status = np.zeros(n, np.int8)
    exitf = np.full(n, -1, np.int32)
    w = np.zeros((n, ma.cell_dofs.shape[1]))
    # compile + cold start
    locate(ma, x, cell.copy(), ref, status, exitf)
    t0 = time.perf_counter()
    locate(ma, x, cell, ref, status, exitf)
    t_cold = time.perf_counter() - t0
    vol = np.full(n, np.pi * d**3 / 6.0)
    d_orig = np.full(n, d)
    n_orig = np.ones(n)
    v = rng.normal(0.0, 0.3, (n, 3))
    if g == 2:
        v[:, 2] = 0.0
    u_nodes = rng.normal(0.0, 0.5, (ma.num_dofs, g))
    gp_nodes = rng.normal(0.0, 1e3, (ma.num_dofs, g))
    stages = dict.fromkeys(
        ["locate", "weights", "project (V, K, Kv)", "filter (1 pass)", "solid fraction", "interpolate u, eps, gradp",
         "drag (gidaspow-blend)", "fused interp + drag + F_P"], 0.0
    )  # fmt: skip
    step = 0.3 * 5e-5  # |v| dt for a DEM sub-step
    law = get_drag_law("gidaspow-blend")
    K, F_d, F_p, eps_f = np.empty(n), np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
    for it in range(steps + 1):
        x += step * rng.standard_normal((n, 3))
        if g == 2:
            x[:, 2] = 0.0
        np.clip(x, lo, hi, out=x)
        t = [time.perf_counter()]
        locate(ma, x, cell, ref, status, exitf)
        t.append(time.perf_counter())
        compute_weights(ma, ref, cell, w)
        t.append(time.perf_counter())
        vals = np.empty((n, 2 + g))
        vals[:, 0] = vol
        vals[:, 1] = 1e-5
        vals[:, 2:] = 1e-5 * v[:, :g]
        nodal = project(ma, cell, w, vals)
        t.append(time.perf_counter())
        filt = neighbour_filter(ma, nodal, 1)
        t.append(time.perf_counter())
        _, eps_nodes, _ = solid_fraction(ma, np.ascontiguousarray(filt[:, 0]), 0.3)
        t.append(time.perf_counter())
        u_p = interpolate(ma, cell, w, u_nodes)
        eps_p = interpolate(ma, cell, w, eps_nodes)
        interpolate(ma, cell, w, gp_nodes)
        t.append(time.perf_counter())
        u3 = np.zeros((n, 3))
        u3[:, :g] = u_p
        drag_forces("gidaspow-blend", eps_p, u3, v, d_orig, n_orig, 1.28, 1.7e-5)
        t.append(time.perf_counter())
        gas_forces_kernel(
            law,
            AtParticles(ma.cell_dofs, cell, w, v, d_orig, n_orig),
            NodalGas(u_nodes, eps_nodes, gp_nodes, 1.28, 1.7e-5, True),
            GasForces.of(K, F_d, F_p, eps_f),
        )
        t.append(time.perf_counter())
        if it == 0:
            continue  # compile
        for k, name in enumerate(stages):
            stages[name] += t[k + 1] - t[k]
    assert np.all(status == 0)
    fused = stages.pop("fused interp + drag + F_P")
    total = sum(stages.values())
    print(f"\n{label}: {ma.num_cells} cells, {ma.num_dofs} nodes, {n} particles, {steps} steps")
    print(f"  setup (extract arrays, once): {t_setup * 1e3:.1f} ms; cold location (cell unknown): "
          f"{t_cold / n * 1e6:.3f} us/particle")  # fmt: skip
    for name, s in stages.items():
        print(f"  {name:28s} {s / steps / n * 1e6:8.4f} us/particle/step  ({s / steps * 1e3:7.3f} ms/step)")
    print(f"  {'total':28s} {total / steps / n * 1e6:8.4f} us/particle/step  ({total / steps * 1e3:7.3f} ms/step)")
    per_sub = stages["locate"] + stages["weights"] + fused
    print(f"  per DEM sub-step (locate + weights + fused interp/drag/F_P): {per_sub / steps / n * 1e6:.4f} "
          f"us/particle  (fused kernel alone {fused / steps / n * 1e6:.4f})")  # fmt: skip
    production_path(ma, x, v, d, steps, lo, hi, u_nodes, gp_nodes)


def production_path(ma, x, v, d, steps, lo, hi, u_nodes, gp_nodes):
    """Time what the coupled solver calls per gas step, on the same particles.

    `Coupler.locate` (walk + weights in one pass), `Coupler.forces_into` (interpolation + drag + F_P writing
    the per-particle record) and `Coupler.project_to_gas` (projection + 1 filter pass + division by ΔV).
    """
    n, g = x.shape[0], ma.gdim
    cp = Coupler(ma, "gidaspow-blend", 1.28, 1.7e-5, filter_passes=1, void_floor=0.3)
    rng = np.random.default_rng(1)
    d_orig, n_orig = np.full(n, d), np.ones(n, dtype=np.int64)
    mass = 1150.0 * np.pi / 6 * d_orig**3
    record = np.zeros((n, RECORD_COLUMNS))
    eps_nodes = np.full(ma.num_dofs, 0.6)
    stages = dict.fromkeys(["Coupler.locate", "Coupler.forces_into", "Coupler.project_to_gas"], 0.0)
    for it in range(steps + 1):
        x += 0.3 * 5e-5 * rng.standard_normal((n, 3))
        if g == 2:
            x[:, 2] = 0.0
        np.clip(x, lo, hi, out=x)
        t = [time.perf_counter()]
        cp.locate(x)
        t.append(time.perf_counter())
        cp.forces_into(u_nodes, eps_nodes, gp_nodes, v, d_orig, n_orig, record, mass)
        t.append(time.perf_counter())
        cp.project_to_gas(d_orig, n_orig, record[:, RECORD_K], v, F_explicit=record[:, RECORD_FP])
        t.append(time.perf_counter())
        if it == 0:
            continue  # compile
        for k, name in enumerate(stages):
            stages[name] += t[k + 1] - t[k]
    print("  production path (febed.solver per gas step):")
    for name, s in stages.items():
        print(f"  {name:28s} {s / steps / n * 1e6:8.4f} us/particle/step  ({s / steps * 1e3:7.3f} ms/step)")
    total = sum(stages.values())
    print(f"  {'total':28s} {total / steps / n * 1e6:8.4f} us/particle/step  ({total / steps * 1e3:7.3f} ms/step)")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=50)
    args = ap.parse_args()
    print(machine())
    with tempfile.TemporaryDirectory() as tmp:
        w2 = build_msh("wang2d", out=os.path.join(tmp, "wang2d.msh"))
        run_case("seed-000 2D bed (wang2d, quadrilaterals)", w2, 4080, ([0, 0, 0], [0.09, 0.2, 0]), 1.5e-3,
                 args.steps, depth=1.5e-3)  # fmt: skip
        p3 = build_msh("pseudo2d", level="intermediate", out=os.path.join(tmp, "p2d.msh"))
        run_case("seed-001 intermediate mesh (pseudo2d, hexahedra)", p3, 57300,
                 ([0, 0, 0], [0.08, 0.015, 0.06]), 1e-3, max(args.steps // 5, 5))  # fmt: skip


if __name__ == "__main__":
    main()
