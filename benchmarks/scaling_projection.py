"""Projected parallel efficiency of the pseudo-2D case C2 and its fine mesh at 2-64 ranks, from a census of the work.

The census (`scaling_census.py`) repeats febed's decomposition on one process for P = 1, 2, 4, ..., 64 parts and
counts, per rank, the owned and ghost particles, listed and force pairs, owned gas nodes and halo nodes, and the
bytes sent per gas step, over particle snapshots of a bubbling bed. The model turns these into time with single-core
costs per unit of work measured on the same bed (`scaling_measure.py`, serially, once with the serial pressure
solver and once with the parallel one, the DEM also on its parallel code path; on several ranks each core's costs
grow by the slow-down measured with every core working, and the exchange calls and the pressure operator's COO fill
add their measured costs) and an interconnect of stated bandwidth and latency, takes the slowest rank of each phase
(DEM, coupling, gas), and checks its 2-rank efficiency against a measured one of the same state and its loads
against a 2-rank run (docs/scaling.md). Besides febed's default decomposition it projects three others (`VARIANTS`):
the particles by DEM work, coupled by the owners of their cells, with the mesh partition or the mesh in compact
blocks, and the latter coupled by the particles' owners through a nodal exchange, which is febed's
`particle_partition = "work"` (its check: `--check TAG` with a 2-rank window run with `--set
run.particle_partition=work --tag TAG_work`):

    python benchmarks/scaling_measure.py --restart RUN_DIR                        # serial costs
    python benchmarks/scaling_measure.py --restart RUN_DIR --warmup 0.001 --sim-time 0.001 --rebuilds 40 \
        --tag _rebuild                                                            # rebuild costs
    GAMG='-febed_pressure_weighted_pc_type gamg -febed_pressure_weighted_pc_gamg_square_graph 0'
    python benchmarks/scaling_measure.py --restart RUN_DIR --tag _gamg --set "gas.petsc_options=\"$GAMG\""
    mpirun -n 2 python benchmarks/scaling_measure.py --restart RUN_DIR --concurrent --tag _concurrent  # every core busy
    python benchmarks/scaling_measure.py --restart RUN_DIR --owners --tag _owners  # the work partition's coupling
    python benchmarks/scaling_measure.py --restart RUN_DIR --staged --tag _staged  # the DEM's parallel code path
    [mpirun -n 2] python benchmarks/scaling_measure.py --restart RUN_DIR --warmup 0.001 --sim-time 0.001 \
        --calls 500 --tag _calls                                                  # exchange calls, 1 and 2 ranks
    mpirun -n 2 python benchmarks/scaling_measure.py --restart RUN_DIR            # 2-rank check
    mpirun -n 2 python benchmarks/scaling_measure.py --pingpong                   # shared-memory figures
    python benchmarks/scaling_projection.py --run RUN_DIR [--from 1.2 --to 1.5] [--bandwidth 10e9 --latency 2e-6]

The check of the model (docs/scaling.md) is made in rounds, each a serial, a 2-rank and a concurrent window of
the same checkpoint tagged alike (`--sim-time 0.02 --tag _r1`, and `--concurrent --tag _r1_concurrent` on 2
ranks); `--check _r1,_r2,...` checks every round with its own serial costs and the rounds' median busy-core
slow-down (which the projections then take too), and prints the median gap.

RUN_DIR is a C2 run folder with particle snapshots over the census window (`--from`, `--to`) and its checkpoint
at the window's end, which the measurements continue (`febed run demos/pseudo2d/C2.toml --set run.end_time=1.5
--set output.particle_interval=0.01`: snapshots every 0.01 s). The census is cached in
benchmarks/out/scaling_census.npz; without `--run` the cached census is used. Writes
benchmarks/out/scaling_projection.png and benchmarks/out/scaling_projection.json.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import scaling_census as sc  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out"
RANKS = (1, 2, 4, 8, 16, 32, 64)
MESHES = {"C2": "demos/pseudo2d/C2.toml", "C3": "demos/pseudo2d/C3.toml"}  # intermediate and fine mesh
UPDATE_BYTES = 6 * 8  # a ghost update row: pos, vel (no rotation; 9 doubles with rotation)
REFRESH_BYTES = 12 * 8 + 3 * 8  # a ghost refresh row (exchange.refresh_ghosts): 12 doubles, 3 integers
MIGRATE_BYTES = 342  # a migrating particle: every per-particle array (the DEM's 342 B per particle)
GAS_VALUES = 1.7  # doubles per halo node in a halo exchange of the gas step outside its pressure solver (estimate)
# Measured on 2 ranks of one machine (scaling_measure.py --pingpong, fastest of many): the calls of a ghost
# update (2,200 rows each way and the rebuild test's reduction) and of a rebuild's exchanges (migration,
# ghost refresh), shared memory; over a network the model adds latency and bytes / bandwidth on top.
UPDATE_CALLS = 17e-6
REBUILD_CALLS = 141e-6
# The calls per gas step that exchange between ranks or reduce over them outside PETSc's solvers (counted with
# `scaling_measure.py --profile` over a C2 window), each costing on several ranks `call_s` beyond one process
# (`scaling_measure.py --calls`): the gas step's halo updates of nodal fields, scatters of the sweeps' extra
# columns, PETSc ghost updates and reductions; the coupling's nodal sums (reverse and forward scatters) and
# reductions.
GAS_CALLS = {"scatter_forward": 5, "vec_scatter": 7, "ghost_update": 2, "allreduce": 3, "Allreduce": 3}
COUPLING_CALLS = {"scatter_forward": 3, "scatter_reverse": 3, "allreduce": 3}
# Outside the pressure solver the gas step's exchanges are those calls: each halo update, scatter or ghost
# update sends one message to each halo neighbour, each reduction costs log2(P) latencies.
GAS_EXCHANGES = GAS_CALLS["scatter_forward"] + GAS_CALLS["vec_scatter"] + GAS_CALLS["ghost_update"]
GAS_REDUCTIONS = GAS_CALLS["allreduce"] + GAS_CALLS["Allreduce"]
# The pressure solver's own messages, bytes and reductions per gas step at each rank count, counted by PETSc
# in its solves and AMG set-ups (`gas_step.py --solver-counts`, on each mesh with a bubbling-bed-like ε, run
# at 1-64 ranks oversubscribed: counts, not times). Each message costs a latency and its bytes / bandwidth, as
# every message of the model does; each exchange the software cost of a PETSc ghost update beyond one process
# (`call_s["ghost_update"]`), with as many exchanges at every P as messages on 2 ranks (one neighbour each).
SOLVER_COUNTS = OUT / "solver_counts.json"
# The same counts with GAMG's coarse levels gathered onto fewer ranks (`gas.petsc_options =
# "-febed_pressure_weighted_pc_gamg_process_eq_limit 500"`), projected as an option beside the default solver.
EQ_LIMIT = 500
SOLVER_COUNTS_EQ = OUT / f"solver_counts_eq{EQ_LIMIT}.json"
LEVELS = {"C2": "intermediate", "C3": "fine"}
# A decomposition of the particles apart from the mesh's: each gas step, a particle whose cell another rank
# owns goes there (position, velocity, diameter, id: 8 doubles) and its forces come back (drag and pressure
# gradient force, 6 doubles), in one exchange each way; taken to cost the calls of a ghost update.
TRANSFER_BYTES = (8 + 6) * 8
TRANSFER_CALLS = 2 * UPDATE_CALLS
# The documented 1 -> 2 rank efficiency of C2 from the census's checkpoint (docs/scaling.md, "Check against
# measured runs"): the median of ten rounds of 0.02 s windows on vm3 (73.2-86.6 %); the reference when no
# 2-rank window of the checkpoint was measured here.
DOCUMENTED = {"0.02 s windows of the census's checkpoint, median of ten rounds on vm3": 0.853}


def snapshots(run: Path, t0: float, t1: float) -> list[tuple[float, Path]]:
    """(time, file) of the run's particle snapshots with t0 <= t <= t1 (from particles/particles.pvd)."""
    pvd = run / "particles" / "particles.pvd"
    if not pvd.is_file():
        raise SystemExit(f"--run {run}: no particles/particles.pvd (a febed run folder with particle output)")
    got = [(float(d.get("timestep")), pvd.parent / d.get("file")) for d in ET.parse(pvd).getroot().iter("DataSet")]
    got = [(t, f) for t, f in got if t0 - 1e-9 <= t <= t1 + 1e-9]
    if len(got) < 2:
        raise SystemExit(f"--run {run}: fewer than 2 particle snapshots between t = {t0} and {t1} s")
    return got


def take_census(run: Path, t0: float, t1: float, skin_ratio: float) -> dict:
    """Per mesh, P and snapshot: the census arrays (see `scaling_census`), and the checkpoint's census."""
    from febed.io.checkpoint import latest_valid
    from febed.io.particles import read_vtp

    snaps = snapshots(run, t0, t1)
    states = []
    for t, f in snaps:
        a = read_vtp(f)
        order = np.argsort(a["gid"])  # rows in gid order: a particle's owner is followed from snapshot to snapshot
        states.append((t, np.ascontiguousarray(a["Points"][order]), a["diameter"][order], a["gid"][order]))
    ck = latest_valid(run / "checkpoints")
    if ck is not None:
        z = np.load(ck)
        states.append((float(z["dem/time"]), np.ascontiguousarray(z["dem/p_pos"]), z["dem/p_diameter"], None))
    out = {"times": [s[0] for s in states[: len(snaps)]], "checkpoint": ck is not None}
    pairs = []
    for _, pos, d, _ in states:
        skin = skin_ratio * d.max()
        pairs.append((skin, sc.all_pairs(pos, d, skin)))
    for name, path in MESHES.items():
        mesh = sc.case_mesh(ROOT / path, OUT / "mesh")
        h = [min(np.diff(a).min() for a in mesh.axes)]
        out[f"{name}/h_min"] = h[0]
        for P in RANKS:
            owner = sc.partition(mesh, P)
            blocks = sc.partition(mesh, P, axes=(0, 1, 2))  # a gas partition the particles need not follow
            for k, v in sc.node_census(mesh, owner, P).items():
                out[f"{name}/{P}/{k}"] = v
            for k, v in sc.node_census(mesh, blocks, P).items():
                out[f"{name}/{P}/blocks/{k}"] = v
            width = 1.2 * (states[0][2].max() * (1 + skin_ratio))
            halo = sc.HaloBins(mesh, owner, P, width)
            rows, work, work_b = [], [], []
            prev = prev_w = prev_b = None
            for (_, pos, d, gid), (skin, pr) in zip(states, pairs, strict=True):
                c = sc.particle_census(mesh, owner, P, halo, pos, d, skin, pr)
                w = sc.work_census(mesh, c["powner"], P, pos, pr, width)
                pc = mesh.locate(pos)
                b = sc.work_census(mesh, blocks[pc], P, pos, pr, width, cells=pc)
                prev = _migrated(c, prev, gid, P)
                prev_w = _migrated(w, prev_w, gid, P)
                prev_b = _migrated(b, prev_b, gid, P)
                rows.append(c)
                work.append(w)
                work_b.append(b)
            for tag, got in (("", rows), ("work/", work), ("blocks/", work_b)):
                for k in got[0]:
                    if k != "powner":
                        out[f"{name}/{P}/{tag}{k}"] = np.array([r[k] for r in got])  # (snapshots [+ checkpoint], P)
            print(f"census {name} P = {P}: done", flush=True)
    return out


def _migrated(c: dict, prev, gid, P: int):
    """Set c["migrated"], the particles leaving each rank since the last snapshot; the state for the next."""
    c["migrated"] = np.zeros(P, dtype=np.int64)
    if prev is not None and gid is not None and np.array_equal(prev[0], gid):
        moved = prev[1] != c["powner"]
        c["migrated"] = np.bincount(prev[1][moved], minlength=P)
    return gid, c["powner"]


def load_measured(name: str, P: int, tag: str = "") -> dict | None:
    path = OUT / f"measured_{name}_P{P}{tag}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def unit_costs(m1: dict, m1_iter: dict | None, m1_rebuild: dict | None = None, loaded: dict | None = None,
               calls: tuple[dict, dict] | None = None, owners: dict | None = None, staged: dict | None = None,
               iter_of: dict | None = None) -> dict:  # fmt: skip
    """Single-core costs per unit of work from the serial measurements (CPU seconds of each phase).

    m1: the serial run with its default pressure solver (a Cholesky factorisation on meshes of at most 50,000
    nodes); m1_iter: the same window with the parallel runs' pressure solver (CG + GAMG) on one process, whose
    gas cost per node is used for every run on several ranks and for meshes too large for the factorisation;
    m1_rebuild: the parallel rebuild's own work (its code path on one process less a serial rebuild, per listed
    pair: the history by key; and locating every particle, per particle), the COO fill of the drag-weighted
    operator, and the coupling's work over the nodes per gas step (the filter's passes, which a rank makes over
    its owned and halo nodes; the rest of the coupling is counted per particle), on one core;
    loaded: the serial window run on every core at once, phases started together (`--concurrent`), whose
    costs over m1's per phase are the slow-down of a core while the others do the same phase (`load_factor`,
    applied on several ranks); calls: the exchange calls timed serially and on 2 ranks (`--calls`), whose
    difference is what each costs on several ranks beyond one process (`call_s`); owners: the window coupled
    the way `particle_partition = "work"` couples, on one process (`--owners`), its coupling cost per particle
    that of the "nodal" decomposition; staged: the window on the DEM's parallel code path on one process
    (`--staged`: the sub-steps stepped from Python with a ghost update each, the rebuilds keying the history),
    whose DEM cost per pair is the DEM's on several ranks (with it the history by key is not counted apart);
    iter_of: the serial window m1_iter and staged were measured beside (m1 when None), so that another window
    m1 (a check's) takes their costs as ratios to its own.
    """
    r = m1["per_rank"][0]
    sim = r["t1"] - r["t0"]
    split = r["split"]
    loads = r["samples"]
    pairs = np.mean([s["pairs"] for s in loads])
    owned = np.mean([s["owned"] for s in loads])
    nodes = loads[0]["nodes_owned"]
    gas_iter = split["gas"]
    ksp_share = r.get("ksp", 0.0) / split["gas"]  # the pressure solves' share of the gas phase
    if m1_iter is not None:
        ri = m1_iter["per_rank"][0]
        ksp_share = ri.get("ksp", 0.0) / ri["split"]["gas"]
        rb = (iter_of or m1)["per_rank"][0]
        gas_iter = split["gas"] * (ri["split"]["gas"] / ri["gas_steps"]) / (rb["split"]["gas"] / rb["gas_steps"])
    dem_staged = split["dem"]
    if staged is not None:
        rs, rb = staged["per_rank"][0], (iter_of or m1)["per_rank"][0]
        dem_staged = split["dem"] * (rs["split"]["dem"] / rs["dem_steps"]) / (rb["split"]["dem"] / rb["dem_steps"])
    keyed = locate = coo = cpl_nodes = 0.0
    entries = 0
    if m1_rebuild is not None:
        rb = m1_rebuild["per_rank"][0]
        if "rebuild_staged" in rb:  # the parallel code path on one process (medians: its first call differs)
            keyed = (rb["rebuild_staged"][1] - rb["rebuild"][1]) / rb["rebuild_loads"]["pairs"]
        else:  # a serial rebuild with the history keyed, which also re-sorts the rows
            keyed = (rb["rebuild_keyed"][0] - rb["rebuild"][0]) / rb["rebuild_loads"]["pairs"]
        locate = rb["locate"][0] / rb["rebuild_loads"]["owned"]  # on one process the migration locates nobody
        if staged is not None:  # the staged window's rebuilds key the history already
            keyed = 0.0
        if "coo_fill" in rb:
            coo, entries = rb["coo_fill"][0] / rb["coo_entries"], rb["coo_entries"]
        if "coupling_nodes" in rb:  # the coupling's work over the nodes per gas step (s), of this window's share
            cpl_nodes = min(rb["coupling_nodes"][0], split["coupling"] / r["gas_steps"])
    factor = load_factor(m1, loaded)
    call_s = {}
    if calls is not None:
        one, two = calls
        alone = one["per_rank"][0]["calls"]
        for k in alone:
            call_s[k] = max(0.0, max(r["calls"][k][0] for r in two["per_rank"]) - alone[k][0])
    per_particle = 1e6 * split["coupling"] / (r["gas_steps"] * owned)  # all of it, less the nodes' below
    per_particle_owners = per_particle
    if owners is not None:
        ro = owners["per_rank"][0]
        per_particle_owners = (
            per_particle * ro["split"]["coupling"] / split["coupling"] * r["gas_steps"] / ro["gas_steps"]
        )
    node_share = 1e6 * cpl_nodes / owned  # µs per particle of the coupling's work over the nodes
    per_particle, per_particle_owners = per_particle - node_share, per_particle_owners - node_share
    return {
        "us_per_particle_step_owners": per_particle_owners,
        "load_factor": factor,
        "call_s": call_s,
        "us_per_entry_coo": 1e6 * coo,
        "entries_per_node": entries / loads[0]["nodes_owned"],
        "sim": sim,
        "us_per_pair_keyed_rebuild": 1e6 * keyed,
        "us_per_particle_locate": 1e6 * locate,
        "gas_steps_per_s": r["gas_steps"] / sim,
        "dem_steps_per_s": r["dem_steps"] / sim,
        "builds_per_s": r["builds"] / sim,
        "us_per_pair_step": 1e6 * split["dem"] / (r["dem_steps"] * pairs),
        "us_per_pair_step_staged": 1e6 * dem_staged / (r["dem_steps"] * pairs),
        "us_per_node_step": 1e6 * split["gas"] / (r["gas_steps"] * nodes),
        "us_per_particle_step": per_particle,
        "us_per_node_coupling": 1e6 * cpl_nodes / nodes,  # the filter's passes over the rank's local nodes
        "us_per_node_step_iter": 1e6 * gas_iter / (r["gas_steps"] * nodes),
        "ksp_share": min(1.0, ksp_share),
        "output_s_per_s": split.get("output", 0.0) / sim,
        "pairs": pairs,
        "nodes": nodes,
    }


def solver_counts(real: dict | None = None, path: Path = SOLVER_COUNTS, scale: dict | None = None) -> dict | None:
    """Per mesh (C2, C3) and rank count P > 1: the pressure solver's messages, bytes and reductions per gas step
    on its busiest rank (max over ranks of each) and its busiest rank's flops, from `gas_step.py --solver-counts`;
    None, with the command to run, if any is missing.

    `real`: a 2-rank window of the bubbling bed (`scaling_measure.py`, which records the same counts). The
    gas-step benchmark's bed-like ε changes more slowly than a bubbling bed's, so its AMG is set up again less
    often; every count is scaled by the real window's count over the benchmark's on C2 at 2 ranks ("scale"), or
    by `scale` if given (the default solver's, for counts of another solver on the same benchmark).
    """
    data = json.loads(path.read_text()) if path.is_file() else {}
    out, missing = {}, []
    for name, level in LEVELS.items():
        out[name] = {}
        for P in RANKS[1:]:
            got = data.get(level, {}).get(str(P))
            if got is None:
                missing.append(f"{level} at {P}")
                continue
            out[name][P] = {k: float(max(got[k])) for k in ("messages", "bytes", "reductions", "flops")}
    if missing:
        print(
            f"skipped: no pressure-solver counts in {path} for the {', '.join(missing)} rank(s); for each mesh level "
            "and P run `mpirun -n P --oversubscribe python benchmarks/gas_step.py --level LEVEL --warmup 20 --steps "
            f"20 --solver-counts {path}`"
        )
        return None
    out["scale"] = {"messages": 1.0, "bytes": 1.0, "reductions": 1.0}
    if scale is not None:
        out["scale"] = dict(scale)
    elif real is not None and "solver" in real["per_rank"][0]:
        for k in out["scale"]:
            got = max(r["solver"][k] / r["gas_steps"] for r in real["per_rank"])
            out["scale"][k] = got / out["C2"][2][k]
    for name in LEVELS:
        for v in out[name].values():
            for k, f in out["scale"].items():
                v[k] *= f
    return out


# `--concurrent` starts each phase with a barrier (`scaling_measure._barriers`): the wait recorded under a phase's
# name is for the other core to end the phase before it (the step's order: coupling, DEM, coupling, gas).
WAITED_ON = {"dem": ("coupling",), "coupling": ("dem", "gas"), "gas": ("untimed",)}


def load_factor(m1: dict, loaded: dict | None) -> dict:
    """Per phase, a core's CPU seconds while every core works (`loaded`, `--concurrent`) over m1's alone.

    The cores start each phase together, as the ranks of a run do, so a phase's time on a busy core is its
    own work and the wait at its end for the other core to finish the same work (the barrier before the next
    phase); the barrier at its own start is the previous phase's.
    """
    factor = {"dem": 1.0, "coupling": 1.0, "gas": 1.0}
    if loaded is not None:
        r = m1["per_rank"][0]
        for k in factor:
            own = np.mean([q["split"][k] - q["waits"][k] + sum(q["waits"][j] for j in WAITED_ON[k])
                           for q in loaded["per_rank"]])  # fmt: skip
            factor[k] = float(own / r["split"][k] * r["gas_steps"] / loaded["per_rank"][0]["gas_steps"])
    return factor


# The decompositions of the projection: particles with the cells of febed's partition (what febed does); the
# particles by DEM work apart from that partition, coupled by the owners of their cells; the same particles
# with the gas in compact blocks (every axis cut), which only a decoupled particle decomposition allows,
# coupled by the owners of their cells ("blocks") or by their own owners, exchanging nodal values ("nodal").
VARIANTS = {
    "cells": "particles with their cells",
    "work": "particles by DEM work, apart from the mesh",
    "blocks": "particles by DEM work, the gas in compact blocks",
    "nodal": "particles by DEM work, the gas in compact blocks, coupled by the particles' owners",
}
# The nodal exchange of a coupling done by the particles' owners, per node of another rank's cells, each gas
# step: the gas values a particle's drag and interpolation need (u, ε, ∇p: 7 doubles) to the particles' owner,
# the nodal sums of the particles (solid volume, K, K v̄: 5 doubles) back.
NODAL_BYTES = (7 + 5) * 8


def _keys(name: str, P: int, variant: str) -> tuple[str, str]:
    """Census key prefixes of the particle loads and of the gas loads of a decomposition."""
    if P == 1 or variant == "cells":
        return f"{name}/{P}/", f"{name}/{P}/"
    if variant in ("blocks", "nodal"):
        return f"{name}/{P}/blocks/", f"{name}/{P}/blocks/"
    return f"{name}/{P}/{variant}/", f"{name}/{P}/"


def phase_times(c: dict, name: str, P: int, cost: dict, net: dict, rows=slice(None), variant: str = "cells") -> dict:
    """Seconds per simulated second of each phase on the slowest rank (mean over the snapshots).

    `variant` (`VARIANTS`): with the particles decomposed by DEM work apart from the mesh
    (`scaling_census.work_census`), the coupling also sends each particle whose cell another rank owns there
    and its forces back.
    """
    L, B = net["latency"], net["bandwidth"]
    red = L * math.ceil(math.log2(P)) if P > 1 else 0.0
    f = cost["load_factor"] if P > 1 else {"dem": 1.0, "coupling": 1.0, "gas": 1.0}  # every core busy
    calls = cost["call_s"] if P > 1 else {}
    nd, nb = cost["dem_steps_per_s"], cost["builds_per_s"]
    ng = cost["gas_steps_per_s"] * (cost["h_ratio"] if name != "C2" else 1.0)
    key, gkey = _keys(name, P, variant)
    fp = c[f"{key}force_pairs"][rows]  # (snapshots, P)
    sent = c[f"{key}sent"][rows]
    nbr = c[f"{key}ghost_nbrs"][rows]
    mig = c[f"{key}migrated"][rows]
    per_pair = cost["us_per_pair_step_staged" if P > 1 else "us_per_pair_step"]  # the parallel code path
    dem = nd * (fp * per_pair * f["dem"] * 1e-6 + (UPDATE_CALLS + nbr * L + sent * UPDATE_BYTES / B + red) * (P > 1))
    gap = float(np.mean(np.diff(c["times"])))  # migration is counted between snapshots
    dem = (
        dem
        + nb * (REBUILD_CALLS + sent * REFRESH_BYTES / B + 2 * nbr * L + P * L) * (P > 1)
        + mig * MIGRATE_BYTES / B / gap
    )
    owned = c[f"{key}owned"][rows]
    listed = c[f"{key}pairs"][rows]
    extra = listed * cost["us_per_pair_keyed_rebuild"] + owned * cost["us_per_particle_locate"]
    dem = dem + nb * extra * f["dem"] * 1e-6 * (P > 1)  # the parallel rebuild's own work: history by key, locating
    coupled = c[f"{key}owned"][rows]  # the particles each rank couples: in its cells, or its own
    if variant == "nodal" and P > 1:  # gas values of other ranks' nodes in, the particles' nodal sums out
        cpl = ng * coupled * cost["us_per_particle_step_owners"] * f["coupling"] * 1e-6
        foreign = c[f"{key}foreign_nodes"][rows]
        cpl = cpl + ng * (foreign * NODAL_BYTES / B + 2 * c[f"{key}node_nbrs"][rows] * L + TRANSFER_CALLS)
    elif key != f"{name}/{P}/":  # particles to the owners of their cells and their forces back
        coupled = coupled + c[f"{key}transfer_in"][rows] - c[f"{key}transfer_out"][rows]
        cpl = ng * coupled * cost["us_per_particle_step"] * f["coupling"] * 1e-6
        moved = c[f"{key}transfer_out"][rows] + c[f"{key}transfer_in"][rows]
        cpl = cpl + ng * (moved * TRANSFER_BYTES / B + 2 * c[f"{key}transfer_nbrs"][rows] * L + TRANSFER_CALLS)
    else:
        cpl = ng * coupled * cost["us_per_particle_step"] * f["coupling"] * 1e-6
    nodes = c[f"{gkey}nodes"][None, :]
    halo = c[f"{gkey}halo"][None, :]
    hn = c[f"{gkey}halo_nbrs"][None, :]
    per_node = cost["us_per_node_step" if name == "C2" and P == 1 else "us_per_node_step_iter"]
    if P > 1 and "solver_flops" in cost:  # another solver: its busiest rank's flops over the default's, in the solves
        per_node *= 1.0 + cost["ksp_share"] * (cost["solver_flops"][name][P] - 1.0)
    coo = cost["us_per_entry_coo"] * cost["entries_per_node"] * (nodes + halo) * (P > 1)  # L_w's COO fill
    solver = cost["solver"][name][P] if P > 1 else {"messages": 0.0, "bytes": 0.0, "reductions": 0.0}
    solver_calls = cost["solver"][name][2]["messages"] if P > 1 else 0.0  # one message per exchange on 2 ranks
    gas = ng * (
        (nodes * per_node + coo) * f["gas"] * 1e-6
        + GAS_EXCHANGES * (hn * L + halo * GAS_VALUES * 8 / B)
        + GAS_REDUCTIONS * red
        + sum(n * calls.get(k, 0.0) for k, n in GAS_CALLS.items())
        + solver["messages"] * L
        + solver_calls * calls.get("ghost_update", 0.0)
        + solver["bytes"] / B
        + solver["reductions"] * red
    )
    cpl = cpl + ng * sum(n * calls.get(k, 0.0) for k, n in COUPLING_CALLS.items())
    cpl = cpl + ng * (nodes + halo) * cost.get("us_per_node_coupling", 0.0) * f["coupling"] * 1e-6  # the filter
    out = {k: float(np.mean(np.max(v, axis=1))) for k, v in (("dem", dem), ("coupling", cpl), ("gas", gas))}
    out["output"] = cost["output_s_per_s"] / P
    out["total"] = sum(out.values())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default=None, help="C2 run folder with particle snapshots (else the cached census)")
    ap.add_argument("--from", dest="t0", type=float, default=1.2, help="first snapshot time (s)")
    ap.add_argument("--to", dest="t1", type=float, default=1.5, help="last snapshot time (s)")
    ap.add_argument("--bandwidth", type=float, default=10e9, help="interconnect bandwidth (B/s)")
    ap.add_argument("--latency", type=float, default=2e-6, help="interconnect latency per message (s)")
    ap.add_argument(
        "--check",
        default="",
        help="tag of the check's measurements: measured_C2_P1<tag>.json (serial, whose costs per unit of work the "
        "check's model takes), measured_C2_P2<tag>.json (the "
        "mesh partition), and if present measured_C2_P2<tag>_work.json (particle_partition = work) and "
        "measured_C2_P2<tag>_concurrent.json (the busy cores' slow-down measured with them)",
    )
    args = ap.parse_args()
    cache = OUT / "scaling_census.npz"
    if not args.run and not cache.is_file() and (ROOT / "runs" / "C2" / "particles").is_dir():
        args.run = str(ROOT / "runs" / "C2")  # where `febed run demos/pseudo2d/C2.toml` writes
    if args.run:
        from febed.case import load_case

        skin = load_case(ROOT / MESHES["C2"]).contact.skin
        census = take_census(Path(args.run), args.t0, args.t1, skin)
        OUT.mkdir(parents=True, exist_ok=True)
        np.savez(cache, **{k: np.asarray(v) for k, v in census.items()})
    elif cache.is_file():
        census = dict(np.load(cache))
    else:
        print(
            "skipped: no census; give --run RUN_DIR, a C2 run folder with particle snapshots over the window "
            "(e.g. `febed run demos/pseudo2d/C2.toml --set run.end_time=5`, which writes runs/C2)"
        )
        return
    m1, m2 = load_measured("C2", 1), load_measured("C2", 2)
    if m1 is None:
        print(
            f"skipped: no serial measurement {OUT / 'measured_C2_P1.json'}: run "
            "`python benchmarks/scaling_measure.py --restart RUN_DIR` first"
        )
        return
    for P, tag, what in (
        (1, "_gamg", "the gas cost per node with CG + GAMG (taken as the serial solver's)"),
        (1, "_rebuild", "the parallel rebuild's own work and the COO fill (taken as zero)"),
        (2, "_concurrent", "the slow-down of a core while every core works (taken as none)"),
        (1, "_calls", "the exchange calls' own cost (taken as zero)"),
        (1, "_owners", "the coupling cost per particle through the particles' owners (taken as the cells')"),
        (1, "_staged", "the DEM's parallel code path on one process (taken as the serial one's)"),
        (2, "_calls", "the exchange calls' own cost (taken as zero)"),
    ):
        if load_measured("C2", P, tag) is None:
            print(f"note: no {OUT / f'measured_C2_P{P}{tag}.json'}: {what}; see the commands in the docstring")
    calls = load_measured("C2", 1, "_calls"), load_measured("C2", 2, "_calls")
    inputs = (
        load_measured("C2", 1, "_gamg"), load_measured("C2", 1, "_rebuild"), load_measured("C2", 2, "_concurrent"),
        calls if None not in calls else None, load_measured("C2", 1, "_owners"), load_measured("C2", 1, "_staged"),
    )  # fmt: skip
    cost = unit_costs(m1, *inputs)
    cost["h_ratio"] = float(census["C2/h_min"] / census["C3/h_min"])  # gas steps per second, fine / intermediate
    tags = args.check.split(",") if args.check else [""]
    factors = [
        load_factor(load_measured("C2", 1, t) or m1, loaded)
        for t in tags
        if t
        if (loaded := load_measured("C2", 2, f"{t}_concurrent")) is not None
    ]
    if len(factors) > 1:  # the projections take the busy-core slow-down of the check's rounds (median per phase)
        cost["load_factor"] = {k: float(np.median([f[k] for f in factors])) for k in factors[0]}
        cost["load_factor_rounds"] = len(factors)
    real = load_measured("C2", 2, tags[0]) if args.check else m2
    cost["solver"] = solver_counts(real)
    if cost["solver"] is None:
        return
    sf = cost["solver"]["scale"]
    print(
        f"pressure-solver counts scaled by the bubbling bed's over the benchmark's at 2 ranks: messages "
        f"{sf['messages']:.2f}, bytes {sf['bytes']:.2f}, reductions {sf['reductions']:.2f}"
    )
    for name in LEVELS:
        per_P = cost["solver"][name]
        print(
            f"{name}'s pressure solver per gas step on the busiest rank (P: messages, kB, reductions): "
            + ", ".join(
                f"{P}: {v['messages']:.0f}, {v['bytes'] / 1e3:.0f}, {v['reductions']:.0f}" for P, v in per_P.items()
            )
        )
    net = {"bandwidth": args.bandwidth, "latency": args.latency}
    times = np.asarray(census["times"])
    n_snap = times.size
    snap = slice(0, n_snap)
    print(f"census: {n_snap} snapshots of the bubbling bed, t = {times[0]:.2f}-{times[-1]:.2f} s")
    print(
        f"single-core costs (CPU time, serial C2 window t = {m1['per_rank'][0]['t0']:.3f} s + {cost['sim']:.3f} s): "
        f"{cost['us_per_pair_step'] * 1e3:.1f} ns per force pair per DEM step (on the parallel code path "
        f"{cost['us_per_pair_step_staged'] * 1e3:.1f}), "
        f"{cost['us_per_node_step']:.3f} µs per gas node per gas step (the serial default pressure solve; CG + GAMG "
        f"{cost['us_per_node_step_iter']:.3f}), "
        f"{cost['us_per_particle_step']:.3f} µs per particle per gas step (coupling); "
        f"{cost['gas_steps_per_s']:.0f} gas steps, {cost['dem_steps_per_s']:.0f} DEM steps, "
        f"{cost['builds_per_s']:.0f} list builds per simulated s (C3: {cost['h_ratio']:.2f} x the gas steps); "
        f"a parallel rebuild's own work {cost['us_per_pair_keyed_rebuild'] * 1e3:.1f} ns per listed pair (history by "
        f"key) + {cost['us_per_particle_locate'] * 1e3:.1f} ns per owned particle (locating)"
    )
    lf, cs = cost["load_factor"], cost["call_s"]
    rounds = f" (the median of the check's {cost['load_factor_rounds']} rounds)" if "load_factor_rounds" in cost else ""
    print(
        f"on several ranks: a core's costs times DEM {lf['dem']:.3f}, coupling {lf['coupling']:.3f}, gas "
        f"{lf['gas']:.3f} while every core works{rounds}; the drag-weighted operator's COO fill "
        f"{cost['us_per_entry_coo'] * 1e3:.2f} ns per entry ({cost['entries_per_node']:.1f} entries per node); "
        "exchange calls (µs beyond one process's): " + ", ".join(f"{k} {v * 1e6:.1f}" for k, v in cs.items())
    )
    print(
        f"interconnect: {args.bandwidth / 1e9:g} GB/s, {args.latency * 1e6:g} µs per message; reductions log2(P) "
        f"latencies"
    )
    needs = {"nodal": "C2/2/blocks/foreign_nodes"}
    variants = [v for v in VARIANTS if needs.get(v, f"{_keys('C2', 2, v)[0]}owned") in census]
    if len(variants) < len(VARIANTS):
        print("note: the cached census predates some decompositions; give --run RUN_DIR to count them")
    result = {"costs": cost, "net": net, **{_result_key(v): {} for v in variants}}
    for name in MESHES:
        label = "intermediate" if name == "C2" else "fine"
        for variant in variants:
            print(
                f"\n{name} ({label} mesh, {int(census[f'{name}/1/nodes'][0])} nodes), {VARIANTS[variant]}: loads "
                f"max/mean over ranks (mean over snapshots) and projected efficiency"
            )
            rows = efficiency_rows(census, name, cost, net, snap, variant)
            for r in rows:
                if r["P"] >= 8:
                    how = "" if variant == "cells" else f", {VARIANTS[variant]}"
                    print(
                        f"{name}{how}: projected efficiency at {r['P']} ranks: "
                        f"{r['E_total']:.0%} (DEM {r['E_dem']:.0%}, coupling {r['E_coupling']:.0%}, gas "
                        f"{r['E_gas']:.0%})"
                    )
            result[_result_key(variant)][name] = rows
    project_eq_limit(census, cost, net, snap, result)
    if census.get("checkpoint") is not None and bool(census["checkpoint"]):
        rounds = {}
        for tag in tags:
            if len(tags) > 1:
                print(f"\n== round {tag}")
            check_round(census, cost, inputs, net, m1, m2, tag, variants, result)
            if "measured" in result["validation"]:
                rounds[tag] = dict(result["validation"])
        if len(rounds) > 1:
            summarize_rounds(rounds, result)
    plot(result)
    (OUT / "scaling_projection.json").write_text(json.dumps(result, indent=1, default=float))


def project_eq_limit(census, cost, net, snap, result) -> None:
    """The projection with GAMG's `process_eq_limit` at EQ_LIMIT (the pressure solver's counts and busiest rank's
    flops from `SOLVER_COUNTS_EQ`, scaled as the default's), for febed's decomposition; nothing without them."""
    if not SOLVER_COUNTS_EQ.is_file():
        print(f"note: no {SOLVER_COUNTS_EQ}: no projection with GAMG's process_eq_limit {EQ_LIMIT}")
        return
    alt = solver_counts(path=SOLVER_COUNTS_EQ, scale=cost["solver"]["scale"])
    if alt is None:
        return
    flops = {n: {P: alt[n][P]["flops"] / cost["solver"][n][P]["flops"] for P in RANKS[1:]} for n in LEVELS}
    alt_cost = {**cost, "solver": alt, "solver_flops": flops}
    result["gamg_eq_limit"] = {"eq_limit": EQ_LIMIT}
    print(f"\nwith GAMG's process_eq_limit {EQ_LIMIT} (particles with their cells):")
    for name in MESHES:
        t1 = phase_times(census, name, 1, cost, net, snap)
        rows = []
        for P in RANKS[1:]:
            tp = phase_times(census, name, P, alt_cost, net, snap)
            e = {k: t1[k] / (P * tp[k]) for k in ("gas", "total")}
            rows.append({"P": P, "E_gas": e["gas"], "E_total": e["total"], "messages": alt[name][P]["messages"],
                         "flops_ratio": flops[name][P]})  # fmt: skip
        result["gamg_eq_limit"][name] = rows
        print(
            f"{name}: " + ", ".join(
                f"{r['P']}: {r['E_total']:.0%} (gas {r['E_gas']:.0%}, {r['messages']:.0f} messages, flops x"
                f"{r['flops_ratio']:.2f})" for r in rows
            )
        )  # fmt: skip


def check_round(census, cost, inputs, net, m1, m2, tag, variants, result) -> None:
    """The check of one round `tag` (its serial, 2-rank and concurrent windows): the model with the round's own
    costs per unit of work and busy-core slow-down (the rounds' median when several are checked, `cost`'s),
    against its 2-rank window (`validate`, `validate_work`)."""
    c1 = load_measured("C2", 1, tag) or m1
    c2 = load_measured("C2", 2, tag) if tag else m2
    check_cost = cost
    if c1 is not m1:  # the costs per unit of work of the code and window the check measured
        keep = ("h_ratio", "solver", "load_factor", "load_factor_rounds")
        check_cost = {**unit_costs(c1, *inputs, iter_of=m1), **{k: cost[k] for k in keep if k in cost}}
        print(
            f"\nthe check's own serial window: {check_cost['us_per_pair_step'] * 1e3:.1f} ns per force pair "
            f"per DEM step, {check_cost['us_per_node_step_iter']:.3f} µs per gas node per gas step (CG + "
            f"GAMG), {check_cost['us_per_particle_step']:.3f} µs per particle per gas step"
        )
    loaded = load_measured("C2", 2, f"{tag}_concurrent") if tag else None
    own = load_factor(c1, loaded) if loaded is not None else None
    if own is not None:
        print(f"\nthe round's own slow-down of a busy core: DEM {own['dem']:.3f}, coupling {own['coupling']:.3f}, "
              f"gas {own['gas']:.3f}")  # fmt: skip
        if "load_factor_rounds" not in cost:  # one round: its own; several: their median (cost's), the better estimate
            check_cost = {**check_cost, "load_factor": own}
    validate(census, check_cost, net, c1, c2, result)
    result["validation"]["load_factor"] = check_cost["load_factor"]
    if own is not None and "load_factor_rounds" in cost:  # the model with the round's own slow-down, for comparison
        ck = slice(-1, None)
        own_cost = {**check_cost, "load_factor": own}
        t1, t2 = phase_times(census, "C2", 1, own_cost, net, ck), phase_times(census, "C2", 2, own_cost, net, ck)
        result["validation"]["model_own_factor"] = t1["total"] / (2 * t2["total"])
    work = load_measured("C2", 2, f"{tag}_work") if tag else None
    if work is not None and "nodal" in variants:
        validate_work(census, check_cost, net, c1, work, result)


def summarize_rounds(rounds: dict, result) -> None:
    """The check over several rounds: each round's model and measured whole step, the median and range of the gap."""
    gaps = {t: 100 * (v["model"]["total"] - v["measured"]["total"]) for t, v in rounds.items()}
    lf = next(iter(rounds.values()))["load_factor"]
    print(
        f"\ncheck over the rounds (whole step, 1 -> 2 ranks), a busy core's slow-down the rounds' median (DEM "
        f"{lf['dem']:.3f}, coupling {lf['coupling']:.3f}, gas {lf['gas']:.3f}):"
    )
    own = {}
    for t, v in rounds.items():
        extra = ""
        if "model_own_factor" in v:
            own[t] = 100 * (v["model_own_factor"] - v["measured"]["total"])
            extra = f"; with the round's own slow-down {v['model_own_factor']:.1%} ({own[t]:+.1f})"
        print(
            f"  {t}: measured {v['measured']['total']:.1%}, model {v['model']['total']:.1%} ({gaps[t]:+.1f} points)"
            + extra
        )
    g = np.array(list(gaps.values()))
    within = int(np.sum(np.abs(g) <= 5.0))
    print(
        f"check: model - measured over {g.size} rounds: median {np.median(g):+.1f} points, from {g.min():+.1f} to "
        f"{g.max():+.1f}; within 5 points in {within} of {g.size}"
    )
    if own:
        o = np.array(list(own.values()))
        print(
            f"  with each round's own slow-down: median {np.median(o):+.1f} points, from {o.min():+.1f} to "
            f"{o.max():+.1f}; within 5 points in {int(np.sum(np.abs(o) <= 5.0))} of {o.size}"
        )
    result["validation_rounds"] = {
        "gaps": gaps, "median": float(np.median(g)), "within_5": within,
        "measured": [v["measured"]["total"] for v in rounds.values()],
        "model": [v["model"]["total"] for v in rounds.values()],
    }  # fmt: skip


def _result_key(variant: str) -> str:
    """The result's table of a decomposition: meshes (febed's), meshes_work, meshes_blocks."""
    return "meshes" if variant == "cells" else f"meshes_{variant}"


def efficiency_rows(census: dict, name: str, cost: dict, net: dict, snap: slice, variant: str) -> list[dict]:
    """Per rank count: the loads (max/mean), the bytes per gas step and the projected efficiencies (printed)."""
    t1 = phase_times(census, name, 1, cost, net, snap)
    print(
        f"{'P':>3} {'particles':>9} {'ghosts/own':>10} {'pairs':>6} {'nodes':>6} {'halo/node':>9} "
        f"{'kB/gas step':>11} {'E_DEM':>6} {'E_cpl':>6} {'E_gas':>6} {'E':>6}"
    )
    rows = []
    for P in RANKS:
        tp = phase_times(census, name, P, cost, net, snap, variant)
        key, gkey = _keys(name, P, variant)
        own = census[f"{key}owned"][snap]
        mm = lambda a: float(np.mean(a.max(axis=1) / np.maximum(a.mean(axis=1), 1)))  # noqa: E731
        ghost = float(np.mean(census[f"{key}ghosts"][snap].sum(axis=1) / own.sum(axis=1)))
        nodes = census[f"{gkey}nodes"]
        halo = float(census[f"{gkey}halo"].max() / max(nodes.min(), 1))
        n_sub = cost["dem_steps_per_s"] / (cost["gas_steps_per_s"] * (cost["h_ratio"] if name != "C2" else 1))
        kb = float(np.mean(census[f"{key}sent"][snap].max(axis=1))) * UPDATE_BYTES * n_sub / 1e3
        kb += float(census[f"{gkey}halo"].max()) * GAS_EXCHANGES * GAS_VALUES * 8 / 1e3
        kb += cost["solver"][name][P]["bytes"] / 1e3 if P > 1 else 0.0
        if variant == "nodal" and P > 1:
            kb += float(np.mean(census[f"{key}foreign_nodes"][snap].max(axis=1))) * NODAL_BYTES / 1e3
        elif key != f"{name}/{P}/":
            moved = census[f"{key}transfer_out"][snap] + census[f"{key}transfer_in"][snap]
            kb += float(np.mean(moved.max(axis=1))) * TRANSFER_BYTES / 1e3
        e = {k: t1[k] / (P * tp[k]) for k in ("dem", "coupling", "gas", "total")}
        rows.append(
            {
                "P": P,
                "particles": mm(own),
                "ghost_ratio": ghost,
                "pairs": mm(census[f"{key}force_pairs"][snap]),
                "nodes": mm(nodes[None, :]),
                "halo_per_node": halo,
                "kB_per_gas_step": kb,
                **{f"E_{k}": v for k, v in e.items()},
                "time": tp,
            }
        )
        print(
            f"{P:3d} {mm(own):9.3f} {ghost:10.3f} {rows[-1]['pairs']:6.3f} {rows[-1]['nodes']:6.3f} "
            f"{halo:9.3f} {kb:11.1f} {e['dem']:6.1%} {e['coupling']:6.1%} {e['gas']:6.1%} {e['total']:6.1%}"
        )
    return rows


def validate(census, cost, net, m1, m2, result) -> None:
    """The model's 2-rank efficiency of C2 on the checkpoint's state against measured ones.

    The reference is m2, a 2-rank window measured from the same checkpoint (run it with nothing else on the
    machine), whose loads per rank are compared too; without it, the documented measurements (`DOCUMENTED`).
    """
    ck = slice(-1, None)  # the last census row is the checkpoint the measured windows continue
    t1 = phase_times(census, "C2", 1, cost, net, ck)
    t2 = phase_times(census, "C2", 2, cost, net, ck)
    model = {k: t1[k] / (2 * t2[k]) for k in ("dem", "coupling", "gas", "total")}
    r1 = m1["per_rank"][0]
    print(f"\nvalidation, C2 from its checkpoint at t = {r1['t0']:.3f} s, 1 -> 2 ranks:")
    result["validation"] = {"model": model, "documented": DOCUMENTED}
    if m2 is not None:
        meas = measured_efficiency(m1, m2)
        e_wall = meas.pop("wall")
        for r in m2["per_rank"]:
            s = r["samples"][0]
            c = {k: int(census[f"C2/2/{k}"][-1][r["rank"]]) for k in ("owned", "ghosts", "pairs")}
            print(
                f"  rank {r['rank']}: run owned {s['owned']}, ghosts {s['ghosts']}, listed pairs {s['pairs']}, "
                f"owned nodes {s['nodes_owned']}, local nodes {s['nodes_local']}; census owned {c['owned']}, ghosts "
                f"{c['ghosts']}, listed pairs {c['pairs']}, owned nodes {census['C2/2/nodes'][r['rank']]:.0f}, "
                f"local nodes {census['C2/2/nodes'][r['rank']] + census['C2/2/halo'][r['rank']]:.0f}"
            )
        print(
            f"  this machine's 2-rank window (CPU seconds of the slowest rank per phase; a shared machine adds "
            f"waits for descheduled ranks): DEM {meas['dem']:.1%}, coupling {meas['coupling']:.1%}, gas "
            f"{meas['gas']:.1%}, whole step {meas['total']:.1%}; wall time {e_wall:.1%}"
        )
        result["validation"].update({"measured": meas, "measured_wall": e_wall})
    avg = result["meshes"]["C2"][1]["E_total"]
    ref = list(DOCUMENTED.items())
    print(f"  documented: {ref[0][0]} {ref[0][1]:.1%}")
    reference = result["validation"]["measured"]["total"] if m2 is not None else ref[0][1]
    own = "; the 2-rank window of the same checkpoint" if m2 is not None else "; the documented window"
    result["validation"]["reference"] = reference
    print(
        f"  model: checkpoint state DEM {model['dem']:.1%}, coupling {model['coupling']:.1%}, gas "
        f"{model['gas']:.1%}, whole step {model['total']:.1%}; mean over the census snapshots {avg:.1%}"
    )
    print(
        f"validation: model 2-rank efficiency {model['total']:.1%} against {reference:.1%} measured "
        f"({100 * (model['total'] - reference):+.1f} points{own})"
    )
    result["validation"]["model_snapshots"] = avg
    pace = core_pace(m1, m2) if m2 is not None else None
    if pace is not None:  # the model on the cores the window ran on: each gas step at the slower core's pace
        on_cores = model["total"] / pace["uneven"]
        result["validation"].update({"core_pace": pace, "model_on_cores": on_cores})
        print(
            f"  the cores' pace in the 2-rank window (`--core-speed`, {pace['samples']} gas steps): the slower core "
            f"{pace['uneven']:.3f} of the two cores' mean (equal cores: 1), the two cores' mean "
            f"{pace['busy']:.3f} of the serial window's core"
        )
        print(
            f"validation on the window's cores: model {on_cores:.1%} (its equal cores' {model['total']:.1%} over "
            f"{pace['uneven']:.3f}) against {reference:.1%} measured ({100 * (on_cores - reference):+.1f} points)"
        )
        if pace.get("latency") is not None:  # the model with the messages' latency of the window
            lat = pace["latency"]
            t2w = phase_times(census, "C2", 2, cost, {**net, "latency": lat}, ck)
            on_window = t1["total"] / (2 * t2w["total"]) / pace["uneven"]
            result["validation"]["model_on_window"] = on_window
            print(
                f"  messages in the window: half a round trip {1e6 * pace['latency_median']:.2f} µs (median), "
                f"{1e6 * lat:.2f} µs (mean; the model's latency {1e6 * net['latency']:.2f} µs)"
            )
            if pace.get("memory_gbs"):
                gbs = ", ".join(f"{g:.1f}" for g in pace["memory_gbs"])
                print(f"  a pass over 16 MB on both ranks at once: {gbs} GB/s per rank (median)")
            print(
                f"validation on the window's cores and messages: model {on_window:.1%} against {reference:.1%} "
                f"measured ({100 * (on_window - reference):+.1f} points)"
            )


def core_pace(m1: dict, m2: dict, smooth: int = 5) -> dict | None:
    """How unevenly the cores ran in a 2-rank window, from `scaling_measure.py --core-speed` samples.

    Each rank timed a fixed loop before every gas step. A gas step exchanges between the ranks many times, so
    it goes at the pace of the rank whose core is slower at that moment. `uneven` = Σ_steps max over ranks /
    Σ_steps mean over ranks of the loop's time (1 for equal cores): the factor by which cores of equal mean
    speed but unequal moment-to-moment speed slow a run that the model counts on equal cores. `busy` = the
    cores' mean time over the serial window's (what the model's load factor stands for). Each rank's series
    is a running median over `smooth` gas steps first (a timer interrupt during one loop is not the core's
    pace; the host's other work changes it over seconds). `latency` (`latency_median`): the mean (median)
    half round trip of 8 bytes between the ranks, timed before every gas step; `memory_gbs`: each rank's median
    GB/s over its 16 MB pass, both ranks at once (every 4th gas step). None without samples.
    """
    rows = [r.get("core_probe") for r in m2["per_rank"]]
    one = m1["per_rank"][0].get("core_probe")
    if not one or any(not r for r in rows):
        return None
    n = min(len(r) for r in rows)
    a = np.array([r[:n] for r in rows])
    if n >= smooth:
        win = np.lib.stride_tricks.sliding_window_view(a, smooth, axis=1)
        a = np.median(win, axis=2)
    uneven = float(np.sum(a.max(axis=0)) / np.sum(a.mean(axis=0)))
    out = {"uneven": uneven, "busy": float(np.mean(a) / np.median(one)), "samples": n}
    msg = m2["per_rank"][0].get("message_probe")
    if msg:
        out.update({"latency": float(np.mean(msg)), "latency_median": float(np.median(msg))})
    mem = [r.get("memory_probe") for r in m2["per_rank"]]
    if all(mem):  # GB/s of each rank's pass over its 16 MB, both at once
        out["memory_gbs"] = [float(16 * (1 << 20) / np.median(m) / 1e9) for m in mem]
    return out


def measured_efficiency(m1: dict, m2: dict) -> dict:
    """Per phase and whole step, from the CPU seconds of the slowest rank in each phase; "wall" from wall time."""
    r1 = m1["per_rank"][0]
    sim1 = r1["t1"] - r1["t0"]
    sim2 = m2["per_rank"][0]["t1"] - m2["per_rank"][0]["t0"]
    one = {k: v / sim1 for k, v in r1["split"].items()}
    two = {k: max(r["split"][k] for r in m2["per_rank"]) / sim2 for k in one}
    meas = {k: one[k] / (2 * two[k]) for k in ("dem", "coupling", "gas")}
    meas["total"] = sum(one.values()) / (2 * sum(two.values()))
    meas["wall"] = r1["wall"] / sim1 / (2 * max(r["wall"] for r in m2["per_rank"]) / sim2)
    return meas


def validate_work(census, cost, net, m1, m2, result) -> None:
    """The model's 2-rank efficiency of the particles by work (mesh in blocks, coupled by the particles' owners)
    on the checkpoint's state, against a 2-rank window run with `particle_partition = "work"`."""
    ck = slice(-1, None)
    t1 = phase_times(census, "C2", 1, cost, net, ck)
    t2 = phase_times(census, "C2", 2, cost, net, ck, "nodal")
    model = {k: t1[k] / (2 * t2[k]) for k in ("dem", "coupling", "gas", "total")}
    meas = measured_efficiency(m1, m2)
    result["validation_work"] = {"model": model, "measured": meas}
    print(
        f"validation, particles by work: model DEM {model['dem']:.1%}, coupling {model['coupling']:.1%}, gas "
        f"{model['gas']:.1%}, whole step {model['total']:.1%}; measured DEM {meas['dem']:.1%}, coupling "
        f"{meas['coupling']:.1%}, gas {meas['gas']:.1%}, whole step {meas['total']:.1%} (wall {meas['wall']:.1%}): "
        f"{100 * (model['total'] - meas['total']):+.1f} points"
    )


def plot(result) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 6), sharey=True)
    for ax, (name, rows) in zip(axes, result["meshes"].items(), strict=True):
        P = [r["P"] for r in rows]
        for key, lab, st in (
            ("E_total", "whole step", "k-o"),
            ("E_dem", "DEM", "C0-s"),
            ("E_coupling", "coupling", "C2-^"),
            ("E_gas", "gas", "C1-d"),
        ):
            ax.plot(P, [r[key] for r in rows], st, label=lab)
        for key, lab, st in (("E_total", "whole step", "k--o"), ("E_dem", "DEM", "C0--s")):
            work = result["meshes_work"][name]
            ax.plot(P, [r[key] for r in work], st, mfc="none", label=f"{lab}, particles by DEM work")
        for variant, st, lab in (
            ("blocks", "m:D", "whole step, particles by DEM work, gas in blocks"),
            ("nodal", "g-.v", "whole step, particles by DEM work, gas in blocks, coupled by the particles' owners"),
        ):
            if f"meshes_{variant}" in result:
                rows_v = result[f"meshes_{variant}"][name]
                ax.plot(P, [r["E_total"] for r in rows_v], st, mfc="none", label=lab)
        if name == "C2" and "validation" in result:
            v = result.get("validation_rounds")  # every round of the check, else the one
            meas = v["measured"] if v else [result["validation"]["reference"]]
            model = v["model"] if v else [result["validation"]["model"]["total"]]
            ax.plot([2] * len(meas), meas, "r*", ms=12, label="measured, 2 ranks, the checkpoint's state")
            ax.plot([2] * len(model), model, "ko", mfc="none", ms=11, label="model, same state as measured")
        ax.axhline(0.7, color="0.6", lw=0.8, ls="--")
        ax.set_xscale("log", base=2)
        ax.set_xticks(P, [str(p) for p in P])
        ax.set_xlabel("ranks")
        ax.set_title(f"{name} ({'intermediate' if name == 'C2' else 'fine'} mesh)")
        ax.set_ylim(0, 1.05)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("projected parallel efficiency")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.2, 1, 1))
    fig.savefig(OUT / "scaling_projection.png", dpi=120)
    print(f"\nwritten {OUT / 'scaling_projection.png'}")


if __name__ == "__main__":
    main()
