"""Driving a coupled run: output and probe intervals, progress, the probe quantities.

`run_coupled` builds the `CoupledSolver` of a case and calls its `step()` until the end time; between
steps it writes

* probes (`probes.csv`, every `[output] probe_interval`): time, gas step, DEM sub-steps per gas step,
  particle count, particles removed at the outlet, particle kinetic energy, bed height, cross-section
  averaged pressures, the bed pressure drop, gas CFL, Poisson iterations, gas mass balance, clipped nodes
  and the wall-time split DEM / coupling / gas / output (cumulative seconds);
* fields (`fields.xdmf`: u, p, ε, α_p) every `field_interval` and particles (`particles/*.vtp` + `.pvd`)
  every `particle_interval`, for ParaView;
* a progress line every `progress_interval` wall seconds (console and `febed.log`).

Definitions:

* **Bed height**: the height (along gravity) below which `[output] bed_fraction` of the particle volume lies.
* **Cross-section averaged pressure** at height z: mean of p over a uniform grid of sample points filling
  the mesh's cross-section at z (midpoint rule; points outside the mesh are dropped).
* **Bed pressure drop** `dp_bed`: ⟨p⟩ at the bottom of the mesh minus ⟨p⟩ at the top, less the weight of
  the gas column ρ_g g H, i.e. the part of the pressure drop that carries the particles.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed.coupling.exchange import solid_volume
from febed.coupling.interpolate import interpolate
from febed.coupling.locate import FOUND, locate
from febed.coupling.weights import compute_weights
from febed.io.probes import ProbeFile
from febed.solver import RunFailure, build_solver


class SectionAverage:
    """Cross-section average of a nodal field at a fixed height, from sample points located once."""

    def __init__(self, ma, axis: int, height: float, lo: np.ndarray, hi: np.ndarray, per_dim: int = 40):
        """Sample points on a uniform grid over the box [lo, hi] of the cross-section at `height`."""
        gdim = ma.gdim
        others = [a for a in range(gdim) if a != axis]
        axes = [lo[a] + (np.arange(per_dim) + 0.5) * (hi[a] - lo[a]) / per_dim for a in others]
        grid = np.meshgrid(*axes, indexing="ij")
        pts = np.zeros((grid[0].size, 3))
        for a, g in zip(others, grid, strict=True):
            pts[:, a] = g.ravel()
        pts[:, axis] = height
        cell = np.full(pts.shape[0], -1, dtype=np.int32)
        cell, ref, status, _, _ = locate(ma, pts, cell)
        keep = (status == FOUND) & (cell < ma.num_owned_cells)
        self.ma = ma
        self.cell = np.ascontiguousarray(cell[keep])
        self.w = compute_weights(ma, np.ascontiguousarray(ref[keep]), self.cell)
        self.count = ma.comm.allreduce(int(keep.sum())) if ma.comm is not None else int(keep.sum())
        if self.count == 0:
            raise ValueError(f"probe height {height} m lies outside the mesh")

    def __call__(self, nodal: np.ndarray) -> float:
        """The average of nodal field `nodal` (nd,) over the section (collective)."""
        local = float(interpolate(self.ma, self.cell, self.w, nodal).sum())
        total = self.ma.comm.allreduce(local) if self.ma.comm is not None else local
        return total / self.count


def bed_height(heights: np.ndarray, volumes: np.ndarray, fraction: float, comm=MPI.COMM_WORLD) -> float:
    """Height below which `fraction` of the particle volume lies (m); NaN without particles (collective)."""
    h = np.concatenate(comm.allgather(np.asarray(heights, dtype=float)))
    v = np.concatenate(comm.allgather(np.asarray(volumes, dtype=float)))
    if h.size == 0:
        return math.nan
    order = np.argsort(h, kind="stable")
    cum = np.cumsum(v[order])
    k = int(np.searchsorted(cum, fraction * cum[-1]))
    return float(h[order][min(k, h.size - 1)])


class CoupledRun:
    """A coupled run with its output: `advance_to(t)` steps the solver, writing probes and output."""

    def __init__(self, case, outdir: Path, log, comm=MPI.COMM_WORLD, md=None):
        """Build the mesh (unless given), the coupled solver, the probes and the writers."""
        from febed.meshing import load_case_mesh

        self.case = case
        self.outdir = Path(outdir)
        self.log = log
        self.comm = comm
        self.md = md if md is not None else load_case_mesh(case, comm, cache_dir=self.outdir / "mesh")
        self.solver = s = build_solver(case, self.md, log)
        self.axis = 1 if self.md.gdim == 2 else 2
        x = self.md.mesh.geometry.x
        lo = np.minimum.reduce(comm.allgather(x.min(axis=0)))
        hi = np.maximum.reduce(comm.allgather(x.max(axis=0)))
        self.height = hi[self.axis] - lo[self.axis]
        eps_h = 1e-9 * self.height
        self.sections = {
            "bottom": SectionAverage(s.ma, self.axis, lo[self.axis] + eps_h, lo, hi),
            "top": SectionAverage(s.ma, self.axis, hi[self.axis] - eps_h, lo, hi),
        }
        for z in case.output.probe_heights:
            self.sections[f"{z:g}"] = SectionAverage(s.ma, self.axis, z, lo, hi)
        heights = [f"p_{name}" for name in self.sections]
        self.columns = [
            "step", "dt", "n_sub", "particles", "left_outlet", "kinetic_energy", "bed_height", "dp_bed", *heights,
            "cfl", "poisson_iterations", "gas_inflow", "gas_mass_imbalance", "clipped_nodes",
            "wall_dem", "wall_coupling", "wall_gas", "wall_output",
        ]  # fmt: skip
        self.probes = ProbeFile(self.outdir / "probes.csv", self.columns, comm)
        self._writers()
        self.next = {"probe": 0.0, "field": 0.0, "particle": 0.0}  # next output time of each kind
        self.last = {"probe": None, "field": None, "particle": None}  # time of the last one written
        self._wall0 = self._last_progress = time.perf_counter()
        self._t0 = s.t

    def _writers(self) -> None:
        import dolfinx.fem

        from febed.io.fields import FieldWriter
        from febed.io.particles import ParticleWriter

        s = self.solver
        self.alpha = dolfinx.fem.Function(s.gas.Q)
        funcs = dict(s.gas.functions())
        funcs["alpha_p"] = self.alpha
        self.fields = FieldWriter(self.outdir / "fields.xdmf", self.md.mesh, funcs, self.comm)
        self.particles = ParticleWriter(self.outdir / "particles", comm=self.comm)

    # ------------------------------------------------------------------------------------------ probes
    def probe_values(self) -> dict[str, float]:
        """Every probe quantity now (collective)."""
        s = self.solver
        P = s.dem.particles
        n = P.n_owned
        vol = solid_volume(P.diameter[:n], 1.0)  # a parcel's volume is that of its sphere
        p = s.gas.p
        sec = {name: f(p) for name, f in self.sections.items()}
        rho_g, g = self.case.gas.density, self.case.run.gravity
        info = s.last_gas
        vals = {
            "step": s.steps,
            "dt": info.dt if info else 0.0,
            "n_sub": s.n_sub,
            "particles": self.comm.allreduce(n),
            "left_outlet": self.comm.allreduce(s.left_outlet),
            "kinetic_energy": self.comm.allreduce(float(P.kinetic_energy())),
            "bed_height": bed_height(P.pos[:n, self.axis], vol, self.case.output.bed_fraction, self.comm),
            "dp_bed": sec["bottom"] - sec["top"] - rho_g * g * self.height,
            "cfl": info.cfl if info else 0.0,
            "poisson_iterations": info.poisson_iterations if info else 0,
            "gas_inflow": rho_g * info.inflow if info else 0.0,
            "gas_mass_imbalance": info.mass_imbalance if info else 0.0,
            "clipped_nodes": s.clipped,
            **s.timers.as_dict(),
        }
        vals.update({f"p_{k}": v for k, v in sec.items()})
        return vals

    def check_health(self) -> None:
        """Stop with a RunFailure naming what is not finite, where and when."""
        s = self.solver
        P = s.dem.particles
        n = P.n_owned
        bad = ~np.isfinite(P.pos[:n]).all(axis=1) | ~np.isfinite(P.vel[:n]).all(axis=1)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise RunFailure(f"particle {int(P.gid[k])} has a non-finite position/velocity at t = {s.t:.6g} s")
        for name, a in (("u", s.gas.u), ("p", s.gas.p)):
            if not np.isfinite(a).all():
                k = int(np.flatnonzero(~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1))[0])
                raise RunFailure(f"gas {name} is not finite at node {s.ma.x_dofs[k].tolist()} at t = {s.t:.6g} s")

    # ------------------------------------------------------------------------------------------ output
    def output(self, force: bool = False) -> None:
        """Write whatever is due (probes, fields, particles); `force` writes all of them now."""
        s = self.solver
        o = self.case.output
        t0 = time.perf_counter()
        tol = 1e-9 * max(s.last_gas.dt if s.last_gas else 1.0, 1e-12)
        due = {k: (force and self.last[k] != s.t) or s.t >= self.next[k] - tol for k in self.next}
        if due["probe"]:
            self.check_health()
            self.probes.write(s.t, self.probe_values())
        if due["field"]:
            self.alpha.x.array[:] = s.alpha
            self.fields.write(s.t)
        if due["particle"]:
            self.particles.write(s.t, s.dem.particles)
        for kind in self.next:
            if due[kind]:
                self.last[kind] = s.t
                self.next[kind] = s.t + getattr(o, f"{kind}_interval")
        s.timers.output += time.perf_counter() - t0

    def progress(self, end: float, force: bool = False) -> None:
        """Log a progress line if `progress_interval` wall seconds have passed (or `force`)."""
        now = time.perf_counter()
        if not force and now - self._last_progress < self.case.output.progress_interval:
            return
        self._last_progress = now
        s = self.solver
        done = s.t - self._t0
        wall = now - self._wall0
        rate = wall / done if done > 0 else math.nan
        eta = rate * (end - s.t) if done > 0 else math.nan
        n = self.comm.allreduce(s.dem.particles.n_owned)
        self.log.info(
            f"t = {s.t:.5f} / {end:g} s  step {s.steps}  {n} particles  {s.n_sub} sub-steps/step  "
            f"{rate / 60:.2f} min wall per simulated s  ETA {_clock(eta)}"
        )

    def advance_to(self, end: float) -> None:
        """Step until `end` (s), writing output and progress on the way."""
        s = self.solver
        self.output(force=s.steps == 0)
        while s.t < end * (1 - 1e-12):
            s.step()
            self.output()
            self.progress(end)
        self.progress(end, force=True)

    def close(self) -> None:
        """Write the last output and close the files."""
        self.output(force=True)
        self.probes.close()
        self.fields.close()


def _clock(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    seconds = int(seconds)
    return f"{seconds // 3600}h{seconds // 60 % 60:02d}m{seconds % 60:02d}s"


def run_coupled(case, outdir, log, comm=MPI.COMM_WORLD):
    """Run a coupled case to `run.end_time` (called by `febed run`); returns the CoupledRun."""
    run = CoupledRun(case, Path(outdir), log, comm)
    s = run.solver
    log.info(
        f"cfd-dem: {comm.allreduce(s.dem.particles.n_owned)} particles, {s.ma.num_dofs} nodes, "
        f"drag {case.coupling.drag}, DEM step {s.dem.dt:.3e} s, to t = {case.run.end_time:g} s"
    )
    try:
        run.advance_to(case.run.end_time)
    finally:
        run.close()
    t = s.timers
    total = t.dem + t.coupling + t.gas + t.output
    log.info(
        f"done: {s.steps} gas steps to t = {s.t:.5f} s in {total:.1f} s "
        f"(DEM {t.dem:.1f} s, coupling {t.coupling:.1f} s, gas {t.gas:.1f} s, output {t.output:.1f} s); "
        f"{s.left_outlet} particles left through the outlet; probes in {run.outdir / 'probes.csv'}"
    )
    return run
