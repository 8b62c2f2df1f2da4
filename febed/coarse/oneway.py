r"""One-way driver: DEM particles moved by a prescribed gas (seed 003 sec 2: the particles do not act on the gas).

Each drag window of length h, the drag is evaluated once from the gas velocity at the particles,
K_p = n_orig law(1, |u - v|, d_orig) (`febed.coupling.drag`), then the DEM advances ⌈h / Δt_DEM⌉ sub-steps with
that force held fixed (contacts, walls and gravity are the DEM's).

Drag integration (`integration`):
* ``exponential`` (default): the force held over the window is K (u - v) φ(h/τ_p), φ(x) = (1 - e^{-x})/x,
  τ_p = m_p/K_p, so that the velocity change over the window is the exact (u - v)(1 - e^{-h/τ_p}) of a frozen
  gas velocity and drag coefficient: stable for any h, exact for linear drag in a uniform flow.
* ``explicit``: F = K (u - v) (forward Euler in the drag); needs h ≪ τ_p.

The default window is h = min(τ_p,min / 20, dt) (`drag_factor`). A case with `[run] mode = "one-way"` runs
through `febed.runs.oneway` (`case_settings` reads its parameters).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from febed.coarse.setup import closure_sizes
from febed.coupling.drag import drag_forces, get_drag_law
from febed.gas.prescribed import PrescribedGas
from febed.schema import check_fields, param, schema_field

INTEGRATIONS = tuple(param("prescribed_gas.integration").choices)
# `OneWay`'s defaults: those of the case keys
_DRAG, _INTEGRATION, _DRAG_FACTOR = (
    param(key).default for key in ("coupling.drag", "prescribed_gas.integration", "prescribed_gas.drag_factor")
)


class OneWay:
    """A DEM in a prescribed gas: `advance(t_end)` moves the particles; `callback(self)` runs after each window."""

    def __init__(self, dem, gas: PrescribedGas, drag: str = _DRAG, integration: str = _INTEGRATION,
                 drag_factor: float = _DRAG_FACTOR, sink: Callable | None = None):  # fmt: skip
        """Couple `dem` to `gas` with a registered drag law; `sink(pos, diameter) -> bool mask` removes particles.

        The defaults and allowed values of `drag`, `integration` and `drag_factor` are those of the case keys
        `coupling.drag`, `prescribed_gas.integration` and `prescribed_gas.drag_factor`.
        """
        if getattr(dem, "exchange", None) is not None:  # its windows and sub-steps are this process's own
            raise ValueError("OneWay: the DEM has an MPI exchange attached; the one-way driver runs on one process")
        for name, key, value in (("integration", "prescribed_gas.integration", integration),
                                 ("drag_factor", "prescribed_gas.drag_factor", drag_factor)):  # fmt: skip
            _, err = param(key).check(value)
            if err:
                raise ValueError(f"{name} = {value!r} ({key}): {err}")
        self.dem = dem
        self.gas = gas
        self.law = get_drag_law(drag)
        self.integration = integration
        self.drag_factor = float(drag_factor)
        self.sink = sink
        self.t = 0.0
        self.removed = 0
        self.windows = 0

    def _drag(self, h: float) -> tuple[np.ndarray, np.ndarray]:
        """Drag force (N, (n, 3)) held over a window of h (s), and the particles' relaxation times τ_p (s)."""
        P = self.dem.particles
        n = P.n_owned
        x = P.pos[:n]
        v = P.vel[:n]
        d_orig, n_orig = closure_sizes(P.diameter[:n], P.n_orig[:n])
        u = self.gas.velocity(x, self.t)
        K, F = drag_forces(self.law, np.ones(n), u, v, d_orig, n_orig, self.gas.density, self.gas.viscosity)
        tau = P.mass[:n] / np.maximum(K, 1e-300)
        if self.integration == "exponential":
            r = h / tau
            phi = np.where(r > 1e-12, -np.expm1(-r) / np.where(r > 1e-12, r, 1.0), 1.0)
            F *= phi[:, None]
        return F, tau

    def relaxation_time(self) -> float:
        """Smallest particle relaxation time m_p/K_p (s) at the current slip."""
        n = self.dem.particles.n_owned
        return float(self._drag(0.0)[1].min()) if n else math.inf

    def step(self, h: float) -> None:
        """One drag window of h (s): drag evaluated now, then DEM sub-steps of at most the DEM's dt."""
        dem = self.dem
        if dem.particles.n_owned:
            n_sub = max(1, math.ceil(h / dem.dt * (1.0 - 1e-12)))
            f, _ = self._drag(h)
            dem.advance(n_sub, h / n_sub, f)
        else:
            dem.advance(1, h)  # nothing to move: the clock advances
        self.t += h
        self.windows += 1
        if self.sink is not None and dem.particles.n_owned:
            P = dem.particles
            gone = np.asarray(self.sink(P.pos[: P.n_owned], P.diameter[: P.n_owned]), dtype=bool)
            if gone.any():
                self.removed += int(gone.sum())
                dem.remove_particles(gone)

    def window(self, t_end: float, h: float | None = None) -> float:
        """The next drag window (s): h (default min(τ_min / drag_factor, DEM dt)), ending at t_end at the latest.

        With no particles the window reaches t_end (nothing happens; pass h when a callback feeds particles).
        """
        if h is None:
            n = self.dem.particles.n_owned
            h = min(self.relaxation_time() / self.drag_factor, self.dem.dt) if n else t_end - self.t
        return min(h, t_end - self.t)

    def advance(self, t_end: float, h: float | None = None, callback: Callable | None = None) -> None:
        """Advance to time t_end (s) in drag windows of h (default min(τ_min / drag_factor, DEM dt))."""
        while self.t < t_end * (1.0 - 1e-12):
            self.step(self.window(t_end, h))
            if callback is not None:
                callback(self)

    def get_state(self) -> dict:
        """The driver's own state beyond the DEM's (JSON-able): its time (s), drag windows made, particles removed.

        The drag is evaluated afresh at the start of each window, so between windows this and the DEM's state
        (`DEM.get_state`) are the whole state: `set_state` on a new `OneWay` over the restored DEM continues bit
        for bit.
        """
        return {"t": self.t, "windows": self.windows, "removed": self.removed}

    def set_state(self, state: dict) -> None:
        """Take back a state of `get_state` (the DEM's own state is restored by the DEM)."""
        self.t, self.windows, self.removed = float(state["t"]), int(state["windows"]), int(state["removed"])


@dataclass
class OneWayCase:
    """The parameters of a one-way run (`case_settings` reads them from a case with `[run] mode = "one-way"`).

    Each field but `NOT_IN_CASE`'s is the case key of its name in the section `case_settings` reads it from;
    its default and allowed values are that key's in `febed/schema.py`. A value the key refuses is a
    ValueError naming the field and the key when the object is made.

    Attributes:
        flow: prescribed flow name (uniform | vortex | function); flow_params: its keyword parameters.
        drag: registered drag law; density, viscosity: gas ρ_g (kg/m^3), μ_g (Pa s).
        end_time: s; window: drag window h (s, 0 = auto); drag_factor: auto h = τ_min / drag_factor.
        integration: exponential | explicit; output_interval: s between particle CSV rows.
        progress_interval: wall-clock s between progress lines.
    """

    # fields that are no single case key, and why
    NOT_IN_CASE: ClassVar[dict[str, str]] = {
        "flow_params": "the keyword parameters of `flow`, gathered from its [prescribed_gas] keys by case_settings",
    }

    flow: str = schema_field("prescribed_gas.flow")
    flow_params: dict = field(default_factory=dict)
    drag: str = schema_field("coupling.drag")
    density: float = schema_field("gas.density")
    viscosity: float = schema_field("gas.viscosity")
    end_time: float = schema_field("run.end_time")
    window: float = schema_field("prescribed_gas.window")
    drag_factor: float = schema_field("prescribed_gas.drag_factor")
    integration: str = schema_field("prescribed_gas.integration")
    output_interval: float = schema_field("prescribed_gas.output_interval")
    progress_interval: float = schema_field("output.progress_interval")

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ValueError naming the first parameter out of range (the ranges of `febed/schema.py`)."""
        check_fields(self)
        if not isinstance(self.flow_params, dict):
            raise ValueError(f"OneWayCase.flow_params must be a dict of keyword parameters, got {self.flow_params!r}")


def case_settings(case) -> OneWayCase:
    """The `OneWayCase` of a case file's `[prescribed_gas]`, `[gas]`, `[coupling] drag` and `[run]`."""
    g = case.prescribed_gas
    flow_params = {
        "uniform": lambda: {"velocity": tuple(g.velocity)},
        "vortex": lambda: {
            "rpm": g.rpm,
            "inflow_ratio": g.inflow_ratio,
            "center": tuple(g.center),
            "outlet_radius": g.outlet_radius,
            "outlet_velocity": g.outlet_velocity,
        },  # fmt: skip
        "function": lambda: {"function": g.function},
    }[g.flow]()
    if g.flow == "function" and ":" not in g.function:
        raise ValueError(f"[prescribed_gas] function = {g.function!r}: give 'module:function'")
    return OneWayCase(
        flow=g.flow, flow_params=flow_params, drag=case.coupling.drag, density=case.gas.density,
        viscosity=case.gas.viscosity, end_time=case.run.end_time, window=g.window, drag_factor=g.drag_factor,
        integration=g.integration, output_interval=g.output_interval,
        progress_interval=case.output.progress_interval,
    )  # fmt: skip
