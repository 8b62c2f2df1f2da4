"""Time integrators of the particles, registered in `febed.schema.INTEGRATORS`: `rk2` (default) and `verlet`.

Each integrator advances the owned particles by up to `n_steps` steps of `dt` in one compiled loop and
returns early (after a whole step) when the pair list must be rebuilt: when the largest displacement since
the last build, plus the displacement the next step can make, exceeds half the skin. The caller rebuilds
and calls again. External forces `bodies.fext` (N, per particle: drag + pressure gradient from the
coupling) are held fixed over the steps; gravity is added in the force loop. The kernels take the named
records of `febed.dem.records` (`Bodies`, `Lists`, `Model`, `Scratch`) and a `febed.dem.walls.WallGeometry`.

2D mode: z components of velocity and x, y components of angular velocity are kept at zero.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from febed.dem.forces import compute_forces
from febed.schema import INTEGRATORS


@njit(cache=True, error_model="numpy")
def _kick(b, h, model):
    """Half kick v += h a, w += h alpha (same arithmetic as `_verlet_drift`, so a split run stays bit for bit)."""
    _pos, vel, omega, force, torque, fext, _diameter, mass, inertia, n_owned, _n = b  # arrays as locals, once
    rotation = model.rotation
    dim2 = model.dim2
    for i in range(n_owned):
        im = 1.0 / mass[i]
        ii = 1.0 / inertia[i] if rotation else 0.0
        for a in range(3):
            vel[i, a] += h * ((force[i, a] + fext[i, a]) * im)
            omega[i, a] += h * (torque[i, a] * ii)
        if dim2:
            vel[i, 2] = 0.0
            omega[i, 0] = 0.0
            omega[i, 1] = 0.0


@njit(cache=True, error_model="numpy")
def _verlet_drift(b, dt, kick, model, vp, wp, pos_ref, half_skin):
    """Fused pass: v += kick a; x += dt v; predicted v^n+1 = v + dt/2 a; returns True if a particle moved too far.

    kick is dt/2 (first step) or dt (the last half kick of the previous step fused with this one's); the dt
    kick is taken as two half kicks so that stopping between steps (`_kick`) gives the same bits.
    """
    pos, vel, omega, force, torque, fext, _diameter, mass, inertia, n_owned, _n = b  # arrays as locals, once
    rotation = model.rotation
    dim2 = model.dim2
    h = 0.5 * dt
    two = kick > h
    hs2 = half_skin * half_skin
    far = False
    for i in range(n_owned):
        im = 1.0 / mass[i]
        ii = 1.0 / inertia[i] if rotation else 0.0
        d2 = 0.0
        for a in range(3):
            acc = (force[i, a] + fext[i, a]) * im
            v = vel[i, a] + h * acc
            if two:
                v = v + h * acc
            if dim2 and a == 2:
                v = 0.0
            vel[i, a] = v
            x = pos[i, a] + dt * v
            pos[i, a] = x
            vp[i, a] = v + h * acc
            d = x - pos_ref[i, a]
            d2 += d * d
            alpha = torque[i, a] * ii
            w = omega[i, a] + h * alpha
            if two:
                w = w + h * alpha
            if dim2 and a < 2:
                w = 0.0
            omega[i, a] = w
            wp[i, a] = w + h * alpha
        if not d2 <= hs2:  # NaN too: the rebuild reports it (`DEM._blow_up`)
            far = True
    return far


@njit(cache=True, error_model="numpy")
def _verlet_predict(b, h, model, vp, wp):
    """Predicted velocities v + dt/2 a of the owned particles after a rebuild (as `verlet_steps` on resume)."""
    _pos, vel, omega, force, torque, fext, _diameter, mass, inertia, n_owned, _n = b  # arrays as locals, once
    rotation = model.rotation
    for i in range(n_owned):
        im = h / mass[i]
        ii = h / inertia[i] if rotation else 0.0
        for a in range(3):
            vp[i, a] = vel[i, a] + im * (force[i, a] + fext[i, a])
            wp[i, a] = omega[i, a] + ii * torque[i, a]


@njit(cache=True, error_model="numpy")
def verlet_steps(n_steps, dt, b, lists, walls, model, pos_ref, half_skin, resume, s):
    """Velocity Verlet for up to n_steps of dt (s); returns (steps completed, largest overlap / smaller diameter, code).

    code 0: done; 2: a particle moved more than half the skin during the drift of the next step: rebuild the
    lists and call again with resume=True (the drift is done, the force evaluation resumes).
    The kick of one step and the kick + drift of the next are fused in one pass over the particles.
    Velocity-dependent contact forces (damping, friction) use the predicted velocities v^n + dt a^n
    (s.vel, s.omega), which keeps the damped impact second order away from the contact-start/end jumps.
    """
    worst = 0.0
    h = 0.5 * dt
    vp = s.vel
    wp = s.omega
    for i in range(b.n_owned, b.n):  # ghosts: their velocities as given
        for a in range(3):
            vp[i, a] = b.vel[i, a]
            wp[i, a] = b.omega[i, a]
    if resume:
        _verlet_predict(b, h, model, vp, wp)
    elif _verlet_drift(b, dt, h, model, vp, wp, pos_ref, half_skin):
        return 0, worst, 2
    for k in range(n_steps):
        w = compute_forces(b, vp, wp, lists, lists.hist, lists.whist, walls, model, dt, dt)
        worst = max(worst, w)
        if k + 1 == n_steps:
            _kick(b, h, model)
        elif _verlet_drift(b, dt, dt, model, vp, wp, pos_ref, half_skin):
            return k + 1, worst, 2
    return n_steps, worst, 0


@njit(cache=True, error_model="numpy")
def rk2_steps(n_steps, dt, b, lists, walls, model, pos_ref, half_skin, resume, s):
    """RK2 of seed 001 eqs 40-41 for up to n_steps of dt (s); returns (steps, largest overlap / smaller diameter, code).

    code 0: done; 1: rebuild the lists before the next step (displacement since the build plus dt |v| exceeds
    half the skin). `resume` is not used (the signature is the integrators' common one).
    """
    worst = 0.0
    h = 0.5 * dt
    for k in range(n_steps):
        # forces at t^n; the tangential elongation is not advanced (dt_eval = 0), its update goes to scratch;
        # the regularised Coulomb cap uses the whole step (with dt/2 the slip would stop at the midpoint and the
        # second stage would see no friction at all)
        compute_forces(b, b.vel, b.omega, lists, s.hist, s.whist, walls, model, 0.0, dt)
        _rk2_half(b, h, model, s)
        w = compute_forces(b, b.vel, b.omega, lists, lists.hist, lists.whist, walls, model, h, dt)
        worst = max(worst, w)
        far = _rk2_full(b, dt, model, s, pos_ref)
        if far > half_skin:
            return k + 1, worst, 1
    return n_steps, worst, 0


@njit(cache=True, error_model="numpy")
def _rk2_half(b, h, model, s):
    """Save the state in `s` (Scratch) and take the half step of seed 001 eq 40."""
    pos, vel, omega, force, torque, fext, _diameter, mass, inertia, n_owned, _n = b  # arrays as locals, once
    x0, v0, w0, _h, _wh = s
    rotation = model.rotation
    dim2 = model.dim2
    for i in range(n_owned):
        im = h / mass[i]
        ii = h / inertia[i] if rotation else 0.0
        for a in range(3):
            x0[i, a] = pos[i, a]
            v0[i, a] = vel[i, a]
            w0[i, a] = omega[i, a]
            pos[i, a] += h * vel[i, a]  # seed 001 eq 40
            vel[i, a] += im * (force[i, a] + fext[i, a])
            omega[i, a] += ii * torque[i, a]
        if dim2:
            vel[i, 2] = 0.0
            omega[i, 0] = 0.0
            omega[i, 1] = 0.0


@njit(cache=True, error_model="numpy")
def _rk2_full(b, dt, model, s, pos_ref):
    """Full step of seed 001 eq 41 from the state saved in `s`; returns max |x - x_ref| + dt |v| (m; inf if NaN)."""
    pos, vel, omega, force, torque, fext, _diameter, mass, inertia, n_owned, _n = b  # arrays as locals, once
    x0, v0, w0, _h, _wh = s
    rotation = model.rotation
    dim2 = model.dim2
    worst = 0.0
    for i in range(n_owned):
        im = dt / mass[i]
        ii = dt / inertia[i] if rotation else 0.0
        d2 = 0.0
        v2 = 0.0
        for a in range(3):
            x = x0[i, a] + dt * vel[i, a]  # seed 001 eq 41
            v = v0[i, a] + im * (force[i, a] + fext[i, a])
            if dim2 and a == 2:
                v = 0.0
            w = w0[i, a] + ii * torque[i, a]
            if dim2 and a < 2:
                w = 0.0
            pos[i, a] = x
            vel[i, a] = v
            omega[i, a] = w
            d = x - pos_ref[i, a]
            d2 += d * d
            v2 += v * v
        reach = math.sqrt(d2) + dt * math.sqrt(v2)
        if not reach <= worst:
            worst = reach if reach == reach else np.inf  # NaN: rebuild, and the rebuild reports it
    return worst


def rk2_staged(dem, n_steps: int, dt: float) -> float:
    """RK2 steps stage by stage with ghost updates before each force evaluation (MPI); returns the max overlap ratio.

    Same kernels and arithmetic as `rk2_steps`. The end-of-step ghost update carries the rebuild criterion's
    reduction over the ranks (two synchronisations per step).
    """
    ex = dem.exchange
    rotation = dem.params.rotation
    h = 0.5 * dt
    worst = 0.0
    P = dem.particles
    b, lists, walls, model, s = dem.kernel_args()
    ex.update_ghosts(P, P.vel, P.omega, spin=rotation)
    for _ in range(n_steps):
        compute_forces(b, b.vel, b.omega, lists, s.hist, s.whist, walls, model, 0.0, dt)
        _rk2_half(b, h, model, s)
        ex.update_ghosts(P, P.vel, P.omega, spin=rotation)
        w = compute_forces(b, b.vel, b.omega, lists, lists.hist, lists.whist, walls, model, h, dt)
        worst = max(worst, w)
        far = _rk2_full(b, dt, model, s, dem.pos_ref)
        if (
            ex.update_ghosts(P, P.vel, P.omega, far, rotation) > 0.5 * dem.pairs.skin
        ):  # ghosts ready for the next step ...
            dem.rebuild()  # ... unless the lists must be rebuilt (which refreshes them)
            P = dem.particles
            b, lists, walls, model, s = dem.kernel_args()
    return worst


def verlet_staged(dem, n_steps: int, dt: float) -> float:
    """Velocity Verlet step by step, ghosts updated before each force evaluation (MPI); returns the max overlap ratio.

    Same kernels and arithmetic as `verlet_steps`; the ghost update after each drift carries the rebuild
    criterion's reduction over the ranks (one synchronisation per step).
    """
    ex = dem.exchange
    rotation = dem.params.rotation
    h = 0.5 * dt
    worst = 0.0
    P = dem.particles
    b, lists, walls, model, s = dem.kernel_args()
    half_skin = 0.5 * dem.pairs.skin
    far = _verlet_drift(b, dt, h, model, s.vel, s.omega, dem.pos_ref, half_skin)
    resume = ex.update_ghosts(P, s.vel, s.omega, float(far), rotation) > 0.0
    for k in range(n_steps):
        if resume:
            dem.rebuild()
            P = dem.particles
            b, lists, walls, model, s = dem.kernel_args()
            half_skin = 0.5 * dem.pairs.skin
            _verlet_predict(b, h, model, s.vel, s.omega)
            ex.update_ghosts(P, s.vel, s.omega, spin=rotation)
        w = compute_forces(b, s.vel, s.omega, lists, lists.hist, lists.whist, walls, model, dt, dt)
        worst = max(worst, w)
        if k + 1 == n_steps:
            _kick(b, h, model)
        else:
            far = _verlet_drift(b, dt, dt, model, s.vel, s.omega, dem.pos_ref, half_skin)
            resume = ex.update_ghosts(P, s.vel, s.omega, float(far), rotation) > 0.0
    return worst


class Integrator:
    """A registered integrator: its compiled multi-step loop and how many force evaluations a step costs."""

    def __init__(self, name: str, steps, force_evals: int, needs_initial_forces: bool, staged=None):
        """Wrap the compiled loop `steps` under `name`; `staged(dem, n, dt)` steps with ghost updates (MPI)."""
        self.name = name
        self.steps = steps
        self.staged = staged
        self.force_evals = force_evals
        self.needs_initial_forces = needs_initial_forces

    def __repr__(self) -> str:
        return f"Integrator({self.name!r})"


INTEGRATORS.register("verlet")(Integrator("verlet", verlet_steps, 1, True, verlet_staged))
INTEGRATORS.register("rk2")(Integrator("rk2", rk2_steps, 2, False, rk2_staged))


def get_integrator(name: str) -> Integrator:
    """The registered integrator called `name` (ValueError listing the valid names otherwise)."""
    try:
        return INTEGRATORS.get(name)
    except KeyError as err:
        raise ValueError(str(err)) from None


def _tc(p, m_eff: float) -> float:
    kn, ce = p.stiffness, p.ce
    if hasattr(p, "m_ref"):  # particle-groups (`linear_groups`): the pair's TM scaling, l^3 = m_eff / m_ref
        ratio = (m_eff / p.m_ref) ** (1.0 / 3.0)  # < 1 for pieces of a divisible original, as in the law
        kn, ce = kn * ratio * ratio, min(ce * math.sqrt(ratio), 0.999)
    w0 = math.sqrt(kn / m_eff)  # seed 001 eq 17
    return math.pi / (w0 * math.sqrt(1.0 - ce * ce))  # seed 001 eqs 18-19


def critical_time(law, pp, pw, mass: np.ndarray, diameter: np.ndarray, rotation: bool, walls: bool = True) -> float:
    """Shortest contact time T_C (s, seed 001 eq 19) over the pair types present: lightest particle pairs.

    Particle-particle pairs of the two lightest particles, particle-wall contact of the lightest one, and,
    for a law with a tangential spring, the tangential half period with the matching effective mass.
    """
    if mass.size == 0:
        raise ValueError("critical_time needs at least one particle")
    order = np.argsort(mass)
    ma = float(mass[order[0]])
    mb = float(mass[order[1]]) if mass.size > 1 else ma
    ra = 0.5 * float(diameter[order[0]])
    rb = 0.5 * float(diameter[order[1]]) if mass.size > 1 else ra
    rot = 1.0 if rotation else 0.0
    ia = 0.4 * ma * ra * ra
    ib = 0.4 * mb * rb * rb
    m_pp = ma * mb / (ma + mb)
    t = _tc(pp, m_pp)
    mt_pp = 1.0 / (1.0 / ma + 1.0 / mb + rot * (ra * ra / ia + rb * rb / ib))
    t = min(t, law.tangential_time(pp, mt_pp))
    if walls:
        t = min(t, _tc(pw, ma))
        t = min(t, law.tangential_time(pw, 1.0 / (1.0 / ma + rot * ra * ra / ia)))
    return t
