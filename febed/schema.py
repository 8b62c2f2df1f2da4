"""Declarations of every case parameter: default, unit, allowed range or choices, help text.

This is the one place a parameter is declared. `febed/case.py` validates against it,
`febed params` prints it, the resolved case written into each output folder is generated from it, and the
Python API's parameter objects take their defaults and ranges from it (`schema_field`, `check_fields`).
To add a parameter, add one `Param(...)` line to its section below and read it as `case.<section>.<key>`.

Choices may be a tuple or a `Registry` (drag laws, contact laws, ...): the registry lists the names of
the closures its module registered, so adding a law needs no edit here.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from dataclasses import Field, dataclass, field, fields
from fnmatch import fnmatch
from typing import Any

from febed.registry import Registry

# Registries of physics closures; each module registers its laws with `@REGISTRY.register(name)`.
CONTACT_LAWS = Registry("contact law", "febed.dem.contact")
INTEGRATORS = Registry("integrator", "febed.dem.integrate")
DRAG_LAWS = Registry("drag law", "febed.coupling.drag")
# PCPM's smallest group (`coarse_grain.min_group`): 1 original, or a power-of-two fraction of one (divisible
# originals), so that every group's count is a multiple of it and sums of counts stay exact in floating point.
MIN_GROUPS = tuple(2.0**-j for j in range(7))

_TYPE_NAMES = {float: "a number", int: "an integer", bool: "true or false", str: "a string", list: "a list"}


@dataclass(frozen=True)
class Param:
    """One case parameter.

    Attributes:
        default: value when the case does not set it (None: unset / derived at run time).
        unit: SI unit, "" if dimensionless, "-" for names and switches.
        help: one sentence for `febed params`.
        type: float, int, bool, str or list (a list of numbers, see `length`).
        lo, hi: inclusive bounds for numbers (list entries too); `lo_open` makes the lower bound strict.
        choices: allowed values for strings (or the items of a list of strings): a tuple or a Registry.
        length: required length of a list (None: any length >= 1).
        finite: numbers (and list entries) must be finite; inf and nan are refused unless False.
    """

    default: Any
    unit: str
    help: str
    type: type = float
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    choices: tuple[str, ...] | Registry | None = None
    length: int | None = None
    item: type = float
    finite: bool = True

    def allowed(self) -> str:
        """Human-readable description of the allowed values."""
        if self.choices is not None:
            names = ", ".join(repr(c) for c in self.choice_names())
            return f"a list of strings from {names}" if self.type is list else f"one of {names}"
        what = _TYPE_NAMES[self.type]
        if self.type is list:
            noun = "numbers" if self.item is float else "strings"
            what = f"a list of {self.length} {noun}" if self.length else f"a list of {noun}"
        rng = []
        if self.lo is not None:
            rng.append(f"{'>' if self.lo_open else '>='} {self.lo:g}")
        if self.hi is not None:
            rng.append(f"<= {self.hi:g}")
        return what + (" " + " and ".join(rng) if rng else "")

    def choice_names(self) -> list[str]:
        """The valid choices (imports the registry's module if needed)."""
        if isinstance(self.choices, Registry):
            return self.choices.names()
        return list(self.choices or ())

    def _in_range(self, x: float) -> bool:
        if isinstance(x, float) and (math.isnan(x) or (self.finite and math.isinf(x))):
            return False
        if self.lo is not None and (x < self.lo or (self.lo_open and x == self.lo)):
            return False
        return not (self.hi is not None and x > self.hi)

    def check(self, value: Any) -> tuple[Any, str | None]:
        """Return (converted value, None) or (None, message saying what is allowed)."""
        t = self.type
        bad = (None, f"expected {self.allowed()}")
        if _non_finite(value) and self.finite:
            bad = (None, f"expected {self.allowed()} (inf and nan are not allowed here)")
        if t is bool:
            return (value, None) if isinstance(value, bool) else bad
        if t is int:
            if isinstance(value, bool) or not isinstance(value, int):
                return bad
            if abs(value) > _INT_MAX:
                return None, f"expected {self.allowed()} (at most {_INT_MAX}: a 64-bit integer)"
            return (value, None) if self._in_range(value) else bad
        if t is float:
            if isinstance(value, bool) or not isinstance(value, int | float):
                return bad
            if isinstance(value, int) and abs(value) > _FLOAT_INT_MAX:
                return None, f"expected {self.allowed()} (a number this large overflows a 64-bit float)"
            value = float(value)
            return (value, None) if self._in_range(value) else bad
        if t is str:
            if not isinstance(value, str):
                return bad
            if self.choices is not None and value not in self.choice_names():
                return bad
            return value, None
        if t is list:
            if not isinstance(value, list):
                return bad
            if self.length is not None and len(value) != self.length:
                return bad
            if self.item is str:
                ok = all(isinstance(x, str) for x in value)
                ok = ok and (self.choices is None or all(x in self.choice_names() for x in value))
                return (value, None) if ok else bad
            if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in value):
                return bad
            if any(isinstance(x, int) and abs(x) > _FLOAT_INT_MAX for x in value):
                return None, f"expected {self.allowed()} (a number this large overflows a 64-bit float)"
            value = [float(x) for x in value]
            return (value, None) if all(self._in_range(x) for x in value) else bad
        raise TypeError(f"unsupported parameter type {t}")


_INT_MAX = 2**63 - 1  # integers are stored as int64
_FLOAT_INT_MAX = 10**308  # integers beyond this do not convert to a float


def _non_finite(value: Any) -> bool:
    """Whether value is (or, for a list, holds) an infinite or nan float."""
    items = value if isinstance(value, list) else [value]
    return any(isinstance(x, float) and not math.isfinite(x) for x in items)


INF = math.inf

SCHEMA: dict[str, dict[str, Param]] = {
    "run": {
        "name": Param("", "-", "case name (output folder name); default: the case file's stem", str),
        "mode": Param(
            "cfd-dem",
            "-",
            "what is solved: coupled gas and particles, particles only, gas only with a given void fraction, or "
            "particles in a prescribed gas ([prescribed_gas], one-way)",
            str,
            choices=("cfd-dem", "dem", "gas", "one-way"),
        ),
        "end_time": Param(
            1.0,
            "s",
            "the run stops at the end of the first gas step at or after this simulated time",
            float,
            lo=0.0,
            lo_open=True,
        ),
        "gravity": Param(9.81, "m/s^2", "gravity magnitude, along -z in 3D and -y in 2D", float, lo=0.0),
        "seed": Param(12345, "-", "random seed (insertion, coarse-grain placement)", int, lo=0),
        "max_overlap": Param(
            0.1,
            "",
            "the run fails if a contact's overlap exceeds this fraction of its smaller particle's diameter",
            float,
            lo=0.0,
            lo_open=True,
            hi=1.0,
        ),
        "particle_partition": Param(
            "auto",
            "-",
            "how the particles are shared among MPI ranks: 'mesh', each on the rank owning its mesh cell (the mesh "
            "cut in columns); 'work', boxes of equal DEM work (particles weighted by their listed pairs), cut again "
            "as the particles move, each particle coupled on its own rank over the whole mesh (the mesh cut in "
            "blocks); 'auto', 'work' in a pure-DEM run and 'mesh' otherwise",
            str,
            choices=("auto", "mesh", "work"),
        ),
        "max_clipped_fraction": Param(
            0.05,
            "",
            "the run fails if more than this share of the nodes has its void fraction clipped to the floor",
            float,
            lo=0.0,
            hi=1.0,
        ),
    },
    "mesh": {
        "file": Param("", "-", "gmsh .msh file with named physical groups (relative to the case file)", str),
        "builtin": Param(
            "",
            "-",
            "a built-in seed geometry instead of a file",
            str,
            choices=("", "pseudo2d", "wang2d", "cylinder", "box"),
        ),
        "level": Param(
            "coarse",
            "-",
            "built-in mesh level (pseudo2d: Table 2 of seed 001)",
            str,
            choices=("coarse", "intermediate", "fine"),
        ),
        "cell": Param(
            "hexahedron",
            "-",
            "built-in cell type; 2D geometries use quadrilateral/triangle",
            str,
            choices=("hexahedron", "tetrahedron", "quadrilateral", "triangle"),
        ),
        "size": Param(0.005, "m", "target cell size of unstructured built-in meshes", float, lo=0.0, lo_open=True),
        "extent": Param([], "m", "built-in box: its lengths [lx, ly] (2D) or [lx, ly, lz] (3D), cells of `size`", list),
        "depth": Param(
            0.0,
            "m",
            "2D meshes: depth that turns cell areas into volumes; 0 = one particle diameter",
            float,
            lo=0.0,
        ),
    },
    "gas": {
        "density": Param(1.2, "kg/m^3", "gas density (constant: incompressible VANS)", float, lo=0.0, lo_open=True),
        "viscosity": Param(1.8e-5, "Pa s", "gas dynamic viscosity", float, lo=0.0, lo_open=True),
        "les": Param("none", "-", "subgrid model", str, choices=("none", "smagorinsky")),
        "smagorinsky_cs": Param(0.17, "", "Smagorinsky constant C_s (filter width = cell size)", float, lo=0.0, hi=1.0),
        "cfl": Param(
            0.2, "", "largest convective CFL number of the gas step (seed 001 sec 2.4.1)", float, lo=0.0, lo_open=True
        ),
        "fourier": Param(0.15, "", "largest Fourier (viscous) number of the gas step", float, lo=0.0, lo_open=True),
        "dt_min": Param(1e-6, "s", "smallest gas time step allowed", float, lo=0.0, lo_open=True),
        "dt_max": Param(1e-3, "s", "largest gas time step allowed", float, lo=0.0, lo_open=True),
        "drag_weighted_projection": Param(
            True,
            "-",
            "pressure equation and velocity correction weighted by 1/(1+D), D = K dt/(rho_g eps), as the predictor's "
            "implicit drag: the pressure balances the step's drag, nothing lagged; false: the constant Laplacian, "
            "whose pressure lags by D/(1+D) per step (changes results at D of order 1)",
            bool,
        ),
        "pressure_passes": Param(
            1,
            "-",
            "predictor-correction passes per gas step; without the drag-weighted projection the pressure's lag "
            "behind the drag, D/(1+D) per step with D = K dt/(rho_g eps), becomes (D/(1+D))^passes, for one "
            "more Poisson solve per pass",
            int,
            lo=1,
            hi=10,
        ),
        "convection_substeps": Param(
            1,
            "-",
            "largest number of explicit sub-steps of the momentum predictor per gas step, each within the cfl and "
            "fourier limits: the gas step, its pressure solve and the coupling take up to this many times the "
            "convective step (the pressure and the drag of the step held through them); a step needs only as many "
            "as its CFL and Fourier numbers ask, one where dt_max is below the convective step",
            int,
            lo=1,
            hi=8,
        ),
        "drag_number": Param(
            0.0,
            "",
            "largest drag number K dt/(rho_g eps) of a gas step, K the nodal momentum-exchange coefficient of "
            "the previous step (0: no limit)",
            float,
            lo=0.0,
        ),
        "taylor_galerkin": Param(True, "-", "Lax-Wendroff streamline term that stabilises explicit convection", bool),
        "backflow": Param(
            1.0,
            "",
            "outlet backflow stabilisation beta: gas re-entering an outlet is braked by beta rho/2 |u.n| u (0 = off)",
            float,
            lo=0.0,
            hi=10.0,
        ),
        "mass_tolerance": Param(
            1e-6,
            "",
            "bound on the per-step gas mass imbalance as a fraction of the inflow",
            float,
            lo=0.0,
            lo_open=True,
            hi=1e-2,
        ),
        "pressure_rtol": Param(
            1e-8, "", "Poisson relative tolerance when no gas flows in", float, lo=0.0, lo_open=True
        ),
        "petsc_options": Param(
            "",
            "-",
            "PETSc options for the gas solves, e.g. '-febed_pressure_weighted_pc_type gamg' (the drag-weighted "
            "pressure solve) or '-febed_pressure_pc_type gamg' (the constant-Laplacian one)",
            str,
        ),
        "void_fraction": Param(
            1.0, "", "gas-only mode: uniform void fraction of the porous medium", float, lo=0.0, lo_open=True, hi=1.0
        ),
    },
    "particles": {
        "diameter": Param(
            1e-3, "m", "particle diameter (of original particles when coarse-graining)", float, lo=0.0, lo_open=True
        ),
        "density": Param(2500.0, "kg/m^3", "particle material density", float, lo=0.0, lo_open=True),
        "count": Param(0, "-", "number of particles to insert (or give bed_mass)", int, lo=0),
        "bed_mass": Param(0.0, "kg", "mass of particles to insert (or give count)", float, lo=0.0),
        "insertion": Param("random", "-", "how inserted particles are placed", str, choices=("random", "lattice")),
        "region": Param(
            [-INF, -INF, -INF, INF, INF, INF],
            "m",
            "insertion box [xmin, ymin, zmin, xmax, ymax, zmax]; infinite bounds are clipped to the mesh",
            list,
            length=6,
            finite=False,
        ),
        "bed_file": Param(
            "",
            "-",
            "packed bed (.npz) to load instead of inserting (relative to the case file); its particles must "
            "match count (or bed_mass, if given), diameter and density to a relative 1e-6 (of the parcels the "
            "case's [coarse_grain] would insert), or set bed_authoritative",
            str,
        ),
        "bed_authoritative": Param(
            False,
            "-",
            "an existing bed_file decides the particles: count, diameter and density are taken from it (logged, and "
            "written so to the resolved case) instead of having to match; false: a mismatch is an error",
            bool,
        ),
        "pack_if_missing": Param(
            True, "-", "if bed_file does not exist, insert and settle a bed and save it there", bool
        ),
        "settle_energy": Param(
            1e-9,
            "J",
            "settling stops when the mean kinetic energy per particle falls below this",
            float,
            lo=0.0,
            lo_open=True,
        ),
        "pack_restitution": Param(
            0.0,
            "-",
            "restitution of all contacts while a missing bed is packed (quicker settling); 0: the case's own",
            float,
            lo=0.0,
            hi=1.0,
        ),
        "settle_max_time": Param(
            10.0, "s", "packing a bed stops after this much simulated time at most", float, lo=0.0, lo_open=True
        ),
        "rotation": Param(True, "-", "integrate particle rotation (seed 001 switches it off)", bool),
        "fixed": Param(False, "-", "cfd-dem: the particles do not move (a fixed bed); the gas still sees them", bool),
    },
    "contact": {
        "model": Param("linear-history", "-", "contact law", str, choices=CONTACT_LAWS),
        "stiffness": Param(1000.0, "N/m", "normal spring stiffness k_n (seed 001 eq 8)", float, lo=0.0, lo_open=True),
        "stiffness_wall": Param(
            None, "N/m", "particle-wall normal stiffness; unset: the same as stiffness", float, lo=0.0, lo_open=True
        ),
        "reference_overlap": Param(
            0.005,
            "",
            "from_material: overlap (fraction of d) at which seed 000's Hertz/Mindlin stiffnesses (eqs 10-11) are "
            "linearised",
            float,
            lo=0.0,
            lo_open=True,
            hi=0.1,
        ),
        "tangential_ratio": Param(2.0 / 7.0, "", "k_t / k_n for linear-history", float, lo=0.0),
        "from_material": Param(False, "-", "derive k_n, k_t from young_modulus and poisson (seed 000 eqs 10-15)", bool),
        "young_modulus": Param(1e7, "Pa", "Young's modulus E (when from_material)", float, lo=0.0, lo_open=True),
        "poisson": Param(0.3, "", "Poisson ratio sigma (when from_material)", float, lo=0.0, hi=0.5),
        "restitution_pp": Param(
            0.9, "", "particle-particle normal restitution e_p", float, lo=0.0, lo_open=True, hi=1.0
        ),
        "restitution_pw": Param(0.9, "", "particle-wall normal restitution e_w", float, lo=0.0, lo_open=True, hi=1.0),
        "friction_pp": Param(0.3, "", "particle-particle Coulomb friction mu_p", float, lo=0.0),
        "friction_pw": Param(0.3, "", "particle-wall Coulomb friction mu_w", float, lo=0.0),
        "integrator": Param("rk2", "-", "particle time integrator (seed 001 eqs 40-41: rk2)", str, choices=INTEGRATORS),
        "dt_factor": Param(6.0, "", "DEM step = contact time T_C / dt_factor (seed 001 eq 42)", float, lo=1.0),
        "skin": Param(
            0.1, "", "neighbour-list skin as a fraction of the largest diameter", float, lo=0.0, lo_open=True, hi=2.0
        ),
    },
    "coupling": {
        "drag": Param("gidaspow-blend", "-", "drag closure", str, choices=DRAG_LAWS),
        "pressure_gradient": Param(True, "-", "include the pressure-gradient force -V_p grad p (seed 001 eq 27)", bool),
        "pressure_gradient_reaction": Param(
            "nodal",
            "-",
            "what the gas receives for the pressure-gradient force: nodal ((1 - eps_i) grad p_i at each node, so the"
            " gas carries -eps grad p as in seed 000 eq 26 and model-A codes; the particles get grad p averaged by"
            " the filter's transpose, so that the totals still balance) or projected (-sum w F_P, filtered, seed"
            " 001 eq 29: lowers a bed's pressure gradient on cells a quarter of its height or more)",
            str,
            choices=("projected", "nodal"),
        ),
        "filter_passes": Param(
            1, "-", "passes of the conservative neighbour filter (seed 001 eqs 31-34)", int, lo=0, hi=20
        ),
        "void_fraction_floor": Param(
            0.3, "", "void fraction is clipped below this (clipped nodes reported)", float, lo=0.0, hi=1.0
        ),
    },
    "coarse_grain": {
        "model": Param(
            "none",
            "-",
            "coarse-graining: none, traditional parcels (tm), rho d^2 rule (scg), dynamic groups (pcpm)",
            str,
            choices=("none", "tm", "scg", "pcpm"),
        ),
        "ratio": Param(
            1.0,
            "",
            "coarse-grain ratio l = d_parcel / d_original (tm, pcpm: l^3 whole originals per parcel; scg: any l)",
            float,
            lo=1.0,
        ),
        "tm_damping": Param(
            "force",
            "-",
            "tm dashpot: seed 000 eq 24 literally (force: l^3 times the originals' force) or keep the restitution",
            str,
            choices=("force", "restitution"),
        ),
        "eps_mf": Param(0.45, "", "pcpm: void fraction at minimum fluidization", float, lo=0.0, lo_open=True, hi=1.0),
        "u_mf": Param(0.0, "m/s", "pcpm: minimum fluidization velocity; 0 = Wen-Yu correlation", float, lo=0.0),
        "eps_max": Param(
            0.9997, "", "pcpm: void fraction at which d_cl = d_original (seed 000 eq 36)", float, lo=0.0, hi=1.0
        ),
        "max_group": Param(27, "originals", "pcpm: largest group after merging", int, lo=1),
        "min_group": Param(
            1.0,
            "originals",
            "pcpm: smallest group a crush may make; 1 keeps the originals whole, 1/2, 1/4, ... 1/64 makes them "
            "divisible into pieces of whole multiples of it (seed 000 sec 4)",
            float,
            lo=2.0**-6,
            hi=1.0,
        ),
        "overlap_tolerance": Param(
            0.05,
            "",
            "pcpm: largest overlap a crush or merge may create, fraction of the pair's smaller diameter",
            float,
            lo=0.0,
            hi=0.5,
        ),
        "merge_tolerance": Param(
            0.01, "", "pcpm: groups merge if |v_i - v_j| < this x max(|v_i|, |v_j|) (seed 000 eq 44)", float, lo=0.0
        ),
        "event_interval": Param(
            0.0,
            "s",
            "pcpm: simulated time between evaluations of the crush/merge criteria; 0 = 0.1 U_mf/g, a tenth of a "
            "group's relaxation time at minimum fluidization (febed.coarse.pcpm); below the gas step: every step",
            float,
            lo=0.0,
        ),
        "interval": Param(
            1,
            "-",
            "pcpm: of the gas steps at which the criteria are due (event_interval), use every this many",
            int,
            lo=1,
        ),  # fmt: skip
        "contact_power": Param(True, "-", "pcpm: include the contact power E_cc (seed 000 eq 38) in d_cl", bool),
        "placement_tries": Param(32, "-", "pcpm: random draws per crushed child's position", int, lo=1),
    },
    "prescribed_gas": {
        "flow": Param(
            "uniform", "-", "one-way: the prescribed gas velocity field", str, choices=("uniform", "vortex", "function")
        ),
        "velocity": Param([1.0, 0.0, 0.0], "m/s", "uniform: the gas velocity", list, length=3),
        "rpm": Param(0.0, "rev/min", "vortex: angular speed of the forced vortex", float),
        "inflow_ratio": Param(0.0, "", "vortex: radial inflow speed as a fraction of the vortex speed", float, lo=0.0),
        "center": Param([0.0, 0.0], "m", "vortex: position (x, y) of the vertical axis", list, length=2),
        "outlet_radius": Param(0.0, "m", "vortex: radius of the axial outlet core flow", float, lo=0.0),
        "outlet_velocity": Param(0.0, "m/s", "vortex: axial gas velocity inside outlet_radius", float),
        "function": Param("", "-", "function: 'module:function' returning u (N, 3) from x (N, 3) and t", str),
        "window": Param(0.0, "s", "drag held over windows of this length; 0 = tau_min / drag_factor", float, lo=0.0),
        "drag_factor": Param(
            20.0, "", "automatic drag window = shortest particle relaxation time / this", float, lo=0.0, lo_open=True
        ),  # fmt: skip
        "integration": Param(
            "exponential",
            "-",
            "drag over a window: exact exponential relaxation or explicit",
            str,
            choices=("exponential", "explicit"),
        ),  # fmt: skip
        "output_interval": Param(
            0.01, "s", "simulated time between rows of particles.csv", float, lo=0.0, lo_open=True
        ),  # fmt: skip
    },
    "output": {
        "directory": Param("", "-", "output folder; default ./runs/<case name>", str),
        "field_interval": Param(
            0.05,
            "s",
            "simulated time between field (XDMF) outputs; inf: none",
            float,
            lo=0.0,
            lo_open=True,
            finite=False,
        ),
        "particle_interval": Param(
            0.05, "s", "simulated time between particle outputs; inf: none", float, lo=0.0, lo_open=True, finite=False
        ),
        "probe_interval": Param(1e-3, "s", "simulated time between probe rows", float, lo=0.0, lo_open=True),
        "checkpoint_interval": Param(
            INF, "s", "simulated time between checkpoints; inf: none", float, lo=0.0, lo_open=True, finite=False
        ),
        "checkpoint_wall_interval": Param(
            3600.0,
            "s",
            "wall-clock time between checkpoints (either interval triggers one); inf: none",
            float,
            lo=0.0,
            lo_open=True,
            finite=False,
        ),
        "probe_heights": Param(
            [], "m", "heights (along gravity) where the cross-section averaged pressure is probed", list
        ),
        "bed_fraction": Param(
            0.95, "", "bed height = height below which this fraction of the particle volume lies", float, lo=0.5, hi=1.0
        ),
        "keep_checkpoints": Param(2, "-", "how many recent checkpoints are kept", int, lo=1),
        "progress_interval": Param(2.0, "s", "wall-clock seconds between progress lines", float, lo=0.0, lo_open=True),
    },
}

BOUNDARY: dict[str, Param] = {
    "type": Param(
        "wall",
        "-",
        "boundary condition on the facets of this mesh tag",
        str,
        choices=("inlet", "wall", "outlet", "symmetry"),
    ),
    "velocity": Param(
        None, "m/s", "inlet: superficial velocity U_f (mass inflow rho U_f A whatever eps)", float, lo=0.0
    ),
    "cross_section_tags": Param(
        [],
        "-",
        "inlet: U_f is superficial over the inlet plus these tags (seed 001: ['bottom_wall']), so the open part "
        "carries U_f A_total / A_open",
        list,
        item=str,
    ),
    "wins_over": Param(
        [],
        "-",
        "inlet: no-slip wall tags whose nodes on the inlet's edge take the inlet's velocity (default none: "
        "no-slip wins where they meet); e.g. ['bottom_wall'] narrows a patch's gas-free strip by two cells",
        list,
        item=str,
    ),
    "ramp_time": Param(0.0, "s", "inlet: ramp the velocity linearly from 0 over this time", float, lo=0.0),
    "slip": Param(False, "-", "wall: slip (true) or no-slip (false) for the gas", bool),
    "slip_normals": Param(
        [],
        "-",
        "wall with slip: only the tag's facets whose normal lies along these axes slip, the rest stay no-slip "
        "(e.g. ['y']: a pseudo-2D bed's front and back walls); default all",
        list,
        choices=("x", "y", "z"),
        item=str,
    ),
    "slip_length": Param(
        None,
        "m",
        "wall with slip: Navier slip length; the gas feels the shear eps mu_eff u_t / slip_length along the wall "
        "(partial slip; unset = free slip; must be > 0). Small values approach no-slip; "
        "demos/pseudo2d/C1-partial-slip-front-back.toml uses one particle diameter",
        float,
        lo=0.0,
        lo_open=True,
    ),
    "wall_law": Param(
        "brinkman",
        "-",
        "wall without slip: 'brinkman' lets the wall nodes slide with the shear of the Brinkman layer of the "
        "local drag (a packed bed's layer is far thinner than a cell; in clear gas it is no-slip), 'no_slip' "
        "holds them at rest (the gas of half a cell then stands still at the wall, a first-order error in a bed)",
        str,
        choices=("brinkman", "no_slip"),
    ),
    "pressure": Param(0.0, "Pa", "outlet: dynamic pressure", float),
    "particles": Param(
        True,
        "-",
        "wall or inlet: particles collide with these facets (false: nothing holds them, and a particle crossing "
        "them stops the run); outlet: particles leave through it and are counted (false: a lid for the "
        "particles, which bounce off it as off a wall while the gas still flows out)",
        bool,
    ),
}


def describe(section: str, key: str, par: Param) -> str:
    """One line for `febed params`: key, default, unit, allowed values, help."""
    default = "(unset)" if par.default is None else par.default
    unit = f" [{par.unit}]" if par.unit not in ("", "-") else ""
    return f"{section}.{key} = {default!r}{unit}  -- {par.help}; {par.allowed()}"


# ------------------------------------------------------------------------------ typed parameter objects
# The Python API's parameter objects (`febed.dem.solver.DEMParams`, `febed.gas.vans.VANSParameters`,
# `febed.coarse.oneway.OneWayCase`) declare no default or range of their own: a field made by
# `schema_field("section.key")` defaults to that key's declared default, and `check_fields` checks its value
# as the case validation checks the key. Their other fields are listed, with the reason, in the class's
# `NOT_IN_CASE` (tests/test_params_single_source.py holds every field to one or the other).


def param(key: str) -> Param:
    """The declaration of a case key given as "section.key" (e.g. "contact.stiffness")."""
    section, _, name = key.partition(".")
    try:
        return SCHEMA[section][name]
    except KeyError:
        raise KeyError(f"no parameter {key!r} is declared in febed/schema.py") from None


def schema_field(key: str) -> Any:
    """A dataclass field whose default is the declared default of `key` ("section.key"), checked against it."""
    default = param(key).default
    meta = {"schema": key}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


def schema_key(f: Field) -> str | None:
    """The case key ("section.key") a dataclass field was made for by `schema_field`, or None."""
    return f.metadata.get("schema")


def check_fields(obj: Any) -> None:
    """Raise ValueError naming the first `schema_field` of dataclass `obj` whose value its case key refuses.

    A key whose declared default is None (unset) accepts None. The message names the field, its value, the
    case key and what is allowed, e.g. `DEMParams.stiffness = -1.0 (contact.stiffness): expected a number > 0`.
    """
    for f in fields(obj):
        key = schema_key(f)
        if key is None:
            continue
        value = getattr(obj, f.name)
        par = param(key)
        if value is None and par.default is None:
            continue
        if getattr(value, "shape", None) == () and hasattr(value, "item"):
            value = value.item()  # a NumPy scalar: check it as the Python number it holds
        if isinstance(value, tuple) and par.type is list:
            value = list(value)
        _, err = par.check(value)
        if err:
            raise ValueError(f"{type(obj).__name__}.{f.name} = {getattr(obj, f.name)!r} ({key}): {err}")


# ------------------------------------------------------------------------------ restarts and identity
# The keys a restart may change: how a run is driven, written and discretised, not its physics or geometry
# (`febed.restart.case_changes`); every other key is part of what a checkpoint belongs to.
CHANGEABLE = (
    "run.end_time",
    "run.max_overlap",
    "run.max_clipped_fraction",
    "run.particle_partition",
    "output.*",
    "gas.cfl",
    "gas.fourier",
    "gas.dt_min",
    "gas.dt_max",
    "gas.drag_number",
    "gas.pressure_passes",
    "gas.convection_substeps",
    "gas.drag_weighted_projection",
    "contact.skin",
    "gas.petsc_options",
    "gas.pressure_rtol",
    "gas.mass_tolerance",
    "gas.backflow",
    "coupling.pressure_gradient_reaction",
)


def flatten_keys(d: dict, prefix: str = "") -> dict[str, object]:
    """A nested case table as {"section.key": value} (sub-tables joined with dots)."""
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten_keys(v, key + "."))
        else:
            out[key] = v
    return out


def physics_keys(case_toml: str) -> dict[str, object]:
    """The keys of a resolved case that a restart cannot change (every key but `CHANGEABLE` and the names)."""
    flat = flatten_keys(tomllib.loads(case_toml))
    return {
        k: v
        for k, v in sorted(flat.items())
        if k not in ("output.directory", "run.name", "extends") and not any(fnmatch(k, pat) for pat in CHANGEABLE)
    }


def physics_digest(case_toml: str) -> str:
    """A SHA-256 digest of `physics_keys` (hex)."""
    text = json.dumps(physics_keys(case_toml), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()
