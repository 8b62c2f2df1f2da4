"""Checkpoint and restart of a run: what the state is, and which case changes a restart accepts.

The arrays of the gas and DEM states are `febed.io.state`'s. A pure-DEM run (`febed.runs.dem.DEMRun`)
checkpoints the particle part (`dem_arrays`, `load_dem`) with its particle-output schedule, a gas-only run
(`febed.runs.gas.GasRun`) the gas part (`gas_arrays`, `restore_gas`) with its field-output schedule, a one-way
run (`febed.runs.oneway.OneWayRun`) the particle part with its driver's counters and particle-output schedule;
every checkpoint records its run mode and continues only that mode.

The state of a coupled run (`capture`: `CoupledSolver.get_state` and the run's schedule) is

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

import tomllib
from fnmatch import fnmatch
from pathlib import Path

import numpy as np

from febed.io.checkpoint import CheckpointError
from febed.io.rundir import RESOLVED_CASE
from febed.schema import BOUNDARY, CHANGEABLE, SCHEMA, flatten_keys, physics_digest

RESTARTABLE = ("cfd-dem", "dem", "gas", "one-way")  # [run] modes whose runs write checkpoints and continue from them


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
    """This rank's state of a `CoupledRun` (copies): the solver's arrays and a JSON-able meta record."""
    arrays, record = run.solver.get_state()
    meta = {
        "time": record["time"],
        "step": record["step"],
        "ranks": run.comm.size,
        "mode": run.case.run.mode,
        "solver": {k: v for k, v in record.items() if k not in ("time", "step")},
        "run": run.schedule(),
    }
    return arrays, meta


def restore(run, arrays: dict[str, np.ndarray], meta: dict) -> None:
    """Put a checkpoint's state into a freshly built `CoupledRun` (every rank holds the whole checkpoint)."""
    run.solver.set_state(arrays, {"time": meta["time"], "step": meta["step"], **meta["solver"]}, meta["ranks"])
    run.set_schedule(meta["run"])


def reload_particles(run, arrays: dict[str, np.ndarray], meta: dict) -> None:
    """Put a checkpoint's particles into the DEM (every rank holds the whole checkpoint; collective).

    One process reading a one-process checkpoint takes the DEM state as it was, neighbour lists included.
    Otherwise every rank takes its share of the particles in global-id order, their contact history by gid
    pairs, and the lists are rebuilt at the next step. Running on several ranks, `CoupledRun.checkpoint`
    passes every checkpoint it writes through here too, so that a run continued from a checkpoint and the
    run that wrote it go on from the same particle layout.
    """
    run.solver.load_particles(arrays, meta["ranks"])


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
