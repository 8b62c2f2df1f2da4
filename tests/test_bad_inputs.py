"""Bad input is refused before anything runs: exit status 2, no traceback, a message naming the key or file.

Every row of the table mutates one key, table or file of the seed-000 case (demos/wang2d/wang2d.toml and its
packed bed, copied to a temporary folder) and runs `febed check` in this process; `febed check` does every
check `febed run` does before it touches the output folder (the case, its mesh, its bed file and the
pre-flight estimate, `febed.preflight`). A generated table refuses nan, inf or a value of the wrong type for
every parameter. Further tests cover what the table cannot: `--force`, a bed declared authoritative,
`febed run` leaving no trace, and restarts from another run's checkpoint.
"""

import math
import shutil
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest
from conftest import reset_febed_logger

from febed.case import CaseError, load_case
from febed.cli import main
from febed.io.checkpoint import list_checkpoints, read_checkpoint, write_checkpoint
from febed.io.rundir import RESOLVED_CASE, prepare_output, release_output
from febed.preflight import preflight
from febed.restart import checkpoint_differences
from febed.schema import BOUNDARY, SCHEMA

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "demos" / "wang2d"
CASE = "wang2d.toml"
BED = "wang2d-bed.npz"
HUGE = "1" + "0" * 399  # a number with 400 digits


class Raw(str):
    """A TOML literal written as is (nan, inf, a 400-digit number, a date)."""


# ------------------------------------------------------------------------------------------ case writing
def _value(v) -> str:
    if isinstance(v, Raw):
        return str(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float) and not math.isfinite(v):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(v)


def dumps(data: dict, prefix: str = "") -> str:
    """Nested dicts -> TOML text, `Raw` values verbatim."""
    lines, tables = [], []
    for k, v in data.items():
        (tables if isinstance(v, dict) else lines).append((k, v))
    out = (f"[{prefix}]\n" if prefix and lines else "") + "".join(f"{k} = {_value(v)}\n" for k, v in lines)
    for k, v in tables:
        out += dumps(v, f"{prefix}.{k}" if prefix else k)
    return out


def seed_case() -> dict:
    return tomllib.loads((DEMO / CASE).read_text())


def _walk(data: dict, dotted: str) -> tuple[dict, str]:
    keys = dotted.split(".")
    for k in keys[:-1]:
        data = data.setdefault(k, {})
    return data, keys[-1]


def S(dotted: str, value):  # noqa: N802
    """Set one key (dotted path) of the case."""

    def mutate(data, folder):
        d, k = _walk(data, dotted)
        d[k] = value

    return mutate


def D(dotted: str):  # noqa: N802
    """Remove one key or table of the case."""

    def mutate(data, folder):
        d, k = _walk(data, dotted)
        del d[k]

    return mutate


def both(*mutations):
    def mutate(data, folder):
        for m in mutations:
            m(data, folder)

    return mutate


def text(name: str, content: str | bytes):
    """Write a file next to the case."""

    def mutate(data, folder):
        p = folder / name
        p.write_bytes(content) if isinstance(content, bytes) else p.write_text(content)

    return mutate


def folder_named(name: str):
    def mutate(data, folder):
        (folder / name).mkdir()

    return mutate


def bed(change):
    """Rewrite the bed file: `change(arrays)` edits the dict of arrays in place (or returns a new one)."""

    def mutate(data, folder):
        with np.load(folder / BED) as z:
            arrays = {k: z[k] for k in z.files}
        arrays = change(arrays) or arrays
        (folder / BED).unlink()
        np.savez(folder / BED, **arrays)

    return mutate


def bed_bytes(make):
    """Replace the bed file by `make(original bytes)`."""

    def mutate(data, folder):
        p = folder / BED
        p.write_bytes(make(p.read_bytes()))

    return mutate


def bed_as_folder(data, folder):
    (folder / BED).unlink()
    (folder / BED).mkdir()


def npy_bed(data, folder):
    (folder / BED).unlink()
    with open(folder / BED, "wb") as f:
        np.save(f, np.zeros((10, 3)))


def pickled_bed(data, folder):
    (folder / BED).unlink()
    np.savez(folder / BED, pos=np.array([{"a": 1}], dtype=object))


def shift(arrays, dx=1.0, rows=slice(None)):
    arrays["pos"][rows, 0] += dx


def _setitem(arrays, key, rows, value):
    arrays[key][rows] = value


# --------------------------------------------------------------------------------------------- the table
# fmt: off
ROWS = [
    # sections and keys that do not exist, TOML that does not read
    ("unknown section", S("partcles.count", 5), ["[partcles]", "did you mean 'particles'"]),
    ("unknown key", S("particles.densty", 1150.0), ["'densty'", "did you mean 'density'"]),
    ("key at the top level", S("end_time", 1.0), ["'end_time' at the top level"]),
    ("unknown boundary key", S("gas.boundary.inlet.velocty", 0.9), ["[gas.boundary.inlet]", "'velocty'"]),
    ("parameter given as a table", S("particles.count", {"value": 5}), ["[particles] count"]),
    ("not TOML", text(CASE, "[run\nmode = 'cfd-dem'\n"), ["not valid TOML"]),
    ("binary case file", text(CASE, b"\x89PNG\r\n\x1a\n\x00\xff\xfe"), [CASE]),
    ("extends a missing base", S("extends", "base-missing.toml"), ["base-missing.toml"]),
    ("extends is a number", S("extends", 5), ["'extends'"]),
    ("extends itself", S("extends", CASE), ["loops back", CASE]),
    # [run]
    ("mode misspelt", S("run.mode", "cfd"), ["[run] mode = 'cfd'", "'cfd-dem'"]),
    ("end_time zero", S("run.end_time", 0.0), ["[run] end_time = 0.0", "> 0"]),
    ("end_time negative", S("run.end_time", -1.0), ["[run] end_time = -1.0"]),
    ("end_time nan", S("run.end_time", math.nan), ["[run] end_time = nan"]),
    ("end_time inf", S("run.end_time", math.inf), ["[run] end_time = inf", "inf and nan are not allowed"]),
    ("end_time a string", S("run.end_time", "1.0"), ["[run] end_time = '1.0'", "a number"]),
    ("end_time a boolean", S("run.end_time", True), ["[run] end_time = True"]),
    ("end_time a date", S("run.end_time", Raw("1979-05-27")), ["[run] end_time = 1979-05-27"]),
    ("end_time of 400 digits", S("run.end_time", Raw(HUGE)), ["[run] end_time", "overflows"]),
    ("end_time 1e9, dt_max 1e-9", both(S("run.end_time", 1e9), S("gas.dt_max", 1e-9), S("gas.dt_min", 1e-10)),
     ["[run] end_time = 1e+09", "dt_max = 1e-09", "--force"]),
    ("end_time 1e9", S("run.end_time", 1e9), ["[run] end_time = 1e+09", "wall time", "--force"]),
    ("gravity negative", S("run.gravity", -9.81), ["[run] gravity = -9.81"]),
    ("seed negative", S("run.seed", -1), ["[run] seed = -1"]),
    ("seed not an integer", S("run.seed", 1.5), ["[run] seed = 1.5", "an integer"]),
    ("seed of 400 digits", S("run.seed", Raw(HUGE)), ["[run] seed", "64-bit integer"]),
    ("max_overlap zero", S("run.max_overlap", 0.0), ["[run] max_overlap = 0.0"]),
    ("max_overlap above 1", S("run.max_overlap", 2.0), ["[run] max_overlap = 2.0"]),
    ("max_clipped_fraction above 1", S("run.max_clipped_fraction", 1.5), ["[run] max_clipped_fraction"]),
    ("particle_partition misspelt", S("run.particle_partition", "cells"),
     ["[run] particle_partition = 'cells'", "'work'"]),  # fmt: skip
    ("particle_partition work in a gas-only run", both(S("run.mode", "gas"), S("run.particle_partition", "work")),
     ["[run] particle_partition = 'work'", "mode = 'gas'", "'cfd-dem'"]),  # fmt: skip
    # [mesh]
    ("builtin misspelt", S("mesh.builtin", "wang3d"), ["[mesh] builtin = 'wang3d'", "'wang2d'"]),
    ("level misspelt", S("mesh.level", "ultra"), ["[mesh] level = 'ultra'"]),
    ("cell misspelt", S("mesh.cell", "hex"), ["[mesh] cell = 'hex'", "'hexahedron'"]),
    ("size on a structured mesh", S("mesh.size", 0.002), ["[mesh] size = 0.002", "structured"]),
    ("size negative", S("mesh.size", -1.0), ["[mesh] size = -1.0"]),
    ("level on wang2d", S("mesh.level", "fine"), ["[mesh] level = 'fine'", "'pseudo2d'"]),
    ("extent on wang2d", S("mesh.extent", [0.09, 0.5]), ["[mesh] extent", "'box'"]),
    ("cell the geometry lacks", both(S("mesh.builtin", "pseudo2d"), S("mesh.cell", "quadrilateral")),
     ["'pseudo2d'", "'quadrilateral'"]),
    ("depth negative", S("mesh.depth", -0.001), ["[mesh] depth = -0.001"]),
    ("no mesh", D("mesh.builtin"), ["[mesh] needs file"]),
    ("file and builtin", S("mesh.file", "bed.msh"), ["[mesh] give either file or builtin"]),
    ("mesh file missing", both(D("mesh.builtin"), S("mesh.file", "missing.msh")), ["missing.msh", "not found"]),
    ("mesh file a folder", both(D("mesh.builtin"), S("mesh.file", "m.msh"), folder_named("m.msh")),
     ["m.msh", "is a folder"]),
    ("mesh file garbage", both(D("mesh.builtin"), S("mesh.file", "g.msh"), text("g.msh", "hello mesh\n")),
     ["g.msh", "gmsh cannot read it"]),
    ("mesh file empty", both(D("mesh.builtin"), S("mesh.file", "e.msh"), text("e.msh", "")), ["e.msh"]),
    ("mesh file with a builtin key", both(D("mesh.builtin"), S("mesh.file", "e.msh"), text("e.msh", ""),
     S("mesh.size", 0.01)), ["[mesh] size = 0.01", "built-in meshes"]),
    # [gas]
    ("gas density zero", S("gas.density", 0.0), ["[gas] density = 0.0"]),
    ("gas density negative", S("gas.density", -1.28), ["[gas] density = -1.28"]),
    ("gas density a word", S("gas.density", "air"), ["[gas] density = 'air'"]),
    ("viscosity nan", S("gas.viscosity", math.nan), ["[gas] viscosity = nan"]),
    ("viscosity zero", S("gas.viscosity", 0.0), ["[gas] viscosity = 0.0"]),
    ("les misspelt", S("gas.les", "dynamic"), ["[gas] les = 'dynamic'", "'smagorinsky'"]),
    ("smagorinsky_cs above 1", S("gas.smagorinsky_cs", 2.0), ["[gas] smagorinsky_cs = 2.0"]),
    ("cfl zero", S("gas.cfl", 0.0), ["[gas] cfl = 0.0"]),
    ("cfl inf", S("gas.cfl", math.inf), ["[gas] cfl = inf"]),
    ("dt_max zero", S("gas.dt_max", 0.0), ["[gas] dt_max = 0.0"]),
    ("dt_min above dt_max", S("gas.dt_min", 1e-3), ["[gas] dt_min = 0.001", "dt_max = 0.0002"]),
    ("pressure_passes zero", S("gas.pressure_passes", 0), ["[gas] pressure_passes = 0"]),
    ("pressure_passes fractional", S("gas.pressure_passes", 1.5), ["[gas] pressure_passes = 1.5"]),
    ("backflow too large", S("gas.backflow", 20.0), ["[gas] backflow = 20.0"]),
    ("mass_tolerance too large", S("gas.mass_tolerance", 0.5), ["[gas] mass_tolerance = 0.5"]),
    ("switch as a word", S("gas.drag_weighted_projection", "yes"), ["[gas] drag_weighted_projection = 'yes'"]),
    ("switch as a number", S("gas.taylor_galerkin", 1), ["[gas] taylor_galerkin = 1", "true or false"]),
    ("void_fraction zero", S("gas.void_fraction", 0.0), ["[gas] void_fraction = 0.0"]),
    ("petsc_options a number", S("gas.petsc_options", 5), ["[gas] petsc_options = 5"]),
    # [gas.boundary.<tag>]
    ("boundary not tables", S("gas.boundary", 5), ["[gas] boundary"]),
    ("a boundary not a table", S("gas.boundary.inlet", "inlet"), ["[gas.boundary] inlet"]),
    ("inlet velocity inf", S("gas.boundary.inlet.velocity", math.inf), ["[gas.boundary.inlet] velocity = inf"]),
    ("inlet velocity nan", S("gas.boundary.inlet.velocity", math.nan), ["[gas.boundary.inlet] velocity = nan"]),
    ("inlet velocity negative", S("gas.boundary.inlet.velocity", -0.9), ["[gas.boundary.inlet] velocity = -0.9"]),
    ("inlet velocity a word", S("gas.boundary.inlet.velocity", "fast"), ["[gas.boundary.inlet] velocity = 'fast'"]),
    ("inlet velocity of 400 digits", S("gas.boundary.inlet.velocity", Raw(HUGE)), ["[gas.boundary.inlet] velocity"]),
    ("inlet velocity missing", D("gas.boundary.inlet.velocity"), ["[gas.boundary.inlet]", "needs velocity"]),
    ("inlet velocity beyond the CFL", S("gas.boundary.inlet.velocity", 1e6),
     ["[gas.boundary.inlet] velocity = 1e+06", "dt_min"]),
    ("boundary type misspelt", S("gas.boundary.inlet.type", "inflow"), ["[gas.boundary.inlet] type = 'inflow'"]),
    ("ramp_time negative", S("gas.boundary.inlet.ramp_time", -1.0), ["[gas.boundary.inlet] ramp_time = -1.0"]),
    ("no outlet", D("gas.boundary.outlet"), ["an inlet needs an outlet", "'outlet'"]),
    ("mesh tag without a table", D("gas.boundary.walls"),
     ["facet tag 'walls'", "[gas.boundary.walls]", "'inlet', 'wall', 'outlet', 'symmetry'"]),
    ("table of a tag the mesh lacks", S("gas.boundary.distributor", {"type": "wall"}),
     ["'distributor'", "the mesh has: inlet, outlet, walls"]),
    ("no boundary tables", D("gas.boundary"), ["needs gas boundary conditions"]),
    ("slip_normals misspelt", both(S("gas.boundary.walls.slip", True), S("gas.boundary.walls.slip_normals", ["w"])),
     ["[gas.boundary.walls] slip_normals"]),
    ("slip_length zero", both(S("gas.boundary.walls.slip", True), S("gas.boundary.walls.slip_length", 0.0)),
     ["[gas.boundary.walls] slip_length = 0.0"]),
    ("slip_length without slip", S("gas.boundary.walls.slip_length", 0.001),
     ["[gas.boundary.walls] slip_length needs"]),
    ("wins_over on an outlet", S("gas.boundary.outlet.wins_over", ["walls"]), ["[gas.boundary.outlet] wins_over"]),
    ("cross_section_tags unknown", S("gas.boundary.inlet.cross_section_tags", ["nosuch"]), ["'nosuch'"]),
    ("wall_law misspelt", S("gas.boundary.walls.wall_law", "log"), ["[gas.boundary.walls] wall_law = 'log'"]),
    ("outlet pressure a word", S("gas.boundary.outlet.pressure", "high"), ["[gas.boundary.outlet] pressure"]),
    ("outlet pressure inf", S("gas.boundary.outlet.pressure", math.inf), ["[gas.boundary.outlet] pressure = inf"]),
    ("boundary particles a word", S("gas.boundary.walls.particles", "no"), ["[gas.boundary.walls] particles"]),
    # [particles] against the bed file
    ("diameter zero", S("particles.diameter", 0.0), ["[particles] diameter = 0.0"]),
    ("diameter negative", S("particles.diameter", -1.5e-3), ["[particles] diameter = -0.0015"]),
    ("diameter nan", S("particles.diameter", math.nan), ["[particles] diameter = nan"]),
    ("density inf", S("particles.density", math.inf), ["[particles] density = inf"]),
    ("density differs from the bed", S("particles.density", 2500.0), ["density = 2500", BED, "bed_authoritative"]),
    ("diameter differs from the bed", S("particles.diameter", 1e-3), ["diameter = 0.001", BED]),
    ("count differs from the bed", S("particles.count", 4000), ["count = 4000", "4080 particles", BED]),
    ("count 10^12 with the bed", S("particles.count", 10**12), ["count = 1000000000000", BED]),
    ("count 10^12 without a bed", both(S("particles.count", 10**12), S("particles.bed_file", "")),
     ["[particles] count = 1000000000000", "2^31"]),
    ("count 10^9 without a bed", both(S("particles.count", 10**9), S("particles.bed_file", "")),
     ["[particles] count", "--force"]),
    ("count of 400 digits", S("particles.count", Raw(HUGE)), ["[particles] count", "64-bit integer"]),
    ("bed_mass of 400 digits", both(D("particles.count"), S("particles.bed_mass", Raw(HUGE))),
     ["[particles] bed_mass", "overflows"]),
    ("count negative", S("particles.count", -5), ["[particles] count = -5"]),
    ("count fractional", S("particles.count", 4080.5), ["[particles] count = 4080.5", "an integer"]),
    ("count and bed_mass", S("particles.bed_mass", 0.01), ["[particles] give count or bed_mass, not both"]),
    ("bed_mass differs from the bed", both(D("particles.count"), S("particles.bed_mass", 0.01)), ["bed_mass", BED]),
    ("insertion misspelt", S("particles.insertion", "grid"), ["[particles] insertion = 'grid'"]),
    ("region of four numbers", S("particles.region", [0.0, 0.0, 0.0, 1.0]), ["[particles] region"]),
    ("region upside down", S("particles.region", [0.09, 0.0, 0.0, 0.0, 0.3, 0.0]), ["[particles] region", "xmin"]),
    ("region nan", S("particles.region", [math.nan, 0.0, 0.0, 0.09, 0.3, 0.0]), ["[particles] region"]),
    ("region off the mesh", both(S("particles.bed_file", ""), S("particles.region", [1.0, 1.0, -math.inf, 2.0,
     2.0, math.inf])), ["[particles] region", "does not intersect"]),
    ("bed missing, no packing", both(S("particles.bed_file", "none.npz"), S("particles.pack_if_missing", False)),
     ["none.npz", "not found"]),
    ("settle_energy zero", S("particles.settle_energy", 0.0), ["[particles] settle_energy = 0.0"]),
    ("pack_restitution above 1", S("particles.pack_restitution", 2.0), ["[particles] pack_restitution = 2.0"]),
    ("rotation a word", S("particles.rotation", "on"), ["[particles] rotation = 'on'"]),
    ("bed_authoritative a word", S("particles.bed_authoritative", "yes"), ["[particles] bed_authoritative"]),
    # the bed file itself
    ("bed a folder", bed_as_folder, [BED, "is a folder"]),
    ("bed truncated", bed_bytes(lambda b: b[: len(b) // 2]), [BED, "not a readable .npz"]),
    ("bed garbage", bed_bytes(lambda b: b"this is not a bed\n" * 10), [BED, "not a .npz archive"]),
    ("bed empty file", bed_bytes(lambda b: b""), [BED, "is empty"]),
    ("bed a zip of text", bed_bytes(lambda b: _zip_of_text()), [BED]),
    ("bed a single array", npy_bed, [BED, "single array"]),
    ("bed of pickled objects", pickled_bed, [BED, "not a readable .npz"]),
    ("bed with positions only", bed(lambda a: {"pos": a["pos"]}), [BED, "lacks", "diameter, mass"]),
    ("bed without masses", bed(lambda a: {k: v for k, v in a.items() if k != "mass"}), [BED, "mass"]),
    ("bed with nan positions", bed(lambda a: _setitem(a, "pos", 7, np.nan)), [BED, "pos is not finite"]),
    ("bed with inf velocities", bed(lambda a: _setitem(a, "vel", 3, np.inf)), [BED, "vel is not finite"]),
    ("bed with negative diameters", bed(lambda a: _setitem(a, "diameter", 0, -1e-3)), [BED, "diameter must be > 0"]),
    ("bed with zero masses", bed(lambda a: _setitem(a, "mass", slice(None), 0.0)), [BED, "mass must be > 0"]),
    ("bed arrays of other lengths", bed(lambda a: {**a, "mass": a["mass"][:-1]}), [BED, "mass has shape"]),
    ("bed of no particles", bed(lambda a: {k: v[:0] for k, v in a.items() if not k.startswith("meta_")}),
     [BED, "holds no particles"]),
    ("bed of 2D positions", bed(lambda a: {**a, "pos": a["pos"][:, :2]}), [BED, "pos has shape"]),
    ("bed of text positions", bed(lambda a: {**a, "pos": a["pos"].astype(str)}), [BED, "pos"]),
    ("bed with duplicate gids", bed(lambda a: _setitem(a, "gid", 1, a["gid"][0])), [BED, "gid"]),
    ("bed with n_orig zero", bed(lambda a: _setitem(a, "n_orig", 5, 0)), [BED, "n_orig"]),
    ("bed every particle outside", bed(lambda a: shift(a, 1.0)), [BED, "4080 of 4080", "outside the mesh"]),
    ("bed one particle outside", bed(lambda a: shift(a, 0.5, slice(0, 1))), [BED, "1 of 4080", "outside"]),
    ("bed polydisperse", bed(lambda a: _setitem(a, "diameter", slice(0, 100), 2e-3)), [BED, "diameter"]),
    ("bed of another material", bed(lambda a: _setitem(a, "mass", slice(None), a["mass"] * 2)), [BED, "density"]),
    # [contact]
    ("contact law misspelt", S("contact.model", "hertz"), ["[contact] model = 'hertz'", "'linear-history'"]),
    ("stiffness zero", S("contact.stiffness", 0.0), ["[contact] stiffness = 0.0"]),
    ("stiffness inf", S("contact.stiffness", math.inf), ["[contact] stiffness = inf"]),
    ("stiffness 1e20", S("contact.stiffness", 1e20), ["[contact] stiffness = 1e+20", "sub-steps per gas step"]),
    ("wall stiffness 1e20", S("contact.stiffness_wall", 1e20), ["[contact] stiffness_wall = 1e+20", "sub-steps"]),
    ("young_modulus 1e20", both(S("contact.from_material", True), S("contact.young_modulus", 1e20)),
     ["[contact] young_modulus = 1e+20", "sub-steps"]),
    ("dt_factor 1e9", S("contact.dt_factor", 1e9), ["dt_factor = 1e+09", "sub-steps"]),
    ("dt_factor below 1", S("contact.dt_factor", 0.5), ["[contact] dt_factor = 0.5"]),
    ("restitution zero", S("contact.restitution_pp", 0.0), ["[contact] restitution_pp = 0.0"]),
    ("restitution above 1", S("contact.restitution_pw", 1.5), ["[contact] restitution_pw = 1.5"]),
    ("friction negative", S("contact.friction_pp", -0.3), ["[contact] friction_pp = -0.3"]),
    ("poisson above 0.5", S("contact.poisson", 0.6), ["[contact] poisson = 0.6"]),
    ("integrator misspelt", S("contact.integrator", "euler"), ["[contact] integrator = 'euler'", "'rk2'"]),
    ("skin zero", S("contact.skin", 0.0), ["[contact] skin = 0.0"]),
    # [coupling], [coarse_grain], [output], [prescribed_gas]
    ("drag law misspelt", S("coupling.drag", "gidaspow"), ["[coupling] drag = 'gidaspow'", "'gidaspow-blend'"]),
    ("filter_passes too many", S("coupling.filter_passes", 100), ["[coupling] filter_passes = 100"]),
    ("void_fraction_floor above 1", S("coupling.void_fraction_floor", 1.5), ["[coupling] void_fraction_floor"]),
    ("pressure_gradient a word", S("coupling.pressure_gradient", "yes"), ["[coupling] pressure_gradient"]),
    ("coarse-grain model misspelt", S("coarse_grain.model", "cg"), ["[coarse_grain] model = 'cg'"]),
    ("coarse-grain ratio below 1", S("coarse_grain.ratio", 0.5), ["[coarse_grain] ratio = 0.5"]),
    ("tm ratio of no whole parcel", both(S("coarse_grain.model", "tm"), S("coarse_grain.ratio", 1.5)),
     ["[coarse_grain] ratio = 1.5"]),
    ("tm parcels from a bed of originals", both(S("coarse_grain.model", "tm"), S("coarse_grain.ratio", 2.0)),
     [BED, "tm parcels"]),
    ("pcpm with linear-history", S("coarse_grain.model", "pcpm"), ["[coarse_grain] model = 'pcpm'"]),
    ("probe_interval zero", S("output.probe_interval", 0.0), ["[output] probe_interval = 0.0"]),
    ("field_interval negative", S("output.field_interval", -1.0), ["[output] field_interval = -1.0"]),
    ("keep_checkpoints zero", S("output.keep_checkpoints", 0), ["[output] keep_checkpoints = 0"]),
    ("probe_heights of words", S("output.probe_heights", ["a"]), ["[output] probe_heights"]),
    ("bed_fraction too small", S("output.bed_fraction", 0.2), ["[output] bed_fraction = 0.2"]),
    ("progress_interval nan", S("output.progress_interval", math.nan), ["[output] progress_interval = nan"]),
    ("output directory a number", S("output.directory", 5), ["[output] directory = 5"]),
    ("prescribed flow misspelt", S("prescribed_gas.flow", "swirl"), ["[prescribed_gas] flow = 'swirl'"]),
]
# fmt: on


def _zip_of_text() -> bytes:
    import io

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("pos.npy", "not an array")
    return buf.getvalue()


@pytest.fixture(autouse=True)
def _collective_teardown():
    """Replaces conftest's: these serial checks hold no PETSc objects, and a full garbage collection after each
    of several hundred cases would take most of their run time; the `febed` logger is reset as there."""
    yield
    reset_febed_logger()


@pytest.fixture
def seed_folder(tmp_path, monkeypatch):
    """The seed-000 case and its bed in a temporary folder (its output folder inside it)."""
    monkeypatch.chdir(tmp_path)
    shutil.copy(DEMO / BED, tmp_path / BED)
    return tmp_path


def febed(*argv, capsys) -> tuple[int, str]:
    """`febed ARGV` in this process: (exit status, stderr + stdout)."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as e:  # argparse
        code = e.code
    out = capsys.readouterr()
    return code, out.err + out.out


def write_case(folder: Path, mutate=None) -> Path:
    data = seed_case()
    data["output"]["directory"] = str(folder / "out")
    if mutate is not None:
        mutate(data, folder)
    path = folder / CASE
    if not path.exists():  # a row may write the case file itself
        path.write_text(dumps(data))
    return path


def assert_refused(code: int, text: str, names: list[str]) -> None:
    assert code == 2, f"exit status {code}, expected 2:\n{text}"
    assert "Traceback" not in text
    for name in names:
        assert name in text, f"{name!r} not in:\n{text}"


def test_the_seed_case_passes(seed_folder, capsys):
    code, text = febed("check", write_case(seed_folder), capsys=capsys)
    assert code == 0, text
    assert "OK" in text and "4080 particles" in text and "11 DEM sub-steps per gas step" in text


@pytest.mark.parametrize("mutate, names", [r[1:] for r in ROWS], ids=[r[0] for r in ROWS])
def test_bad_input_is_refused(seed_folder, capsys, mutate, names):
    case = write_case(seed_folder, mutate)
    code, text = febed("check", case, capsys=capsys)
    assert_refused(code, text, names)


def test_the_table_is_large_and_names_differ():
    assert len(ROWS) >= 100
    assert len({r[0] for r in ROWS}) == len(ROWS)


# ------------------------------------------------------------------------------- command-line mistakes
ARGV = [
    ("--set without =", ["--set", "particles.density"], ["--set 'particles.density'", "section.key=value"]),
    ("--set without a section", ["--set", "density=2"], ["section.key"]),
    ("--set of an unknown section", ["--set", "nosuch.key=1"], ["[nosuch]"]),
    ("--set of a nan", ["--set", "gas.density=nan"], ["[gas] density = nan"]),
    ("--set of 400 digits", ["--set", f"particles.count={HUGE}"], ["[particles] count"]),
    ("--set a word", ["--set", "particles.density=heavy"], ["[particles] density = 'heavy'"]),
]


@pytest.mark.parametrize("extra, names", [r[1:] for r in ARGV], ids=[r[0] for r in ARGV])
def test_bad_override_is_refused(seed_folder, capsys, extra, names):
    code, text = febed("check", write_case(seed_folder), *extra, capsys=capsys)
    assert_refused(code, text, names)


def test_missing_case_file_is_refused(tmp_path, capsys):
    code, text = febed("check", tmp_path / "nosuch.toml", capsys=capsys)
    assert_refused(code, text, ["nosuch.toml", "not found"])


# -------------------------------------------------------------------- every parameter: nan, inf, wrong type
def _wrong_values(par):
    """(value, why) pairs that the parameter must refuse."""
    if par.type is float:
        out = [(math.nan, "nan"), ("1.0", "a string")]
        if par.finite:
            out.append((math.inf, "inf"))
        return out
    if par.type is int:
        return [(1.5, "a fraction"), (True, "a boolean")]
    if par.type is bool:
        return [("yes", "a string"), (1, "a number")]
    if par.type is str:
        return [(5, "a number")] + ([("no-such-choice", "not a choice")] if par.choices else [])
    return [("abc", "not a list"), ([math.nan] * (par.length or 1), "nan entries")]


GENERATED = [
    (f"{sec}.{key} {why}", sec, key, value)
    for sec, params in SCHEMA.items()
    for key, par in params.items()
    for value, why in _wrong_values(par)
    if not (par.type is list and par.item is str and why == "nan entries")
] + [
    (f"gas.boundary.inlet.{key} {why}", "gas.boundary.inlet", key, value)
    for key, par in BOUNDARY.items()
    for value, why in _wrong_values(par)
]


@pytest.mark.parametrize("sec, key, value", [g[1:] for g in GENERATED], ids=[g[0] for g in GENERATED])
def test_every_parameter_refuses_nan_inf_and_wrong_types(tmp_path, sec, key, value):
    data = seed_case()
    _walk(data, f"{sec}.{key}")[0][key] = value
    path = tmp_path / CASE
    path.write_text(dumps(data))
    with pytest.raises(CaseError) as info:
        load_case(path, check_files=False)
    assert f"[{sec}] {key} = " in str(info.value)


# --------------------------------------------------------------------------- beyond the table
def test_force_runs_an_absurd_estimate_but_not_an_impossible_one(seed_folder, capsys):
    case = write_case(seed_folder, S("contact.stiffness", 1e20))
    code, text = febed("check", case, "--force", capsys=capsys)
    assert code == 0, text
    assert "--force: [contact] stiffness = 1e+20" in text
    case.unlink()
    case = write_case(seed_folder, both(S("particles.count", 10**12), S("particles.bed_file", "")))
    code, text = febed("check", case, "--force", capsys=capsys)
    assert_refused(code, text, ["2^31"])


def test_an_authoritative_bed_decides_the_particles(seed_folder, capsys):
    mutate = both(
        S("particles.bed_authoritative", True),
        S("particles.density", 2500.0),
        S("particles.count", 10**12),
        S("particles.diameter", 1e-3),
    )
    case = write_case(seed_folder, mutate)
    code, text = febed("check", case, capsys=capsys)
    assert code == 0, text
    for line in ("[particles] density = 2500.0 -> 1150.0", "count = 1000000000000 -> 4080", "diameter = 0.001 ->"):
        assert line in text
    pf = preflight(load_case(case))
    p = pf.case.particles
    assert (p.count, p.density) == (4080, pytest.approx(1150.0, rel=1e-12))
    assert p.diameter == pytest.approx(1.5e-3, rel=1e-12)
    assert "density = 1150.0" in pf.case.to_toml()  # what ran is what the resolved case records


def test_refused_run_leaves_no_trace(seed_folder, capsys):
    case = write_case(seed_folder, S("contact.stiffness", 1e20))
    code, text = febed("run", case, capsys=capsys)
    assert_refused(code, text, ["[contact] stiffness = 1e+20"])
    assert not (seed_folder / "out").exists()


# ------------------------------------------------------------------------------ checkpoint identity
def _checkpoint_of(case, folder: Path, mesh_x: np.ndarray, n_particles: int, left: int = 0) -> Path:
    """A checkpoint as a coupled run of `case` writes it (at t = 0.01 s), with the given gas nodes and particles."""
    arrays = {"gas/x": mesh_x, "gas/p": np.zeros(len(mesh_x)), "dem/p_gid": np.arange(n_particles)}
    meta = {
        "time": 0.01,
        "step": 50,
        "ranks": 1,
        "mode": "cfd-dem",
        "solver": {"left_outlet": left},
        "case": case.to_toml(),
    }
    return write_checkpoint(folder, arrays, meta, keep=5)


def _wang2d_nodes() -> np.ndarray:
    x, y = np.meshgrid(np.linspace(0, 0.09, 19), np.linspace(0, 0.5, 101))
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)


def test_restart_refuses_another_runs_checkpoint_and_keeps_the_resolved_case(seed_folder, capsys):
    case_path = write_case(seed_folder)
    case = load_case(case_path)
    out = prepare_output(case)
    release_output(out)
    resolved = (out / RESOLVED_CASE).read_bytes()
    stamp = (out / RESOLVED_CASE).stat().st_mtime_ns
    nodes = _wang2d_nodes()
    own = _checkpoint_of(case, out / "checkpoints", nodes, 4080 - 3, left=3)
    meta = read_checkpoint(own)[1]
    ident = meta["identity"]
    assert ident["mesh"]["nodes"] == 1919 and ident["particles"] == 4077 and ident["left"] == 3
    assert len(ident["physics"]) == 64
    pf = preflight(case)
    assert pf.mesh["nodes"] == 1919 and pf.estimate.particles == 4080
    assert checkpoint_differences(ident, meta, case, pf.mesh, pf.estimate.particles) == []  # its own run

    other = load_case(case_path, ["contact.stiffness=1000", "gas.boundary.inlet.velocity=1.2", "gas.cfl=0.1"])
    foreign = seed_folder / "foreign"
    cases = {
        "physics": _checkpoint_of(other, foreign / "a", nodes, 4080),
        "mesh": _checkpoint_of(case, foreign / "b", nodes * [1.0, 1.2, 1.0], 4080),
        "particles": _checkpoint_of(case, foreign / "c", nodes, 2000),
    }
    expect = {
        "physics": ["contact.stiffness: 1000.0 -> 800.0", "gas.boundary.inlet.velocity: 1.2 -> 0.9"],
        "mesh": ["mesh bounds: [0, 0, 0] to [0.09, 0.6, 0] m -> [0, 0, 0] to [0.09, 0.5, 0] m"],
        "particles": ["particles at the start: 2000 (2000 in the checkpoint, 0 left the domain) -> 4080"],
    }
    # a changeable key (gas.cfl) is not a difference
    for what, ckpt in cases.items():
        code, text = febed("run", case_path, "--restart", ckpt, "--set", "gas.cfl=0.15", capsys=capsys)
        assert_refused(code, text, ["belongs to another run", str(ckpt), *expect[what]])
        assert "gas.cfl" not in text
        assert (out / RESOLVED_CASE).read_bytes() == resolved  # a refused restart rewrites nothing
        assert (out / RESOLVED_CASE).stat().st_mtime_ns == stamp
        assert not list(out.glob("case.before-restart-*"))
    # its own checkpoint, past its end time: refused before the accepted change is written; a newer checkpoint
    # that does not read is named
    corrupt = own.with_name("checkpoint_000000099.npz")
    corrupt.write_bytes(own.read_bytes()[:1000])
    code, text = febed("run", case_path, "--restart", "--set", "run.end_time=0.005", capsys=capsys)
    assert_refused(code, text, ["not before run.end_time", f"skipped a newer checkpoint that does not read: {corrupt}"])
    assert (out / RESOLVED_CASE).read_bytes() == resolved
    assert list_checkpoints(out / "checkpoints") == [own, corrupt]
