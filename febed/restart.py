"""Checkpoint and restart of a run: what the state is, and which case changes a restart accepts.

A pure-DEM run (`febed.runs.dem.DEMRun`) checkpoints the particle part below (`dem_arrays`, `load_dem`)
with its particle-output schedule, a gas-only run (`febed.runs.gas.GasRun`) the gas part (`gas_arrays`,
`restore_gas`) with its field-output schedule; every checkpoint records its run mode and continues only that
mode.

The state of a coupled run (`capture`) is

* the gas (`VANSSolver.get_state`): superficial velocity, pressure, void fraction, pressure gradient and the
  last pressure increment (the warm start of the next Poisson solve), at the owned nodes with their
  coordinates, so that a restart on another number of ranks finds its nodes by position;
* the particles (`DEM.get_state`): every particle array by row, the contact history keyed by global-id
  pairs, and — on one rank — the pair and wall lists themselves, the neighbour-list reference positions and
  sort counters, so that a serial restart continues bit for bit;
* the coupled loop's counters (time, gas steps, particles removed, timers, the random generator) and the
  run's output schedule (next probe / field / particle times, files written so far).

Restarting on another number of ranks keeps every particle and its contact history; only the neighbour
lists are rebuilt, so results agree to round-off rather than bit for bit.

A restart may change how the run is driven and written (`CHANGEABLE`: end time, output intervals, gas
time-step bounds, solver options, failure limits) but not the physics or the geometry: any other changed
key is refused with the list of differences.

Every checkpoint records what it belongs to (`febed.io.checkpoint.identity`): a digest of the physics keys
of its case (every key but the `CHANGEABLE` ones, `physics_digest`), its mesh (node count and bounding box,
from the gas nodes) and its particles (how many it holds and how many have left the domain). `febed run
--restart CHECKPOINT` compares them with the case and its mesh (`checkpoint_differences`) and refuses
another run's checkpoint with the list of differences, before anything is written.
"""

from __future__ import annotations

import dataclasses
import tomllib
from fnmatch import fnmatch
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed.io.checkpoint import CheckpointError, gather_rows, match_nodes
from febed.io.rundir import RESOLVED_CASE
from febed.schema import BOUNDARY, CHANGEABLE, SCHEMA, flatten_keys, physics_digest

RESTARTABLE = ("cfd-dem", "dem", "gas")  # [run] modes whose runs write checkpoints and continue from them
_ROWS = "p_"  # DEM state keys holding one row per particle
_HISTORY = ("saved_keys", "saved_vals", "saved_wkeys", "saved_wvals")


# ------------------------------------------------------------------------------------------ case changes
def _is_default(key: str, value) -> bool:
    """Whether `value` is the schema default of the case key `section.name` or `gas.boundary.<tag>.name`."""
    parts = key.split(".")
    if len(parts) == 4 and parts[:2] == ["gas", "boundary"]:
        param = BOUNDARY.get(parts[3])
    else:
        section, _, name = key.partition(".")
        param = SCHEMA.get(section, {}).get(name)
    return param is not None and value == param.default


def case_changes(old_toml: str, new_toml: str) -> tuple[list[str], list[str]]:
    """Changed keys between two resolved cases, split into (accepted, refused) lines `key: old -> new`."""
    old, new = flatten_keys(tomllib.loads(old_toml)), flatten_keys(tomllib.loads(new_toml))
    accepted, refused = [], []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key, "(unset)"), new.get(key, "(unset)")
        if a == b or key in ("output.directory", "run.name", "extends"):
            continue
        if a == "(unset)" and _is_default(key, b):  # a key febed gained since the checkpoint, at its default
            continue
        line = f"{key}: {a!r} -> {b!r}"
        (accepted if any(fnmatch(key, pat) for pat in CHANGEABLE) else refused).append(line)
    return accepted, refused


def checkpoint_differences(ident: dict, meta: dict, case, mesh: dict | None, particles: int | None) -> list[str]:
    """What makes a checkpoint another run's than `case`'s: lines `what: checkpoint -> case` (empty: the same run).

    Args:
        ident: the checkpoint's identity (`febed.io.checkpoint.identity`).
        meta: its meta record (its `case`, when recorded, lists the changed physics keys one by one).
        case: the case to continue.
        mesh: `febed.preflight.mesh_identity` of the case's mesh (None: not compared).
        particles: the particles the case starts with (None: not compared).
    """
    lines: list[str] = []
    toml = case.to_toml()
    if meta.get("case"):
        lines += case_changes(meta["case"], toml)[1]
    elif ident.get("physics") and ident["physics"] != physics_digest(toml):
        lines.append("physics keys: the checkpoint's digest differs from the case's (it records no case to list them)")
    m = ident.get("mesh")
    if m and mesh:
        if m["nodes"] != mesh["nodes"]:
            lines.append(f"mesh nodes: {m['nodes']} -> {mesh['nodes']}")
        lo, hi = np.array(m["bounds"][:3]), np.array(m["bounds"][3:])
        tol = 1e-9 * max(float(np.max(hi - lo)), 1e-300)
        if np.max(np.abs(np.array(m["bounds"]) - np.array(mesh["bounds"]))) > tol:
            lines.append(f"mesh bounds: {_box(m['bounds'])} -> {_box(mesh['bounds'])}")
    n = ident.get("particles")
    if n is not None and particles is not None and case.coarse_grain.model != "pcpm":  # pcpm groups crush and merge
        left = ident.get("left")
        if left is not None and n + left != particles:
            was = f"{n + left} ({n} in the checkpoint, {left} left the domain)"
            lines.append(f"particles at the start: {was} -> {particles}")
        elif left is None and n > particles:
            lines.append(f"particles: {n} in the checkpoint -> {particles} in the case")
    return lines


def _box(b) -> str:
    return f"[{', '.join(f'{v:.6g}' for v in b[:3])}] to [{', '.join(f'{v:.6g}' for v in b[3:])}] m"


# ------------------------------------------------------------------------------------------ the state
def capture(run) -> tuple[dict[str, np.ndarray], dict]:
    """This rank's state of a `CoupledRun` (copies): arrays and a JSON-able meta record."""
    s = run.solver
    arrays = gas_arrays(s.gas)
    arrays.update(dem_arrays(s.dem))
    meta = {
        "time": s.t,
        "step": s.steps,
        "ranks": run.comm.size,
        "mode": run.case.run.mode,
        "solver": {
            "left_outlet": run.comm.allreduce(s.left_outlet),
            "n_sub": s.n_sub,
            "timers": s.timers.as_dict(),
            "last_gas": dataclasses.asdict(s.last_gas) if s.last_gas is not None else None,
            "rng": s.rng.bit_generator.state,
            "groups": s.groups.state_dict() if s.groups is not None else None,
        },
        "run": run.schedule(),
    }
    return arrays, meta


def gas_arrays(gas) -> dict[str, np.ndarray]:
    """This rank's gas state as checkpoint arrays `gas/<key>` (copies), with the owned nodes' coordinates."""
    arrays = {f"gas/{k}": v for k, v in gas.get_state().items()}
    arrays["gas/x"] = gas.x[: gas.n_owned].copy()
    return arrays


def restore_gas(gas, arrays: dict[str, np.ndarray], t: float, comm=MPI.COMM_WORLD) -> None:
    """Put a checkpoint's `gas/` arrays into `gas` at time t, finding this rank's nodes by position (collective)."""
    n = gas.n_owned
    width = float(np.min(gas.ops.width[:n], initial=np.inf))
    h = comm.allreduce(width, op=MPI.MIN)
    idx = match_nodes(arrays["gas/x"], gas.x[:n], h)
    gas.set_state({k[4:]: v[idx] for k, v in arrays.items() if k.startswith("gas/") and k != "gas/x"}, t)


def dem_arrays(dem) -> dict[str, np.ndarray]:
    """This rank's DEM state as checkpoint arrays `dem/<key>` (copies), the contact history keyed by gids too."""
    state = dem.get_state()
    if "saved_keys" not in state and int(state.get("lists_valid", 0)):  # one rank: the lists hold the history;
        (k, v), (wk, wv) = dem._history_keys()  # keyed by gids too, for a restart on other rank counts
        state.update(keyed_keys=k, keyed_vals=v, keyed_wkeys=wk, keyed_wvals=wv)
    return {f"dem/{k}": np.array(v, copy=True) for k, v in state.items()}


def gather(arrays: dict[str, np.ndarray], meta: dict, comm=MPI.COMM_WORLD) -> dict[str, np.ndarray]:
    """The rank-count-independent checkpoint arrays on rank 0 (one rank: the state unchanged)."""
    if comm.size == 1:
        return arrays
    rows = {k: v for k, v in arrays.items() if k.startswith("gas/") or k.startswith(f"dem/{_ROWS}")}
    rows.update({f"dem/{k}": arrays[f"dem/{k}"] for k in _HISTORY if f"dem/{k}" in arrays})
    out = gather_rows(rows, comm)
    if "dem/p_gid" not in arrays:  # a gas-only run
        return out
    scalars = ("time", "steps", "dt", "pl_skin", "pl_builds", "max_overlap", "walls_count")
    top = comm.allreduce(int(arrays["dem/p_gid"].max(initial=-1)), op=MPI.MAX)
    if comm.rank == 0:
        for k in _HISTORY[::2]:  # cross-partition pairs are held by both ranks: keep each key once
            key, val = f"dem/{k}", f"dem/{k.replace('keys', 'vals')}"
            if key in out:
                out[key], first = np.unique(out[key], return_index=True)
                out[val] = out[val][first]
        out.update({f"dem/{k}": arrays[f"dem/{k}"] for k in scalars if f"dem/{k}" in arrays})
        out["dem/p_next_gid"] = np.array(top + 1)  # each rank gets its own block above it on restart
        out["dem/has_saved"] = np.array(int("dem/saved_keys" in out))
        out["dem/lists_valid"] = np.array(0)
        out["dem/dirty"] = np.array(1)
    return out


def restore(run, arrays: dict[str, np.ndarray], meta: dict) -> None:
    """Put a checkpoint's state into a freshly built `CoupledRun` (every rank holds the whole checkpoint)."""
    s = run.solver
    comm = run.comm
    restore_gas(s.gas, arrays, meta["time"], comm)
    reload_particles(run, arrays, meta)
    sm = meta["solver"]
    s.t, s.steps = float(meta["time"]), int(meta["step"])
    s.left_outlet = int(sm["left_outlet"]) if comm.rank == 0 else 0  # the total, counted once
    s.n_sub = int(sm["n_sub"])
    for k, v in sm["timers"].items():
        setattr(s.timers, k.removeprefix("wall_"), float(v))
    if sm["last_gas"] is not None:
        from febed.gas.vans import StepInfo

        s.last_gas = StepInfo(**sm["last_gas"])
    s.rng.bit_generator.state = sm["rng"]
    if s.groups is not None and sm.get("groups"):
        s.groups.load_state_dict(sm["groups"])
    run.set_schedule(meta["run"])


def reload_particles(run, arrays: dict[str, np.ndarray], meta: dict) -> None:
    """Put a checkpoint's particles into the DEM (every rank holds the whole checkpoint; collective).

    One process reading a one-process checkpoint takes the DEM state as it was, neighbour lists included.
    Otherwise every rank takes its share of the particles in global-id order, their contact history by gid
    pairs, and the lists are rebuilt at the next step. Running on several ranks, `CoupledRun.checkpoint`
    passes every checkpoint it writes through here too, so that a run continued from a checkpoint and the
    run that wrote it go on from the same particle layout.
    """
    s = run.solver
    load_dem(s.dem, arrays, meta, run.comm.size)
    s.reset_coupling()  # locate the particles and recompute α_p as at the end of the last step


def load_dem(dem, arrays: dict[str, np.ndarray], meta: dict, ranks: int) -> None:
    """Put a checkpoint's `dem/` arrays into `dem` (every rank holds the whole checkpoint; collective).

    A one-rank checkpoint read by one process continues bit for bit; otherwise see `reload_particles`.
    """
    state = {k[4:]: v for k, v in arrays.items() if k.startswith("dem/")}
    same_layout = meta["ranks"] == ranks == 1
    if not same_layout:
        state = _portable(state)
    dem.set_state(state)
    if not same_layout:  # cell indices are rank-local: search the restored particles afresh
        dem.particles.cell[: dem.particles.n_owned] = -1
    if dem.exchange is not None:  # every rank holds every particle: keep this rank's share
        dem.exchange.distribute(dem.particles)


def _portable(dem: dict) -> dict:
    """A DEM state in global-id order without the rank-local neighbour lists (rebuilt from the keyed history)."""
    out = {k: v for k, v in dem.items() if not k.startswith(("pl_start", "pl_nbr", "pl_hist", "w_", "keyed_"))}
    if "keyed_keys" in dem and "saved_keys" not in dem:  # a one-rank checkpoint: its history keyed by gids
        out.update({f"saved_{k[6:]}": dem[k] for k in dem if k.startswith("keyed_")})
        out["has_saved"] = 1
    order = np.argsort(out["p_gid"], kind="stable")
    out.update({k: np.asarray(v)[order] for k, v in out.items() if k.startswith(_ROWS) and k != "p_next_gid"})
    out["lists_valid"], out["dirty"], out["forces_valid"] = 0, 1, 0
    out["pos_ref"] = np.array(out["p_pos"], copy=True)  # lists are rebuilt at the first step
    return out


def check_restartable(meta: dict, case) -> None:
    """Raise CheckpointError if the checkpoint cannot continue this case (e.g. it is already past its end)."""
    mode = meta.get("mode", "cfd-dem")  # older coupled checkpoints carry no mode
    if mode != case.run.mode:
        raise CheckpointError(
            f"the checkpoint is of a [run] mode = {mode!r} run, the case is {case.run.mode!r}: a run continues "
            "in its own mode"
        )
    if meta["time"] >= case.run.end_time * (1 - 1e-12):
        raise CheckpointError(
            f"the checkpoint is at t = {meta['time']:.6g} s, not before run.end_time = {case.run.end_time:g} s: "
            "nothing to do (raise end_time with --set run.end_time=... to continue)"
        )


def read_resolved(outdir: Path) -> str:
    """The resolved case a run folder was started with."""
    return (Path(outdir) / RESOLVED_CASE).read_text()
