"""What post-processing reads from a run folder: the resolved case, the particle snapshots, the domain box.

Everything here works on a run that is still going and on runs made on any number of ranks:

* the particle snapshots are the files listed in `particles/particles.pvd` that exist (the writer replaces
  each .vtp and the .pvd atomically, so a listed, existing file is complete); a file that cannot be parsed
  is skipped with a warning instead of stopping the post-processing;
* every snapshot is sorted by particle id (`gid`) before use, so sums do not depend on the order in which
  the ranks' particles were gathered: the results are bitwise the same whatever rank count wrote them.

The resolved case (`case.resolved.toml`, or `case.toml`) is read as plain TOML, so post-processing does
not depend on the current parameter schema accepting an older run's file.
"""

from __future__ import annotations

import binascii
import json
import logging
import math
import re
import tomllib
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from febed.coarse.scg import scg_particles

log = logging.getLogger("febed.post")

CASE_FILES = ("case.resolved.toml", "case.toml")


def _get(d: dict, dotted: str, default):
    for k in dotted.split("."):
        if not isinstance(d, dict) or k not in d:
            return default
        d = d[k]
    return d


@dataclass(frozen=True)
class RunInfo:
    """The physical scales of a run, from its resolved case and domain.

    Attributes:
        run_dir: the run's output folder.
        dim: 2 or 3 (gravity along -y in 2D, -z in 3D).
        lo, hi: the domain's bounding box (3,) in m.
        depth: extent along the averaged direction (3D: y; 2D: the case depth) in m.
        rho_p, rho_g: density of the simulated particles and of the gas (kg/m^3); for an SCG run (seed 003
            eq 7) rho_p is the CG density ρ_O d_O²/d_CG², so that mass fluxes and the bed weight are those of
            the simulated particles.
        d_p: particle diameter (m) of the case (original particles).
        u_f: inlet superficial velocity U_f (m/s); NaN if the case has no inlet.
        gravity: gravity magnitude (m/s^2).
        end_time: the run's end time (s).
    """

    run_dir: Path
    dim: int
    lo: np.ndarray
    hi: np.ndarray
    depth: float
    rho_p: float
    rho_g: float
    d_p: float
    u_f: float
    gravity: float
    end_time: float

    @property
    def axes(self) -> tuple[int, int]:
        """The (horizontal, vertical) axes of the averaged plane: (x, z) in 3D, (x, y) in 2D."""
        return (0, 2) if self.dim == 3 else (0, 1)

    @property
    def width(self) -> float:
        """Bed width L (m), along x."""
        return float(self.hi[0] - self.lo[0])

    @property
    def height(self) -> float:
        """Bed (domain) height H (m), along gravity."""
        v = self.axes[1]
        return float(self.hi[v] - self.lo[v])

    @property
    def cross_section(self) -> float:
        """Horizontal cross-section A = L x depth (m^2)."""
        return self.width * self.depth


def read_case(run_dir: str | Path) -> dict:
    """The run's resolved case as a plain dict (`case.resolved.toml`, else `case.toml`)."""
    run_dir = Path(run_dir)
    for name in CASE_FILES:
        if (run_dir / name).is_file():
            with open(run_dir / name, "rb") as f:
                return tomllib.load(f)
    raise ValueError(f"run_dir {run_dir}: no {' or '.join(CASE_FILES)} (is it a febed output folder?)")


def read_status(run_dir: str | Path) -> dict | None:
    """A run folder's status.json as a dict (`febed.io.rundir.write_status`); None if absent or unreadable."""
    try:
        return json.loads((Path(run_dir) / "status.json").read_text())
    except (OSError, ValueError):
        return None


def inlet_velocity(case: dict) -> float:
    """The superficial velocity U_f (m/s) of the case's first inlet, NaN without one."""
    for b in _get(case, "gas.boundary", {}).values():
        if b.get("type") == "inlet" and b.get("velocity") is not None:
            return float(b["velocity"])
    return math.nan


def _mesh_box_h5(run_dir: Path) -> tuple[np.ndarray, np.ndarray] | None:
    h5 = next((f for f in (run_dir / "fields" / "mesh.h5", run_dir / "fields.h5") if f.is_file()), None)
    if h5 is None:  # (fields.h5: the single field file of run folders written before fields/)
        return None
    try:
        import h5py

        with h5py.File(h5, "r") as f:
            geo = [f["Mesh"][k]["geometry"] for k in f.get("Mesh", {}) if "geometry" in f["Mesh"][k]]
            if not geo:
                return None
            x = np.asarray(geo[0][...], dtype=float)
    except (OSError, KeyError):
        return None
    lo = np.zeros(3)
    hi = np.zeros(3)
    lo[: x.shape[1]] = x.min(axis=0)
    hi[: x.shape[1]] = x.max(axis=0)
    return lo, hi


def _builtin_box(case: dict) -> tuple[np.ndarray, np.ndarray] | None:
    from febed.meshing import PSEUDO2D_BOX, WANG2D_BOX

    name = _get(case, "mesh.builtin", "")
    if name == "pseudo2d":
        return np.zeros(3), np.array(PSEUDO2D_BOX, dtype=float)
    if name == "wang2d":
        return np.zeros(3), np.array([*WANG2D_BOX, 0.0])
    ext = _get(case, "mesh.extent", [])
    if name == "box" and len(ext) in (2, 3):
        return np.zeros(3), np.array([*ext, 0.0][:3], dtype=float)
    return None


def run_info(run_dir: str | Path, box: tuple | None = None) -> RunInfo:
    """The scales of a run: resolved case + domain box (given, else the mesh of the field output, else built-in)."""
    run_dir = Path(run_dir)
    case = read_case(run_dir)
    if box is not None:
        lo, hi = (np.asarray(b, dtype=float) for b in box)
        if lo.shape != (3,) or hi.shape != (3,) or np.any(hi < lo):
            raise ValueError(f"box: expected ((xmin, ymin, zmin), (xmax, ymax, zmax)) with max >= min, got {box}")
    else:
        found = _mesh_box_h5(run_dir) or _builtin_box(case)
        if found is None:
            raise ValueError(
                f"run_dir {run_dir}: cannot tell the domain box (no fields/mesh.h5, not a built-in mesh); give box="
            )
        lo, hi = found
    dim = 2 if hi[2] - lo[2] <= 0.0 else 3
    d_p = float(_get(case, "particles.diameter", 1e-3))
    if dim == 3:
        depth = float(hi[1] - lo[1])
    else:
        depth = float(_get(case, "mesh.depth", 0.0)) or d_p  # a 2D case's depth defaults to one diameter
    return RunInfo(
        run_dir=run_dir,
        dim=dim,
        lo=lo,
        hi=hi,
        depth=depth,
        rho_p=_particle_density(case),
        rho_g=float(_get(case, "gas.density", 1.2)),
        d_p=d_p,
        u_f=inlet_velocity(case),
        gravity=float(_get(case, "run.gravity", 9.81)),
        end_time=float(_get(case, "run.end_time", math.nan)),
    )


def _particle_density(case: dict) -> float:
    """Material density of the simulated particles (kg/m^3): the case's, or the SCG rule's (seed 003 eq 7)."""
    rho = float(_get(case, "particles.density", 2500.0))
    if _get(case, "coarse_grain.model", "none") == "scg":
        ratio = float(_get(case, "coarse_grain.ratio", 1.0))
        return scg_particles(float(_get(case, "particles.diameter", 1e-3)), rho, ratio)[1]
    return rho


def list_snapshots(run_dir: str | Path, name: str = "particles") -> list[tuple[float, Path]]:
    """(time s, path) of the complete particle snapshots of a run, in time order (see module docstring)."""
    folder = Path(run_dir) / name
    pvd = folder / f"{name}.pvd"
    if not pvd.is_file():
        raise ValueError(f"run_dir {run_dir}: no particle output ({pvd} is missing)")
    root = ET.parse(pvd).getroot()
    out = []
    for ds in root.iter("DataSet"):
        f = folder / ds.get("file")
        if f.is_file():
            out.append((float(ds.get("timestep")), f))
    out.sort(key=lambda tf: tf[0])
    return out


_DATA_ARRAY = re.compile(
    rb'<DataArray type="(\w+)" Name="(\w+)" NumberOfComponents="(\d+)" format="binary">([^<]*)</DataArray>'
)
_DTYPES = {b"Float64": np.float64, b"Int64": np.int64, b"Int32": np.int32}
_WANTED = (b"Points", b"velocity", b"diameter", b"gid", b"n_orig")


def _read_vtp_arrays(path: Path) -> dict[str, np.ndarray]:
    """The arrays post-processing needs from a ParticleWriter .vtp (about twice as fast as a full XML parse)."""
    data = Path(path).read_bytes()
    if not data.rstrip().endswith(b"</VTKFile>"):
        raise ValueError("incomplete file")
    out = {}
    for m in _DATA_ARRAY.finditer(data):
        typ, name, ncomp, payload = m.groups()
        if name not in _WANTED:
            continue
        raw = binascii.a2b_base64(payload)
        size = int(np.frombuffer(raw[:8], dtype=np.uint64)[0])
        a = np.frombuffer(raw[8 : 8 + size], dtype=_DTYPES[typ])
        out[name.decode()] = a.reshape(-1, int(ncomp)) if int(ncomp) > 1 else a
    return out


def read_snapshot(path: str | Path) -> dict[str, np.ndarray] | None:
    """Arrays of one particle snapshot sorted by gid: pos (n, 3), velocity (n, 3), diameter, ...; None if unreadable."""
    from febed.io.particles import read_vtp

    try:
        a = _read_vtp_arrays(path)
        if not {"Points", "velocity", "diameter"} <= set(a):
            a = read_vtp(path)  # written some other way: the full parser
    except (ET.ParseError, ValueError, KeyError, OSError, binascii.Error) as e:
        log.warning(f"skipping unreadable particle file {path}: {e}")
        return None
    a["pos"] = a.pop("Points").reshape(-1, 3)
    a.pop("connectivity", None)
    a.pop("offsets", None)
    if "velocity" in a:
        a["velocity"] = a["velocity"].reshape(-1, 3)
    if "gid" in a:
        order = np.argsort(a["gid"], kind="stable")
        a = {k: v[order] for k, v in a.items()}
    return a


def select_window(
    snaps: list[tuple[float, Path]], window: tuple[float, float] | None
) -> tuple[list[tuple[float, Path]], tuple[float, float]]:
    """The snapshots inside the time window [t0, t1] (s); default window: the last half of the output."""
    if not snaps:
        raise ValueError("no particle snapshots to average")
    if window is None:
        t_last = snaps[-1][0]
        window = (snaps[0][0] + 0.5 * (t_last - snaps[0][0]), t_last)
    t0, t1 = (float(w) for w in window)
    if not t1 >= t0:
        raise ValueError(f"window: expected (t0, t1) with t1 >= t0 in s, got {window}")
    tol = 1e-9 * max(abs(t1), 1.0)
    chosen = [(t, p) for t, p in snaps if t0 - tol <= t <= t1 + tol]
    if not chosen:
        avail = f"{snaps[0][0]:g}..{snaps[-1][0]:g} s"
        raise ValueError(f"window: no particle snapshot between {t0:g} and {t1:g} s (output covers {avail})")
    return chosen, (t0, t1)
