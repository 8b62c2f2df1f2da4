"""Pre-flight: a validated case checked against its mesh and bed file, and its cost estimated, before it runs.

`febed check` and `febed run` call `preflight` after the case file has been validated (`febed.case`) and
before the output folder is touched. It

* loads the mesh (a built-in one is built in a temporary folder) and, when the case has any
  `[gas.boundary.<tag>]` table, requires one for every facet tag of the mesh: a tag without a table is an
  error naming it and the allowed types, never silently a wall;
* loads the bed file (`[particles] bed_file`, when it exists; `febed.dem.insertion.load_bed` refuses a file
  that is not a bed, naming it) and compares its particles with the case: their number (when `count` or
  `bed_mass` is given), diameter and density, as the case's `[coarse_grain]` would insert them, to a relative
  `BED_RTOL`. A mismatch is an error, unless `bed_authoritative = true`: the case then takes the bed's values,
  each change logged and written so to the resolved case;
* requires every bed particle to lie inside the mesh, and an insertion region that meets the mesh;
* estimates the run (`Estimate`) and refuses an absurd one unless forced (`febed run --force`):

  - the DEM step is T_C / dt_factor of the stiffest contact and lightest particles (`critical_time`), the
    gas step the smallest of `dt_max` and the CFL and Fourier limits on the mean cell size. The CFL limit is
    taken at the fastest inlet velocity U_f, or, in a fluidized bed (particles, and U_f above the minimum
    fluidization velocity of Wen and Yu), at `BED_GAS_SPEED` U_f: bubbles and jets carry gas several times
    faster than U_f, and that speed sets the gas step of a bubbling bed on a fine mesh. More than
    `MAX_SUBSTEPS` DEM sub-steps per gas step is refused (a stiffness typo: one gas step would take hours, and
    a stop signal waits for the step to end);
  - wall time: particles x DEM steps x `DEM_SECONDS` plus nodes x gas steps x `GAS_SECONDS`, over the
    ranks (one-core throughputs measured on the seed beds); with `gas.convection_substeps` the estimated gas
    step spans m convective steps, and each extra explicit sub-step adds `PREDICTOR_SHARE` of a gas step;
    refused when even `FAST` times faster it would exceed `MAX_WALL_DAYS`;
  - memory: `RANK_BYTES` per process, `PARTICLE_BYTES` per particle and `NODE_BYTES` per mesh node (the peak
    resident memory of the seed cases), plus `WHOLE_MESH_BYTES` per node
    on every rank of a coupled run whose particles are shared by work (each rank holds the whole mesh's
    coupling arrays); refused when a quarter of it exceeds the physical memory of the ranks' machine;
  - an inlet velocity whose CFL step on the mean cell is below `dt_min` (the gas step could not follow it),
    and more particles than febed's global ids can number (2^31), are refused even with --force.

Every problem found is reported together (`PreflightError`, a `CaseError`), each naming the key or file and
what is allowed.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed.case import Case, CaseError, Section
from febed.coarse import setup as coarse
from febed.meshing import MeshError, load_case_mesh
from febed.schema import BOUNDARY

BED_RTOL = 1e-6  # bed diameters and densities match the case's to this relative tolerance
MAX_SUBSTEPS = 100_000  # DEM sub-steps per gas step (seed cases: 10-500)
MAX_WALL_DAYS = 30.0  # refuse when the optimistic wall-time estimate exceeds this
# One core: wall seconds per particle per DEM step, coupling included (measured 0.93e-7 on C2's bubbling bed, 1.0e-7
# on C1, 1.7e-7 on the wang2d bed), and per mesh node per gas step (1.1e-6 on C2, hexahedra; 0.9e-6 on C3 with
# one convective sub-step; 0.3e-6 on the wang2d quadrilaterals). The estimate then gives the wang2d bed's DEM (tm1)
# 0.94 and on 2 ranks C1 0.88, C2 1.09 and C3 0.83-0.86 of their measured wall times; it assumes perfect scaling,
# and 2-rank runs are at 80-85 % of it.
DEM_SECONDS = 1.3e-7
GAS_SECONDS = 1.1e-6
# The explicit predictor's share of a gas step, paid again by each extra convective sub-step (seed 001's C3 on
# 2 ranks: 0.28 of the gas with one sub-step; 0.50 with 3.2 sub-steps on average, k = 4)
PREDICTOR_SHARE = 0.3
FAST = 5.0  # the optimistic estimate assumes throughputs this many times the measured ones
# The fastest gas speed of a fluidized bed over its U_f, which limits the gas step by the CFL number: in febed's
# pseudo-2D beds (seed 001, U_f = 1.2 m/s, 2.2 U_mf) the median over 0.1-6 s of max|u| was 3.4, 4.4 and 5.8 U_f on
# the coarse, intermediate and fine meshes (faster jets resolved on finer cells).
BED_GAS_SPEED = 5.0
# Peak memory: `RANK_BYTES` per process (Python, DOLFINx, PETSc, the compiled kernels and forms), `NODE_BYTES` per
# mesh node (gas fields, nodal operators, matrices, preconditioners; hexahedra) and `PARTICLE_BYTES` per particle
# (arrays, neighbour lists, coupling records, output copies). Peak resident memory measured per process: the wang2d
# bed 280 MB; C1 416 MB and C2 623 MB serially; C2 490-510 MB and C3 1.42-1.46 GB on each of 2 ranks; so about
# 10 kB per node, 1 kB per particle and 0.3 GB per process (this estimate, for the whole run: 0.32, 0.40, 0.64,
# 0.94 and 2.70 GB).
RANK_BYTES = 300e6
PARTICLE_BYTES = 1000.0
NODE_BYTES = 10_000.0
WHOLE_MESH_BYTES = 1000.0  # per node and rank with particle_partition = "work" (hexahedra 0.37 kB, tetrahedra more)
GAS_MODES = ("cfd-dem", "gas")
DEM_MODES = ("cfd-dem", "dem", "one-way")


class PreflightError(CaseError):
    """A case that its mesh, bed or estimate refuses; `problems` lists every message."""


@dataclass
class Estimate:
    """What a run will take, from the case, its mesh and its bed (see the module docstring)."""

    particles: int = 0
    nodes: int = 0
    cells: int = 0
    ranks: int = 1
    dt_dem: float | None = None  # s
    dt_gas: float | None = None  # s
    bed_cfl: bool = False  # the gas step is the CFL limit at a fluidized bed's gas speed (BED_GAS_SPEED U_f)
    convective: int = 1  # explicit predictor sub-steps per gas step (gas.convection_substeps, as the step needs)
    gas_steps: float = 0.0
    dem_steps: float = 0.0
    memory: float = 0.0  # bytes, the whole run
    wall: float = 0.0  # s

    @property
    def sub_steps(self) -> float:
        """DEM sub-steps per gas step (0 without gas or particles)."""
        if not self.dt_gas or not self.dt_dem:
            return 0.0
        return math.ceil(self.dt_gas / self.dt_dem * (1 - 1e-12))

    def text(self) -> str:
        """One line for the log and `febed check`."""
        parts = [f"{self.particles} particles" if self.particles else "no particles", f"{self.nodes} mesh nodes"]
        if self.dt_gas:
            where = f" (CFL at a fluidized bed's gas speed, {BED_GAS_SPEED:g} U_f)" if self.bed_cfl else ""
            parts.append(f"~{_num(self.gas_steps)} gas steps of ~{self.dt_gas:.3g} s{where}")
            if self.convective > 1:
                parts.append(f"{self.convective} convective sub-steps per gas step")
        if self.dt_dem:
            parts.append(f"DEM step {self.dt_dem:.3g} s")
            if self.dt_gas:
                parts.append(f"{_num(self.sub_steps)} DEM sub-steps per gas step")
            else:
                parts.append(f"~{_num(self.dem_steps)} DEM steps")
        parts.append(f"memory ~{_bytes(self.memory)}")
        parts.append(f"wall time ~{_duration(self.wall)} on {self.ranks} rank(s)")
        return "estimate: " + ", ".join(parts)


@dataclass
class Preflight:
    """The outcome of `preflight`: the case to run (reconciled with its bed), notes for the log, the estimate."""

    case: Case
    notes: list[str] = field(default_factory=list)
    estimate: Estimate = field(default_factory=Estimate)
    mesh: dict = field(default_factory=dict)  # `mesh_identity` of the case's mesh
    tags: list[str] = field(default_factory=list)  # the mesh's facet tags
    bed_particles: int | None = None  # particles in the existing bed file, if any


def preflight(case: Case, comm=MPI.COMM_WORLD, force: bool = False) -> Preflight:
    """Check `case` against its mesh and bed and estimate its cost; raise PreflightError listing every problem.

    `force` turns the refusals of an absurd estimate (sub-steps, wall time, memory) into notes; the other
    problems remain errors. Collective: every rank loads the mesh and the bed and reaches the same verdict.
    """
    problems: list[str] = []
    with tempfile.TemporaryDirectory(prefix="febed-preflight-") as tmp:
        try:
            md = load_case_mesh(case, comm, cache_dir=Path(tmp))
        except MeshError as e:  # a built-in mesh is named by the case, not by its temporary file
            raise MeshError(re.sub(re.escape(tmp) + r"\S*\.msh", mesh_name(case), str(e))) from None
    out = Preflight(case=case, mesh=mesh_identity(md), tags=sorted(md.tags))
    problems += _boundary_tags(case, md)
    p = case.particles
    bed = None
    bed_path = case.resolve_path(p.bed_file) if p.bed_file else None
    if bed_path is not None and bed_path.exists() and case.run.mode in DEM_MODES:
        from febed.dem.insertion import BedError, load_bed

        try:
            bed, _ = load_bed(bed_path)
        except BedError as e:
            problems.append(f"[particles] bed_file = {p.bed_file!r}: {e}")
    if bed is not None:
        out.bed_particles = bed.n_owned
        diffs = bed_differences(case, bed, md.gdim)
        if diffs and not p.bed_authoritative:
            problems.append(_mismatch_message(p.bed_file, bed_path, diffs))
        elif diffs:
            out.case, notes = reconcile(case, bed, md.gdim)
            out.notes += notes
            left = [d for d in bed_differences(out.case, bed, md.gdim) if d[0] == "[coarse_grain] ratio"]
            if left:  # what the bed cannot decide
                problems.append(_mismatch_message(p.bed_file, bed_path, left, authoritative=True))
        problems += _outside(md, bed, p.bed_file, bed_path)
    elif case.run.mode in DEM_MODES and (p.count > 0 or p.bed_mass > 0):
        from febed.bed import insertion_region

        try:
            insertion_region(case, md, md.gdim)
        except ValueError as e:
            problems.append(str(e))
    if problems:
        raise PreflightError(problems, str(case.path or "case"))
    out.estimate, refusals, hard = estimate(out.case, md, bed, comm)
    problems += hard
    if force:
        out.notes += [f"--force: {r}" for r in refusals]
    else:
        problems += [f"{r}; or run with --force" for r in refusals]
    if problems:
        raise PreflightError(problems, str(case.path or "case"))
    del md
    return out


# ------------------------------------------------------------------------------------------------ mesh
def mesh_identity(md) -> dict:
    """What identifies a mesh: node and cell counts and its bounding box [xmin, ymin, zmin, xmax, ymax, zmax]."""
    x = md.mesh.geometry.x
    lo = np.array(x.min(axis=0) if x.size else np.full(3, np.inf), dtype=np.float64)
    hi = np.array(x.max(axis=0) if x.size else np.full(3, -np.inf), dtype=np.float64)
    if md.comm.size > 1:
        md.comm.Allreduce(MPI.IN_PLACE, lo, op=MPI.MIN)
        md.comm.Allreduce(MPI.IN_PLACE, hi, op=MPI.MAX)
    topo = md.mesh.topology
    return {
        "nodes": int(topo.index_map(0).size_global),
        "cells": int(topo.index_map(topo.dim).size_global),
        "bounds": [float(v) for v in (*lo, *hi)],
    }


def mesh_name(case: Case) -> str:
    """How messages name the case's mesh: its file, or the built-in geometry."""
    m = case.mesh
    return f"[mesh] file = {m.file!r}" if m.file else f"[mesh] builtin = {m.builtin!r}"


def _boundary_tags(case: Case, md) -> list[str]:
    """Every facet tag of the mesh needs a [gas.boundary.<tag>] table once the case has any."""
    if not case.boundary:
        return []
    types = ", ".join(repr(c) for c in BOUNDARY["type"].choice_names())
    return [
        f"{mesh_name(case)}: the mesh has facet tag {tag!r} but the case has no [gas.boundary.{tag}] table: add one "
        f"with type = one of {types} (a tag without a table is not taken as a wall)"
        for tag in sorted(md.tags)
        if tag not in case.boundary
    ]


# ------------------------------------------------------------------------------------------------- bed
def _expected(case: Case, dim: int):
    """(count or None, parcel diameter of originals' rule, parcel density) the case would insert."""
    from febed.bed import original_count

    p = case.particles
    count = None
    if p.count > 0 or p.bed_mass > 0:
        count = coarse.parcels(case, original_count(case), dim).count
    spec = coarse.parcels(case, 1, dim)
    return count, spec


def _original_diameters(case: Case, bed) -> np.ndarray:
    """The diameter of the original particles each bed particle stands for (m)."""
    n = bed.n_owned
    d = bed.diameter[:n]
    cg = case.coarse_grain
    if cg.model in ("tm", "pcpm"):
        return coarse.closure_sizes(d, bed.n_orig[:n])[0]
    if cg.model == "scg":
        return d / cg.ratio
    return d


def _densities(bed) -> np.ndarray:
    n = bed.n_owned
    return bed.mass[:n] / (math.pi / 6.0 * bed.diameter[:n] ** 3)


def _spread(a: np.ndarray) -> str:
    lo, hi = float(a.min()), float(a.max())
    return f"{lo:.6g}" if lo == hi else f"{lo:.6g} to {hi:.6g}"


def bed_differences(case: Case, bed, dim: int) -> list[tuple[str, str, str]]:
    """(key, case value, bed value) of each `[particles]` key on which the bed disagrees with the case."""
    p, cg = case.particles, case.coarse_grain
    count, spec = _expected(case, dim)
    n = bed.n_owned
    parcels = "" if cg.model == "none" else f" {cg.model} parcels"
    diffs = []
    if count is not None and count != n:
        key = "count" if p.count > 0 else "bed_mass"
        value = p.count if p.count > 0 else p.bed_mass
        diffs.append((key, f"{value} ({count}{parcels or ' particles'})", f"{n} particles"))
    if cg.model in ("tm", "pcpm") and np.any(bed.n_orig[:n] != spec.n_orig):
        diffs.append(
            ("[coarse_grain] ratio", f"{cg.ratio:g} ({spec.n_orig} originals a parcel)", f"{_spread(bed.n_orig[:n])}")
        )
    d = bed.diameter[:n]
    if np.any(np.abs(d / spec.diameter - 1.0) > BED_RTOL):
        of = f" ({spec.diameter:.6g} m{parcels})" if parcels else ""
        diffs.append(("diameter", f"{p.diameter:.6g} m{of}", f"{_spread(d)} m"))
    rho = _densities(bed)
    if np.any(np.abs(rho / spec.density - 1.0) > BED_RTOL):
        of = f" ({spec.density:.6g} kg/m^3{parcels})" if spec.density != p.density else ""
        diffs.append(("density", f"{p.density:.6g} kg/m^3{of}", f"{_spread(rho)} kg/m^3"))
    return diffs


def _mismatch_message(name: str, path: Path, diffs, authoritative: bool = False) -> str:
    lines = "; ".join(f"{k} = {a} in the case, {b} in the bed" for k, a, b in diffs)
    fix = (
        "bed_authoritative takes count, diameter and density from a bed, not the coarse-graining: set "
        "[coarse_grain] to the bed's"
        if authoritative
        else "Either set these [particles] values to the bed's, or set [particles] bed_authoritative = true to "
        "take them from the bed"
    )
    return f"[particles] bed_file = {name!r}: the bed {path} does not match the case: {lines}. {fix}"


def reconcile(case: Case, bed, dim: int) -> tuple[Case, list[str]]:
    """The case with `[particles]` count, diameter and density taken from the bed, and a note per change."""
    p, cg = case.particles, case.coarse_grain
    n = bed.n_owned
    values = p.as_dict()
    d_orig = float(np.mean(_original_diameters(case, bed)))
    rho = float(np.mean(_densities(bed)))
    d_bed = float(np.mean(bed.diameter[:n]))
    if cg.model == "scg":
        rho = rho * d_bed**2 / d_orig**2  # invert rho_cg = rho d^2 / d_cg^2 (seed 003 eq 7)
    if cg.model in ("tm", "pcpm"):
        count = int(bed.n_orig[:n].sum()) if dim == 3 else round(n * cg.ratio**2)
    elif cg.model == "scg":
        count = round(n * cg.ratio**3)
    else:
        count = n
    values.update(count=count, bed_mass=0.0, diameter=d_orig, density=rho)
    notes = [
        f"[particles] {k} = {p.as_dict()[k]!r} -> {values[k]!r} (taken from the bed file {p.bed_file!r}, "
        "bed_authoritative = true)"
        for k in ("count", "bed_mass", "diameter", "density")
        if values[k] != p.as_dict()[k]
    ]
    d, rho = bed.diameter[:n], _densities(bed)
    if np.ptp(d) > BED_RTOL * d.max() or np.ptp(rho) > BED_RTOL * rho.max():
        notes.append(
            f"the bed file {p.bed_file!r} is polydisperse (diameters {_spread(d)} m, densities {_spread(rho)} "
            "kg/m^3): [particles] diameter and density are its means"
        )
    sections = dict(case.sections)
    sections["particles"] = Section("particles", values)
    return Case(path=case.path, sections=sections, boundary=case.boundary), notes


def _outside(md, bed, name: str, path: Path) -> list[str]:
    """A problem if any bed particle lies outside the mesh (collective)."""
    from febed.bed import inside_mesh

    n = bed.n_owned
    pos = bed.pos[:n]
    ok = inside_mesh(md, pos)
    if ok.all():
        return []
    b = mesh_identity(md)["bounds"]
    k = 3 if md.gdim == 3 else 2

    def pt(x) -> str:
        return "(" + ", ".join(f"{v:.6g}" for v in x[:k]) + ")"

    first = pos[np.flatnonzero(~ok)[0]]
    return [
        f"[particles] bed_file = {name!r}: {int((~ok).sum())} of {n} particles of the bed {path} lie outside the mesh "
        f"(the mesh spans {pt(b[:3])} to {pt(b[3:])} m, the bed {pt(pos.min(axis=0))} to {pt(pos.max(axis=0))} m; "
        f"the first outside is at {pt(first)} m): a bed must be packed in the case's mesh (delete the file and keep "
        "pack_if_missing = true to pack it again)"
    ]


# -------------------------------------------------------------------------------------------- estimate
def estimate(case: Case, md, bed, comm=MPI.COMM_WORLD) -> tuple[Estimate, list[str], list[str]]:
    """The run's `Estimate`, the refusals `--force` overrides and the problems it does not."""
    from febed.dem.particles import GID_LIMIT

    mode = case.run.mode
    end = case.run.end_time
    ident = mesh_identity(md)
    est = Estimate(nodes=ident["nodes"], cells=ident["cells"], ranks=comm.size)
    refusals: list[str] = []
    hard: list[str] = []
    p = case.particles
    if mode in DEM_MODES:
        if bed is not None:
            est.particles = bed.n_owned
        elif p.count > 0 or p.bed_mass > 0:
            count, _ = _expected(case, md.gdim)
            est.particles = int(count)
    if est.particles >= GID_LIMIT:
        key = "count" if p.count > 0 else "bed_mass"
        hard.append(
            f"[particles] {key} = {getattr(p, key)!r} gives {est.particles:.3g} particles; febed numbers at most "
            f"{GID_LIMIT} (2^31) particles"
        )
        return est, refusals, hard
    if est.particles:
        est.dt_dem = _dem_step(case, md.gdim, bed)
    if mode in GAS_MODES:
        est.dt_gas, cfl_dt = _gas_step(case, md, ident)
        speed = 1.0
        if est.particles and _fluidized(case):
            dt_bed = _gas_step(case, md, ident, BED_GAS_SPEED)[0]
            est.bed_cfl, est.dt_gas = dt_bed < est.dt_gas, dt_bed
            speed = BED_GAS_SPEED
        est.convective = _convective_substeps(case, md, ident, est.dt_gas, speed)
        if cfl_dt < case.gas.dt_min:
            tag, u = _fastest_inlet(case)
            hard.append(
                f"[gas.boundary.{tag}] velocity = {u:g} m/s: the CFL step cfl h / U on cells of "
                f"~{_cell_size(md, ident):.3g} m is {cfl_dt:.3g} s, below [gas] dt_min = {case.gas.dt_min:g} s: "
                "the gas step could not follow the flow; check the velocity (m/s) or lower dt_min"
            )
        est.gas_steps = end / est.dt_gas
    if est.dt_dem:
        est.dem_steps = est.gas_steps * est.sub_steps if est.dt_gas else end / est.dt_dem
    est.memory = comm.size * RANK_BYTES + est.particles * PARTICLE_BYTES + est.nodes * NODE_BYTES
    if case.run.mode == "cfd-dem" and case.run.particle_partition == "work" and comm.size > 1:
        est.memory += est.nodes * WHOLE_MESH_BYTES * comm.size  # the whole mesh's coupling arrays on every rank
    gas_cost = GAS_SECONDS * (1.0 + PREDICTOR_SHARE * (est.convective - 1))
    est.wall = (est.particles * est.dem_steps * DEM_SECONDS + est.nodes * est.gas_steps * gas_cost) / comm.size
    if est.dt_dem and est.dt_gas and est.sub_steps > MAX_SUBSTEPS:
        refusals.append(
            f"{_dem_keys(case)}: the DEM step T_C / dt_factor is {est.dt_dem:.3g} s, {_num(est.sub_steps)} DEM "
            f"sub-steps per gas step of {est.dt_gas:.3g} s; at most {MAX_SUBSTEPS} are allowed (one gas step would "
            f"take ~{_duration(est.particles * est.sub_steps * DEM_SECONDS / comm.size)}): check the stiffness "
            "(N/m) and the particle size and density"
        )
    if est.wall / FAST > MAX_WALL_DAYS * 86400.0:
        refusals.append(
            f"[run] end_time = {end:g} s: the run would take ~{_duration(est.wall)} of wall time (at least "
            f"{_duration(est.wall / FAST)}; the limit is {MAX_WALL_DAYS:g} days): {_num(est.gas_steps)} gas steps "
            f"(end_time / ~{est.dt_gas or 0:.3g} s, [gas] dt_max = {case.gas.dt_max:g} s) on {est.nodes} nodes and "
            f"{_num(est.dem_steps)} DEM steps of {est.particles} particles on {comm.size} rank(s); check end_time, "
            "dt_max, [contact] stiffness and [particles] count"
        )
    local = comm.Split_type(MPI.COMM_TYPE_SHARED) if comm.size > 1 else None
    on_node = local.size if local is not None else 1
    if local is not None:
        local.Free()
    need = est.memory / 4.0 / comm.size * on_node
    have = _physical_memory()
    if have and need > have:
        key = "[particles] count" if est.particles * PARTICLE_BYTES > est.nodes * NODE_BYTES else "[mesh]"
        refusals.append(
            f"{key}: {est.particles} particles and {est.nodes} mesh nodes need ~{_bytes(est.memory)} of memory (at "
            f"least {_bytes(need)} on this machine), more than its {_bytes(have)}"
        )
    return est, refusals, hard


def _dem_step(case: Case, dim: int, bed) -> float:
    """The DEM step T_C / dt_factor (s) of the case's contact law for the bed's (or inserted) lightest particles."""
    from febed.bed import dem_from_case
    from febed.dem.integrate import critical_time
    from febed.dem.particles import Particles
    from febed.dem.walls import Walls

    if bed is not None:
        n = bed.n_owned
        two = np.argsort(bed.mass[:n])[:2]
        data = bed.to_dict()
        parts = Particles.from_dict({k: v[two] for k, v in data.items()})
    else:
        spec = coarse.parcels(case, 1, dim)
        parts = Particles(capacity=2)
        parts.add(np.zeros((2, 3)), spec.diameter, spec.density, n_orig=spec.n_orig)
    dem = dem_from_case(case, Walls(), dim, parts)
    k = parts.n_owned
    tc = critical_time(dem.law, dem.pp, dem.pw, parts.mass[:k], parts.diameter[:k], case.particles.rotation, True)
    return tc / case.contact.dt_factor


def _dem_keys(case: Case) -> str:
    c = case.contact
    if c.from_material:
        k = f"[contact] young_modulus = {c.young_modulus:g} Pa (from_material)"
    elif c.stiffness_wall is not None and c.stiffness_wall > c.stiffness:
        k = f"[contact] stiffness_wall = {c.stiffness_wall:g} N/m"
    else:
        k = f"[contact] stiffness = {c.stiffness:g} N/m"
    return k + f", dt_factor = {c.dt_factor:g}"


def _fastest_inlet(case: Case) -> tuple[str, float]:
    inlets = [(tag, b.velocity) for tag, b in case.boundary.items() if b.type == "inlet" and b.velocity]
    return max(inlets, key=lambda tv: tv[1]) if inlets else ("", 0.0)


def _cell_size(md, ident: dict) -> float:
    b = ident["bounds"]
    dim = md.gdim
    volume = math.prod(max(b[3 + a] - b[a], 0.0) for a in range(dim))
    return (volume / max(ident["cells"], 1)) ** (1.0 / dim)


def _fluidized(case: Case) -> bool:
    """Whether the fastest inlet's velocity exceeds the particles' minimum fluidization velocity (Wen and Yu)."""
    from febed.coarse.pcpm import u_mf_wen_yu

    _, u = _fastest_inlet(case)
    p, g = case.particles, case.gas
    if u <= 0 or not p.density > g.density:
        return False
    gravity = case.run.gravity
    return gravity > 0 and u > u_mf_wen_yu(p.diameter, p.density, g.density, g.viscosity, gravity)


def _gas_step(case: Case, md, ident: dict, speed: float = 1.0, substeps: int | None = None) -> tuple[float, float]:
    """(estimated gas step, CFL step at the fastest inlet) in s on the mean cell size.

    The estimate takes the CFL limit at `speed` times the fastest inlet velocity (a fluidized bed's gas speed),
    with up to `substeps` (default: the case's `gas.convection_substeps`) convective steps per gas step.
    """
    g = case.gas
    h = _cell_size(md, ident)
    _, u = _fastest_inlet(case)
    k = g.convection_substeps if substeps is None else substeps  # each explicit sub-step within the limits
    cfl_dt = k * g.cfl * h / u if u > 0 else math.inf
    fourier_dt = k * g.fourier * h * h * g.density / g.viscosity
    return max(min(g.dt_max, cfl_dt / speed, fourier_dt), g.dt_min), cfl_dt


def _convective_substeps(case: Case, md, ident: dict, dt: float, speed: float) -> int:
    """Explicit sub-steps of a gas step of `dt` (s): as many convective steps as it spans, up to the case's k."""
    k = case.gas.convection_substeps
    if k == 1:
        return 1
    single = _gas_step(case, md, ident, speed, substeps=1)[0]
    return int(min(k, max(1, math.ceil(dt / single * (1.0 - 1e-9)))))


def _physical_memory() -> float:
    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 0.0


# ------------------------------------------------------------------------------------------- formatting
def _num(x: float) -> str:
    return f"{x:.0f}" if x < 1e6 else f"{x:.2g}"


def _bytes(b: float) -> str:
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if b >= size:
            return f"{b / size:.3g} {unit}"
    return f"{b:.0f} B"


def _duration(s: float) -> str:
    if not math.isfinite(s):
        return "forever"
    for unit, size in (("years", 365.25 * 86400), ("days", 86400), ("h", 3600), ("min", 60)):
        if s >= size:
            return f"{s / size:.3g} {unit}"
    return f"{s:.2g} s"
