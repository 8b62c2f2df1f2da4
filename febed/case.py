"""The case file: every parameter declared once, TOML loaded and validated before anything runs.

A case is a TOML file with the sections `[run]`, `[mesh]`, `[gas]`, `[gas.boundary.<tag>]`,
`[particles]`, `[contact]`, `[coupling]`, `[coarse_grain]` and `[output]`. The declarations in
`febed/schema.py` are the single source of truth: defaults, units, ranges, choices and help text feed
the validation here, `febed params`, and the resolved case written to the output folder.

Validation is strict and happens before any computation:

* an unknown section or key is an error naming the nearest valid one;
* a wrong type or an out-of-range value is an error naming the key, the value and what is allowed;
* a missing mesh or bed file is an error naming the path.

All problems of a file are collected and reported together (`CaseError.problems`).

A case may extend another: a top-level `extends = "base.toml"` (relative to the case file) loads the
base first and overlays this file's values, table by table.

Python API:
    >>> case = load_case("bed.toml", overrides=["gas.density=1.2"])
    >>> case.gas.density, case.gas.boundary["inlet"].velocity
"""

from __future__ import annotations

import difflib
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from febed.coarse.setup import check_case
from febed.schema import BOUNDARY, SCHEMA, Param


class CaseError(ValueError):
    """A case that cannot run; `problems` lists every message, each naming the key and the fix."""

    def __init__(self, problems: list[str], source: str = "case"):
        self.problems = list(problems)
        self.source = source
        lines = "\n".join(f"  - {p}" for p in self.problems)
        super().__init__(f"{source}: {len(self.problems)} problem(s):\n{lines}")


class Section:
    """Read-only attribute view of one validated section (e.g. `case.gas.density`)."""

    def __init__(self, name: str, values: dict[str, Any]):
        object.__setattr__(self, "_name", name)
        object.__setattr__(self, "_values", dict(values))

    def __getattr__(self, key: str) -> Any:
        try:
            return self._values[key]
        except KeyError:
            raise AttributeError(f"section [{self._name}] has no parameter {key!r}") from None

    def __setattr__(self, key: str, value: Any) -> None:
        raise AttributeError("case sections are read-only; use --set or overrides=[...]")

    def as_dict(self) -> dict[str, Any]:
        """The section's values as a plain dict."""
        return dict(self._values)

    def __repr__(self) -> str:
        return f"Section({self._name!r}, {self._values!r})"


@dataclass
class Case:
    """A validated case: one `Section` per schema section plus `gas.boundary[tag]`."""

    path: Path | None
    sections: dict[str, Section]
    boundary: dict[str, Section] = field(default_factory=dict)

    def __getattr__(self, name: str) -> Any:
        sections = self.__dict__.get("sections", {})
        if name in sections:
            return sections[name]
        raise AttributeError(f"a case has no section {name!r}")

    @property
    def name(self) -> str:
        """The case name: `[run] name`, else the case file's stem."""
        return self.sections["run"].name or (self.path.stem if self.path else "case")

    @property
    def base_dir(self) -> Path:
        """Folder that relative paths in the case are resolved against."""
        return self.path.parent if self.path else Path.cwd()

    def resolve_path(self, value: str) -> Path:
        """An absolute path for a path written in the case (relative to the case file)."""
        p = Path(value).expanduser()
        return p if p.is_absolute() else (self.base_dir / p).resolve()

    def output_dir(self) -> Path:
        """The run's output folder: `[output] directory`, else `./runs/<case name>`."""
        d = self.sections["output"].directory
        return self.resolve_path(d) if d else (Path.cwd() / "runs" / self.name).resolve()

    def to_dict(self) -> dict[str, Any]:
        """Every value, defaults filled in, as nested dicts (the resolved case)."""
        out: dict[str, Any] = {}
        for sec, s in self.sections.items():
            _set_nested(out, sec.split("."), s.as_dict())
        if self.boundary:
            out.setdefault("gas", {})["boundary"] = {t: b.as_dict() for t, b in self.boundary.items()}
        return out

    def to_toml(self) -> str:
        """The resolved case as TOML text that `load_case` reads back to an equal case."""
        return dumps_toml(self.to_dict())


def _set_nested(d: dict, keys: list[str], value: dict) -> None:
    for k in keys[:-1]:
        d = d.setdefault(k, {})
    d.setdefault(keys[-1], {}).update(value)


# ---------------------------------------------------------------------------------------------- loading


def load_case(
    path: str | Path | None = None,
    overrides: list[str] | None = None,
    data: dict[str, Any] | None = None,
    check_files: bool = True,
) -> Case:
    """Load, merge, override and validate a case; raise `CaseError` listing every problem.

    Args:
        path: the TOML case file (or None when `data` is given).
        overrides: `section.key=value` strings, as given to `--set` (value parsed as TOML, else a string).
        data: an already parsed case (Python API); overlaid on the file when both are given.
        check_files: check that the files the case names (mesh, packed bed) exist.

    Returns:
        The validated `Case`: one typed section per table (`case.gas.density`, ...), every default filled in.

    Raises:
        CaseError: every problem found, each naming its key or file and what is allowed.
    """
    source = str(path) if path is not None else "case"
    raw: dict[str, Any] = {}
    p = None
    if path is not None:
        p = Path(path).expanduser().resolve()
        raw = _read_with_extends(p, [])
    if data:
        raw = _merge(raw, data)
    problems: list[str] = []
    for ov in overrides or []:
        try:
            raw = _merge(raw, parse_override(ov))
        except CaseError as e:
            problems += e.problems
    case, more = _validate(raw, p, check_files)
    problems += more
    if problems:
        raise CaseError(problems, source)
    return case


def _read_with_extends(path: Path, chain: list[Path]) -> dict[str, Any]:
    if not path.is_file():
        where = f" (extended by {chain[-1]})" if chain else ""
        raise CaseError([f"case file not found: {path}{where}"], str(path))
    if path in chain:
        raise CaseError([f"'extends' loops back to {path}"], str(chain[0]))
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise CaseError([f"not valid TOML: {e}"], str(path)) from None
    except UnicodeDecodeError:
        raise CaseError(["not a text file (expected a TOML case file)"], str(path)) from None
    base = raw.pop("extends", None)
    if base is None:
        return raw
    if not isinstance(base, str):
        raise CaseError([f"'extends' must be a file name (string), got {base!r}"], str(path))
    parent = _read_with_extends((path.parent / base).resolve(), [*chain, path])
    return _merge(parent, raw)


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def parse_override(text: str) -> dict[str, Any]:
    """`"gas.density=1.2"` -> `{"gas": {"density": 1.2}}`; the value is read as TOML, else as a string."""
    if "=" not in text:
        raise CaseError([f"--set {text!r}: expected section.key=value"], "--set")
    dotted, value = (s.strip() for s in text.split("=", 1))
    keys = dotted.split(".")
    if len(keys) < 2 or not all(keys):
        raise CaseError([f"--set {text!r}: the key must be section.key (e.g. gas.density)"], "--set")
    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value
    out: dict[str, Any] = {}
    d = out
    for k in keys[:-1]:
        d = d.setdefault(k, {})
    d[keys[-1]] = parsed
    return out


# ------------------------------------------------------------------------------------------- validation


def _nearest(word: str, candidates: list[str]) -> str:
    best = difflib.get_close_matches(word, candidates, n=1, cutoff=0.5)
    if best:
        return f"did you mean {best[0]!r}?"
    return f"valid: {', '.join(sorted(candidates))}"


def _flatten_sections(raw: dict[str, Any]) -> tuple[dict[str, dict], dict[str, Any], list[str]]:
    """Split the raw tree into schema sections, boundary tables and problems for unknown sections."""
    problems: list[str] = []
    found: dict[str, dict] = {}
    boundary: dict[str, Any] = {}
    section_names = list(SCHEMA)
    for top, val in raw.items():
        if not isinstance(val, dict):
            problems.append(f"'{top}' at the top level: keys belong in a [section]; {_nearest(top, section_names)}")
            continue
        if top not in SCHEMA:
            problems.append(f"unknown section [{top}]: {_nearest(top, section_names)}")
            continue
        found[top] = {}
        for k, v in val.items():
            if top == "gas" and k == "boundary":
                if not isinstance(v, dict):
                    problems.append("[gas] boundary must be tables [gas.boundary.<tag>]")
                else:
                    boundary = v
            else:
                found[top][k] = v
    return found, boundary, problems


def _validate(raw: dict[str, Any], path: Path | None, check_files: bool) -> tuple[Case, list[str]]:
    found, boundary_raw, problems = _flatten_sections(raw)
    sections: dict[str, Section] = {}
    for sec, params in SCHEMA.items():
        values, errs = _check_table(f"[{sec}]", found.get(sec, {}), params)
        problems += errs
        sections[sec] = Section(sec, values)
    boundary: dict[str, Section] = {}
    for tag, table in boundary_raw.items():
        if not isinstance(table, dict):
            problems.append(f"[gas.boundary] {tag} = {table!r}: each boundary is a table [gas.boundary.{tag}]")
            continue
        values, errs = _check_table(f"[gas.boundary.{tag}]", table, BOUNDARY)
        problems += errs
        boundary[tag] = Section(f"gas.boundary.{tag}", values)
    case = Case(path=path, sections=sections, boundary=boundary)
    if not problems:
        problems += _cross_checks(case, check_files)
    return case, problems


def _check_table(where: str, table: dict[str, Any], params: dict[str, Param]) -> tuple[dict, list[str]]:
    values: dict[str, Any] = {}
    problems: list[str] = []
    for key in table:
        if key not in params:
            problems.append(f"{where} unknown key {key!r}: {_nearest(key, list(params))}")
    for key, par in params.items():
        if key in table:
            val, err = par.check(table[key])
            if err:
                problems.append(f"{where} {key} = {_show(table[key])}: {err}")
                val = par.default
            values[key] = val
        else:
            values[key] = par.default
    return values, problems


def _show(v: Any) -> str:
    text = repr(v) if isinstance(v, str) else str(v)
    if isinstance(v, int) and not isinstance(v, bool) and len(text) > 30:
        return f"{text[:6]}... (a {len(text.lstrip('-'))}-digit number)"
    return text if len(text) <= 200 else f"{text[:60]}... ({len(text)} characters)"


def _cross_checks(case: Case, check_files: bool) -> list[str]:
    """Checks that involve more than one key (files, required pairs, consistency)."""
    problems: list[str] = []
    mesh = case.mesh
    if mesh.file and mesh.builtin:
        problems.append("[mesh] give either file or builtin, not both")
    if not mesh.file and not mesh.builtin:
        problems.append("[mesh] needs file = 'path/to/mesh.msh' or builtin = 'pseudo2d' | 'wang2d' | 'cylinder'")
    if check_files and mesh.file:
        f = case.resolve_path(mesh.file)
        if f.is_dir():
            problems.append(f"[mesh] file = {mesh.file!r}: {f} is a folder; give a gmsh .msh file")
        elif not f.is_file():
            problems.append(f"[mesh] file = {mesh.file!r}: mesh file not found: {f}")
    problems += _unused_mesh_keys(mesh)
    parts = case.particles
    if check_files and parts.bed_file:
        f = case.resolve_path(parts.bed_file)
        if not f.is_file() and not parts.pack_if_missing:
            problems.append(f"[particles] bed_file = {parts.bed_file!r}: packed bed not found: {f}")
    if parts.count and parts.bed_mass:
        problems.append("[particles] give count or bed_mass, not both")
    lo, hi = parts.region[:3], parts.region[3:]
    if any(b < a for a, b in zip(lo, hi, strict=True)):  # equal bounds allowed: z of a 2D case
        problems.append(f"[particles] region = {parts.region}: needs xmin <= xmax, ymin <= ymax, zmin <= zmax")
    run = case.run
    if run.particle_partition == "work" and run.mode not in ("dem", "cfd-dem"):
        problems.append(
            f"[run] particle_partition = 'work' is for runs whose particles move by their own contacts (mode = "
            f"'dem' or 'cfd-dem'), not mode = {run.mode!r}: use particle_partition = 'mesh'"
        )
    if run.mode in ("gas", "cfd-dem") and not case.boundary:
        problems.append(f"[run] mode = {run.mode!r} needs gas boundary conditions: add [gas.boundary.<tag>] tables")
    types = {b.type for b in case.boundary.values()}
    if run.mode in ("gas", "cfd-dem") and "inlet" in types and "outlet" not in types:
        problems.append(
            "[gas.boundary] an inlet needs an outlet: the gas flowing in has nowhere to go; give the tag it leaves "
            "by type = 'outlet'"
        )
    if case.gas.dt_min > case.gas.dt_max:
        problems.append(f"[gas] dt_min = {case.gas.dt_min:g} s must not exceed dt_max = {case.gas.dt_max:g} s")
    for tag, b in case.boundary.items():
        if b.type == "inlet" and b.velocity is None:
            problems.append(f"[gas.boundary.{tag}] type = 'inlet' needs velocity (superficial, m/s)")
        if b.as_dict().get("slip_normals") and not (b.type == "wall" and b.slip):  # the axes: schema choices
            problems.append(f"[gas.boundary.{tag}] slip_normals needs type = 'wall' and slip = true")
        if b.as_dict().get("wall_law", "brinkman") != "brinkman" and not (b.type == "wall" and not b.slip):
            problems.append(f"[gas.boundary.{tag}] wall_law is for a wall without slip (type = 'wall', slip = false)")
        if b.as_dict().get("slip_length") is not None and not (b.type == "wall" and b.slip):
            problems.append(f"[gas.boundary.{tag}] slip_length needs type = 'wall' and slip = true")
        for w in b.as_dict().get("wins_over") or ():
            if b.type != "inlet":
                problems.append(f"[gas.boundary.{tag}] wins_over is for an inlet (type = 'inlet')")
                break
            other = case.boundary.get(w)
            if other is not None and not (other.type == "wall" and not other.slip):
                problems.append(
                    f"[gas.boundary.{tag}] wins_over = {w!r}: [gas.boundary.{w}] must be a no-slip wall "
                    "(type = 'wall', slip = false)"
                )
            elif other is not None and other.as_dict().get("wall_law", "brinkman") != "no_slip":
                problems.append(
                    f"[gas.boundary.{tag}] wins_over = {w!r}: [gas.boundary.{w}] must set wall_law = 'no_slip' "
                    "(an inlet already shares its nodes with a wall of the porous wall law by facet)"
                )
    problems += check_case(case)
    out = case.output
    if out.keep_checkpoints < 1:
        problems.append("[output] keep_checkpoints must be at least 1")
    if math.isfinite(run.end_time) and run.end_time <= 0:
        problems.append("[run] end_time must be > 0")
    return problems


def _unused_mesh_keys(mesh: Section) -> list[str]:
    """`[mesh]` keys given (not at their default) that the chosen mesh would ignore."""
    default = {k: p.default for k, p in SCHEMA["mesh"].items()}
    given = [k for k in ("level", "size", "extent", "cell") if getattr(mesh, k) != default[k]]
    if mesh.file:
        return [
            f"[mesh] {k} = {_show(getattr(mesh, k))} applies to built-in meshes, not to [mesh] file = {mesh.file!r}; "
            "remove it"
            for k in given
        ]
    b, cell = mesh.builtin, mesh.cell
    structured = b == "wang2d" or (b == "pseudo2d" and cell == "hexahedron")
    name = f"{b!r} ({cell})" if b == "pseudo2d" else repr(b)
    problems = []
    if "size" in given and structured:
        problems.append(
            f"[mesh] size = {mesh.size:g}: the built-in mesh {name} is structured, its cells are fixed "
            "(pseudo2d: by level); size applies to 'box', 'cylinder' and tetrahedral 'pseudo2d'; remove it"
        )
    if "level" in given and not (b == "pseudo2d" and cell == "hexahedron"):
        problems.append(
            f"[mesh] level = {mesh.level!r} applies to the hexahedral 'pseudo2d' mesh only, not to {name}; remove it"
        )
    if "extent" in given and b != "box":
        problems.append(f"[mesh] extent applies to builtin = 'box' only, not to {b!r}; remove it")
    return problems


# -------------------------------------------------------------------------------------------- TOML out


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        if math.isnan(v):
            return "nan"
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} to TOML")


def dumps_toml(data: dict[str, Any], _prefix: str = "") -> str:
    """Nested dicts of scalars and lists -> TOML text (None values are left out: they mean 'unset')."""
    lines: list[str] = []
    tables = []
    for k, v in data.items():
        if isinstance(v, dict):
            tables.append((k, v))
        elif v is not None:
            lines.append(f"{k} = {_toml_value(v)}")
    out = ""
    if lines:
        out += (f"[{_prefix}]\n" if _prefix else "") + "\n".join(lines) + "\n\n"
    for k, v in tables:
        out += dumps_toml(v, f"{_prefix}.{k}" if _prefix else k)
    return out
