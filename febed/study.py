"""Parameter studies: a family of runs of one base case varying named parameters, resumable, compared.

A study file (TOML):

    [study]
    base = "C1.toml"                 # the case every member starts from (relative to this file)
    name = "mesh"                    # default: this file's stem
    directory = "out/mesh"           # members' output folders go in here (relative to this file);
                                     # default ./runs/<name>
    combine = "product"              # "product" of the parameter lists, or "zip" (equal lengths, paired)
    set = ["run.end_time = 5.0"]     # overrides common to every member
    ranks = 1                        # processes per run; > 1 runs `mpirun -n ranks ...`
    mpirun = "mpirun -n {ranks}"     # launcher template when ranks > 1
    window = [2.0, 5.0]              # averaging window of the comparison (s); default the last half of each run

    [parameters]                     # named parameters and their values
    "mesh.level" = ["coarse", "intermediate", "fine"]

    [cases.extra]                    # optional explicit members: name -> overrides
    "contact.friction_pw" = 0.4

Each member is `febed run BASE --set <its values> --set <study set> --set output.directory=<dir>/<member>`,
run one after another (`run_study`), or written as command lines for separate jobs (`job_lines`).

A member's state comes from `<its folder>/status.json` ({"state": "running" | "finished" | "failed" |
"interrupted", "time": t, "end_time": T}, written by `febed run`):

* finished -> skipped;
* live (status "running" and its process still alive on this machine, e.g. a member submitted as a separate
  job) -> skipped and reported;
* running or interrupted -> resumed with `febed run ... --restart` (a run found "running" whose process is
  gone was killed);
* failed -> skipped and reported, re-run from scratch with `retry_failed` (`--overwrite`);
* no folder -> run. A febed folder without status.json (older runs) counts as finished when its probes or
  particle output reach the end time (within min(1e-3 end_time, gas.dt_max)), else as interrupted.

`collect` compares the members: mean and spread of the bed pressure drop (and its ratio to the bed weight
per cross-section) and of the bed height over the window, the vertical solid flux in the bed's centre at
z/H = 0.092, in `<directory>/comparison/comparison.csv`, with figures of each quantity against each varied
parameter and the members' flux profiles overlaid.
"""

from __future__ import annotations

import itertools
import json
import math
import re
import shlex
import subprocess
import sys
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from febed.case import CaseError, load_case
from febed.post.collect import Comparison, compare_members
from febed.post.rundata import list_snapshots, read_case, read_status
from febed.post.series import read_series

STATES = ("new", "live", "running", "interrupted", "finished", "failed")
_STUDY_KEYS = {"base", "name", "directory", "combine", "set", "ranks", "mpirun", "window"}


@dataclass
class Member:
    """One run of a study: its name, parameter values, the overrides that make it, its output folder."""

    name: str
    values: dict[str, object]
    overrides: list[str]
    directory: Path

    def command(self, study: Study, restart: bool = False, overwrite: bool = False) -> list[str]:
        """The command line that runs (or, with `restart`, resumes) this member."""
        cmd = [sys.executable, "-m", "febed.cli", "run", str(study.base)]
        for ov in [*self.overrides, *study.common, f"output.directory={self.directory}"]:
            cmd += ["--set", ov]
        if restart:
            cmd.append("--restart")
        if overwrite:
            cmd.append("--overwrite")
        if study.ranks > 1:
            cmd = [*shlex.split(study.mpirun.format(ranks=study.ranks)), *cmd]
        return cmd


@dataclass
class Study:
    """A loaded study file (see the module docstring)."""

    path: Path
    name: str
    base: Path
    directory: Path
    members: list[Member]
    parameters: dict[str, list]
    common: list[str] = field(default_factory=list)
    ranks: int = 1
    mpirun: str = "mpirun -n {ranks}"
    window: tuple[float, float] | None = None


def _toml_text(v) -> str:
    """A value as `--set` expects it (TOML; bare strings stay strings)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf")
    if isinstance(v, str):
        return v
    if isinstance(v, list):
        return "[" + ", ".join(json.dumps(x) if isinstance(x, str) else _toml_text(x) for x in v) + "]"
    raise ValueError(f"parameter value {v!r}: expected a number, string, boolean or list")


def _label(key: str, v) -> str:
    text = _toml_text(v) if not isinstance(v, str) else v
    return re.sub(r"[^A-Za-z0-9._+-]+", "-", f"{key.rsplit('.', 1)[-1]}-{text}").strip("-")


def load_study(path: str | Path) -> Study:
    """Read and check a study file; every member's case is validated (febed.case) before anything runs."""
    path = Path(path).expanduser().resolve()
    if not path.is_file():
        raise ValueError(f"study file {path} not found")
    with open(path, "rb") as f:
        try:
            raw = tomllib.load(f)
        except tomllib.TOMLDecodeError as e:
            raise ValueError(f"study file {path}: {e}") from None
    unknown = set(raw) - {"study", "parameters", "cases"}
    if unknown:
        raise ValueError(f"study file {path}: unknown table(s) {sorted(unknown)}; allowed: study, parameters, cases")
    st = raw.get("study", {})
    bad = set(st) - _STUDY_KEYS
    if bad:
        raise ValueError(f"[study] unknown key(s) {sorted(bad)}; allowed: {', '.join(sorted(_STUDY_KEYS))}")
    if "base" not in st:
        raise ValueError("[study] base = 'CASE.toml' is required")
    base = (path.parent / st["base"]).resolve()
    if not base.is_file():
        raise ValueError(f"[study] base = {st['base']!r}: case file {base} not found")
    name = st.get("name") or path.stem
    directory = (path.parent / st["directory"]).resolve() if st.get("directory") else Path.cwd() / "runs" / name
    combine = st.get("combine", "product")
    if combine not in ("product", "zip"):
        raise ValueError(f"[study] combine = {combine!r}: expected 'product' or 'zip'")
    common = st.get("set", [])
    if not isinstance(common, list) or not all(isinstance(s, str) and "=" in s for s in common):
        raise ValueError(f"[study] set = {common!r}: expected a list of 'section.key=value' strings")
    ranks = st.get("ranks", 1)
    if not isinstance(ranks, int) or isinstance(ranks, bool) or ranks < 1:
        raise ValueError(f"[study] ranks = {ranks!r}: expected an integer >= 1")
    window = st.get("window")
    if window is not None:
        if not (isinstance(window, list) and len(window) == 2 and window[1] >= window[0]):
            raise ValueError(f"[study] window = {window!r}: expected [t0, t1] in s with t1 >= t0")
        window = (float(window[0]), float(window[1]))
    params = raw.get("parameters", {})
    for k, v in params.items():
        if not isinstance(v, list) or not v:
            raise ValueError(f"[parameters] {k!r}: expected a non-empty list of values")
    members: list[Member] = []
    if params:
        keys = list(params)
        if combine == "zip":
            lengths = {len(v) for v in params.values()}
            if len(lengths) != 1:
                raise ValueError(f"[study] combine = 'zip' needs lists of equal length, got {lengths}")
            combos = list(zip(*params.values(), strict=True))
        else:
            combos = list(itertools.product(*params.values()))
        for combo in combos:
            values = dict(zip(keys, combo, strict=True))
            mname = "_".join(_label(k, v) for k, v in values.items())
            members.append(Member(mname, values, [f"{k}={_toml_text(v)}" for k, v in values.items()], directory))
    for mname, table in raw.get("cases", {}).items():
        if not isinstance(table, dict):
            raise ValueError(f"[cases.{mname}]: expected a table of 'section.key' = value")
        nested = [k for k, v in table.items() if isinstance(v, dict)]
        if nested:
            raise ValueError(
                f"[cases.{mname}]: {nested} are tables; write keys as quoted dotted names "
                f'("contact.friction_pp" = 0.1) and quote member names holding dots ([cases."mu0.1"])'
            )
        ovs = [f"{k}={_toml_text(v)}" for k, v in table.items()]
        members.append(Member(mname, dict(table), ovs, directory))
    if not members:
        raise ValueError(f"study file {path}: no members: give [parameters] lists or [cases.<name>] tables")
    names = [m.name for m in members]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ValueError(f"study members with the same name: {sorted(dup)}")
    problems = []
    for m in members:
        m.directory = directory / m.name
        try:
            load_case(base, [*m.overrides, *common, f"output.directory={m.directory}"])
        except CaseError as e:
            problems.append(f"member {m.name}: " + "; ".join(e.problems))
    if problems:
        raise ValueError("study members that would not run:\n  " + "\n  ".join(problems))
    allkeys = {k: [] for m in members for k in m.values}
    for m in members:
        for k in allkeys:
            if k in m.values and m.values[k] not in allkeys[k]:
                allkeys[k].append(m.values[k])
    return Study(
        path, name, base, directory, members, allkeys, common, ranks, st.get("mpirun", "mpirun -n {ranks}"), window
    )


def _last_output_time(run_dir: Path) -> float:
    t = read_series(run_dir).get("time")
    last = float(t[-1]) if t is not None and t.size else -math.inf
    try:
        snaps = list_snapshots(run_dir)
        if snaps:
            last = max(last, snaps[-1][0])
    except (ValueError, OSError):
        pass
    return last


def member_state(m: Member) -> str:
    """One of STATES for a member's output folder (see the module docstring)."""
    d = m.directory
    if not d.is_dir() or not any(d.iterdir()):
        return "new"
    st = read_status(d)
    if st is not None:
        s = st.get("state")
        if s == "running":
            from febed.io.rundir import running_process  # loads mpi4py (MPI starts)

            return "live" if running_process(d) is not None else "running"
        if s in ("interrupted", "finished", "failed"):
            return s
    try:
        case = read_case(d)
        end = float(case["run"]["end_time"])
    except (ValueError, KeyError, TypeError):
        return "interrupted"
    # runs stop within a step of end_time (pure DEM: half a DEM step before it)
    tol = min(1e-3 * end, float(case.get("gas", {}).get("dt_max", 1e-3)))
    return "finished" if _last_output_time(d) >= end - tol else "interrupted"


def resume_flags(m: Member, state: str) -> tuple[bool, bool]:
    """(restart, overwrite) for a member in `state` (`febed run --restart` / `--overwrite`).

    An unfinished run of a mode without checkpoints (not in `febed.restart.RESTARTABLE`) starts again from
    scratch.
    """
    from febed.restart import RESTARTABLE  # loads mpi4py (MPI starts)

    if state not in ("running", "interrupted"):
        return False, state == "failed"
    try:
        mode = read_case(m.directory)["run"].get("mode", "cfd-dem")
    except (ValueError, KeyError, TypeError, OSError):
        return True, False
    return (True, False) if mode in RESTARTABLE else (False, True)


def member_states(study: Study) -> list[tuple[Member, str]]:
    """(member, state) of every member, in study order."""
    return [(m, member_state(m)) for m in study.members]


def _subprocess_runner(cmd: list[str], member: Member) -> int:
    return subprocess.run(cmd, check=False).returncode


def run_study(
    study: Study,
    runner: Callable[[list[str], Member], int] = _subprocess_runner,
    retry_failed: bool = False,
    say: Callable[[str], None] = print,
) -> bool:
    """Run the unfinished members one after another; True if every member is finished at the end.

    `runner(cmd, member)` runs one command line and returns its exit status (default: a subprocess).
    """
    study.directory.mkdir(parents=True, exist_ok=True)
    _write_manifest(study)
    for m in study.members:
        state = member_state(m)
        if state == "finished":
            say(f"study {study.name}: {m.name} finished, skipped")
            continue
        if state == "failed" and not retry_failed:
            say(f"study {study.name}: {m.name} failed before, skipped (--retry-failed re-runs it)")
            continue
        if state == "live":
            say(f"study {study.name}: {m.name} is still running (another process on this machine), skipped")
            continue
        restart, overwrite = resume_flags(m, state)
        cmd = m.command(study, restart=restart, overwrite=overwrite)
        say(f"study {study.name}: {'resuming' if restart else 'running'} {m.name}: {shlex.join(cmd)}")
        rc = runner(cmd, m)
        if rc != 0:
            say(f"study {study.name}: {m.name} exited with status {rc}")
    states = member_states(study)
    _write_manifest(study, states)
    return all(s == "finished" for _, s in states)


def job_lines(study: Study, retry_failed: bool = False) -> list[str]:
    """Shell command lines (one per unfinished member) to submit as separate (MPI) jobs."""
    lines = []
    for m, state in member_states(study):
        if state in ("finished", "live") or (state == "failed" and not retry_failed):
            continue
        restart, overwrite = resume_flags(m, state)
        lines.append(shlex.join(m.command(study, restart=restart, overwrite=overwrite)))
    return lines


def _write_manifest(study: Study, states=None) -> None:
    states = states or member_states(study)
    rows = [
        {"name": m.name, "values": m.values, "directory": str(m.directory), "state": s, "overrides": m.overrides}
        for m, s in states
    ]
    doc = {"study": str(study.path), "base": str(study.base), "set": study.common, "members": rows}
    (study.directory / "study.json").write_text(json.dumps(doc, indent=1, default=str) + "\n")


def collect(study: Study, fields: bool = True, height: float = 0.092, out: Path | None = None) -> Comparison:
    """Compare the members' results (see the module docstring); writes `<directory>/comparison/`."""
    return compare_members(study, member_states(study), fields=fields, height=height, out=out)
