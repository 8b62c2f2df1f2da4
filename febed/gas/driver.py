"""Gas-only runs (`run.mode = "gas"`): the VANS solver with a prescribed void fraction, to run.end_time.

The void fraction is the uniform `gas.void_fraction`, or (Python API) a callable eps(x, t) of the node
coordinates x (n, 3) and the time t returning (n,) values in (0, 1]. Fields u, p, ε are written as XDMF
(`fields.xdmf` in the output folder) every `output.field_interval`, and a progress line is logged every
`output.progress_interval` seconds of wall-clock time.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed.gas.vans import VANSSolver
from febed.io.fields import FieldWriter


def run(case, outdir, log: logging.Logger | None = None, eps=None, mesh_data=None) -> VANSSolver:
    """Run a gas-only case to `run.end_time`; write fields to `outdir`; return the solver at the end."""
    from febed.meshing import load_case_mesh

    log = log or logging.getLogger("febed")
    outdir = Path(outdir)
    md = mesh_data if mesh_data is not None else load_case_mesh(case, MPI.COMM_WORLD, cache_dir=outdir / "mesh")
    if eps is not None and not callable(eps):
        raise ValueError("eps must be a callable eps(x, t) -> (n,) array, or None for gas.void_fraction")
    eps_at = eps if eps is not None else (lambda x, t: np.full(x.shape[0], case.gas.void_fraction))
    solver = VANSSolver.from_case(case, md)
    x = solver.x
    if eps is not None:
        solver.set_void_fraction(eps_at(x, 0.0))
    end, every = case.run.end_time, case.output.field_interval
    log.info(
        f"gas: {solver.comm.allreduce(solver.n_owned)} nodes, LES {case.gas.les}, "
        f"boundaries {', '.join(f'{n}={s.type}' for n, s in solver.bc.specs.items())}"
    )
    writer = FieldWriter(outdir / "fields.xdmf", md.mesh, solver.functions(), md.comm)
    writer.write(0.0)
    next_out, n_steps = every, 0
    wall0 = last = time.perf_counter()
    while solver.t < end * (1 - 1e-12):
        dt = solver.compute_dt()
        stop = min(end, next_out)
        if solver.t + dt > stop - 1e-9 * dt:  # land exactly on the next output / end time
            dt = stop - solver.t
        info = solver.step(dt, eps=eps_at(x, solver.t + dt) if eps is not None else None)
        n_steps += 1
        if solver.t >= next_out * (1 - 1e-12):
            writer.write(solver.t)
            next_out += every
        now = time.perf_counter()
        if now - last >= case.output.progress_interval or solver.t >= end * (1 - 1e-12):
            last = now
            log.info(
                f"t = {solver.t:.5g} s  dt = {dt:.3g} s  CFL {info.cfl:.3f}  Poisson its {info.poisson_iterations}  "
                f"mass imbalance {info.mass_imbalance:.3g} kg/s (inflow {case.gas.density * info.inflow:.4g} kg/s)  "
                f"{1e3 * (now - wall0) / n_steps:.1f} ms/step"
            )
    writer.close()
    log.info(f"gas: {n_steps} steps to t = {solver.t:.5g} s; fields in {writer.path}")
    return solver
