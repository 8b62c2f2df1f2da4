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

import numpy as np

from febed.coupling.drag import drag_forces, get_drag_law
from febed.gas.prescribed import PrescribedGas

INTEGRATIONS = ("exponential", "explicit")


class OneWay:
    """A DEM in a prescribed gas: `advance(t_end)` moves the particles; `callback(self)` runs after each window."""

    def __init__(self, dem, gas: PrescribedGas, drag: str = "stokes", integration: str = "exponential",
                 drag_factor: float = 20.0, sink: Callable | None = None):  # fmt: skip
        """Couple `dem` to `gas` with a registered drag law; `sink(pos, diameter) -> bool mask` removes particles."""
        if integration not in INTEGRATIONS:
            raise ValueError(f"integration: must be one of {INTEGRATIONS}, got {integration!r}")
        if not drag_factor > 0:
            raise ValueError(f"drag_factor: must be > 0, got {drag_factor}")
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
        n_orig = P.n_orig[:n]
        d_orig = P.diameter[:n] if n_orig.max(initial=1) == 1 else P.diameter[:n] / np.cbrt(n_orig.astype(float))
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

    def advance(self, t_end: float, h: float | None = None, callback: Callable | None = None) -> None:
        """Advance to time t_end (s) in drag windows of h (default min(τ_min / drag_factor, DEM dt))."""
        while self.t < t_end * (1.0 - 1e-12):
            if h is not None:
                hh = h
            elif self.dem.particles.n_owned:
                hh = min(self.relaxation_time() / self.drag_factor, self.dem.dt)
            else:
                hh = t_end - self.t  # no particles: nothing happens (pass h when a callback feeds particles)
            hh = min(hh, t_end - self.t)
            self.step(hh)
            if callback is not None:
                callback(self)


@dataclass
class OneWayCase:
    """The parameters of a one-way run (`case_settings` reads them from a case with `[run] mode = "one-way"`).

    Attributes:
        flow: prescribed flow name (uniform | vortex | function); flow_params: its keyword parameters.
        drag: registered drag law; density, viscosity: gas ρ_g (kg/m^3), μ_g (Pa s).
        end_time: s; window: drag window h (s, 0 = auto); drag_factor: auto h = τ_min / drag_factor.
        integration: exponential | explicit; output_interval: s between particle CSV rows.
        progress_interval: wall-clock s between progress lines.
    """

    flow: str = "uniform"
    flow_params: dict = field(default_factory=dict)
    drag: str = "stokes"
    density: float = 1.2
    viscosity: float = 1.8e-5
    end_time: float = 1.0
    window: float = 0.0
    drag_factor: float = 20.0
    integration: str = "exponential"
    output_interval: float = 0.01
    progress_interval: float = 10.0


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
