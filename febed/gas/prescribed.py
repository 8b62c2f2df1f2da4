r"""Prescribed (one-way) gas: a given velocity field replaces the gas solver (seed 003 sec 2, 4-5).

The particles feel the gas; the gas does not feel them (void fraction 1). A field is chosen by name from
`PRESCRIBED_FLOWS` and built from plain keyword parameters:

* ``uniform``: u = U (m/s), a constant 3-vector (seed 003 sec 4, Fig 1).
* ``vortex``: a forced vortex about a vertical axis through `center` (x, y) with angular speed ω (rad/s, or
  `rpm`), superposed with a flow towards the axis whose speed is `inflow_ratio` times the vortex speed, and an
  axial `outlet_velocity` inside `outlet_radius` (seed 003 sec 4 and 5, Figs 4 and 7):

      u_θ = ω r,   u_r = -a ω r,   u_z = w if r < r_o else 0,

  i.e. u_x = -ω (y - y_c) - a ω (x - x_c), u_y = ω (x - x_c) - a ω (y - y_c). Seed 003 uses a = 0.1, w = 0
  (vortex test, 300 rpm) and a = 5, w = 1 m/s (classifier, 5000 rpm).
  A Stokes particle (τ = ρ_p d² / 18 μ) in this field drifts outwards if τ ω > a and inwards if τ ω < a, so the
  classifier's cut size is d_c = sqrt(18 μ a / (ρ_p ω)) (176 μm for Table 3's originals, between the 160 and
  220 μm the paper finds).
* ``function``: any Python function ``module:function`` taking (x (N, 3) m, t s) and returning u (N, 3) m/s.

2D cases use the x-y plane with the same formulas (u_z = 0).
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable

import numpy as np

from febed.registry import Registry

PRESCRIBED_FLOWS = Registry("prescribed flow", "febed.gas.prescribed")


class PrescribedGas:
    """A prescribed gas: velocity field u(x, t) (m/s), density ρ_g (kg/m^3), viscosity μ_g (Pa s), ε = 1."""

    def __init__(self, velocity: Callable, density: float = 1.2, viscosity: float = 1.8e-5, name: str = ""):
        """Wrap `velocity(x (N, 3), t) -> (N, 3)` with the gas properties."""
        if not (density > 0 and viscosity > 0):
            raise ValueError(f"density, viscosity: must be > 0, got {density}, {viscosity}")
        self._velocity = velocity
        self.density = float(density)
        self.viscosity = float(viscosity)
        self.name = name

    def velocity(self, x: np.ndarray, t: float = 0.0) -> np.ndarray:
        """Gas velocity (m/s) at points x (N, 3) (m) and time t (s), shape (N, 3)."""
        x = np.asarray(x, dtype=float)
        u = np.asarray(self._velocity(x, t), dtype=float)
        if u.shape != x.shape:
            raise ValueError(f"prescribed flow {self.name!r} returned shape {u.shape} for points of shape {x.shape}")
        return u

    def void_fraction(self, x: np.ndarray) -> np.ndarray:
        """Void fraction at x: 1 (one-way coupling: the particles take no volume from the gas)."""
        return np.ones(np.shape(x)[0])


@PRESCRIBED_FLOWS.register("uniform")
def uniform(velocity=(1.0, 0.0, 0.0)) -> Callable:
    """Uniform flow u = velocity (m/s, 3-vector)."""
    u0 = np.asarray(velocity, dtype=float)
    if u0.shape != (3,) or not np.all(np.isfinite(u0)):
        raise ValueError(f"velocity: must be a finite 3-vector (m/s), got {velocity!r}")

    def field(x, t):
        return np.broadcast_to(u0, np.shape(x)).copy()

    return field


@PRESCRIBED_FLOWS.register("vortex")
def vortex(omega=None, rpm=None, inflow_ratio=0.0, center=(0.0, 0.0), outlet_radius=0.0, outlet_velocity=0.0):
    """Forced vortex ω (rad/s, or rpm) + radial inflow inflow_ratio ω r + axial outlet core flow (seed 003 sec 4-5)."""
    if (omega is None) == (rpm is None):
        raise ValueError("vortex: give exactly one of omega (rad/s) and rpm")
    w = float(omega) if omega is not None else float(rpm) * 2.0 * math.pi / 60.0
    a = float(inflow_ratio)
    if not math.isfinite(w) or not a >= 0 or not outlet_radius >= 0:
        raise ValueError("vortex: need a finite omega, inflow_ratio >= 0, outlet_radius >= 0")
    cx, cy = (float(c) for c in center)
    ro2 = float(outlet_radius) ** 2
    wz = float(outlet_velocity)

    def field(x, t):
        dx = x[:, 0] - cx
        dy = x[:, 1] - cy
        u = np.empty_like(x)
        u[:, 0] = -w * dy - a * w * dx
        u[:, 1] = w * dx - a * w * dy
        u[:, 2] = np.where(dx * dx + dy * dy < ro2, wz, 0.0) if ro2 > 0 else 0.0
        return u

    return field


def load_function(spec: str) -> Callable:
    """The user function named 'module:function' (ValueError naming the spec if it cannot be imported)."""
    if not isinstance(spec, str) or spec.count(":") != 1:
        raise ValueError(f"function: expected 'module:function', got {spec!r}")
    mod, name = spec.split(":")
    try:
        f = getattr(importlib.import_module(mod), name)
    except (ImportError, AttributeError) as err:
        raise ValueError(f"function: cannot load {spec!r}: {err}") from None
    if not callable(f):
        raise ValueError(f"function: {spec!r} is not callable")
    return f


@PRESCRIBED_FLOWS.register("function")
def function(function: str = "") -> Callable:
    """A user velocity field 'module:function' with signature f(x (N, 3) m, t s) -> u (N, 3) m/s."""
    return load_function(function)


def make_prescribed_gas(kind: str, density: float = 1.2, viscosity: float = 1.8e-5, **params) -> PrescribedGas:
    """The prescribed gas `kind` (uniform | vortex | function) with its parameters (see module docstring)."""
    try:
        builder = PRESCRIBED_FLOWS.get(kind)
    except KeyError as err:
        raise ValueError(f"flow: {err.args[0]}") from None
    try:
        field = builder(**params)
    except TypeError as err:
        raise ValueError(f"flow {kind!r}: {err}") from None
    return PrescribedGas(field, density, viscosity, kind)
