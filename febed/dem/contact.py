"""Contact laws: one pure Numba function per law, chosen by name through `febed.schema.CONTACT_LAWS`.

A law computes the force of one contact on particle a from the overlap, the unit normal from a to its
partner b (a particle, or a wall = a particle of infinite mass and zero radius, seed 001 sec 2.2.1), the
relative velocity of a's surface with respect to b's at the contact point, the effective normal and
tangential masses, and the pair's tangential history. Signature (all floats):

    fx, fy, fz, hx, hy, hz = law(p, delta, nx, ny, nz, vx, vy, vz, m_eff, mt_eff, hx0, hy0, hz0, dt_eval, dt_store)

`p` is the law's parameter namedtuple (named fields, one for particle-particle and one for particle-wall
pairs). The law is *passed into* the neighbour loop through the type of `p`: `pair_force(p, ...)` is a
Numba overload that dispatches at compile time on the parameter class, so the force loops in
`febed.dem.forces` are written once and compiled (and cached) once per law. (Numba 0.56 cannot cache
kernels that take a jitted function as an argument, hence the dispatch on the parameter type.)
The compiled force loops are cached under a key of the kernels' sources (`febed.kernel_cache`): after a
law is edited they are recompiled with it.

`h` is the tangential spring elongation of the pair (m), oriented as a's displacement relative to b.
`dt_eval` is the time over which the current tangential velocity is added to the stored elongation for
the force evaluated now, `dt_store` the time for the elongation stored for the next step (and the step
that limits the regularised Coulomb force of `linear`).
"""

from __future__ import annotations

import math
from collections import namedtuple
from dataclasses import dataclass

import numpy as np
from numba import njit, types
from numba.extending import overload

from febed.schema import CONTACT_LAWS

LinearParams = namedtuple("LinearParams", "stiffness ce friction")
LinearParams.__doc__ = (
    "Spring-dashpot + Coulomb: stiffness k_n (N/m, `contact.stiffness` or `stiffness_wall`), ce = gamma_n/omega_0 "
    "from e_n (seed 001 eq 18), friction mu (`contact.friction_pp` or `friction_pw`)."
)
HistoryParams = namedtuple("HistoryParams", "stiffness ce friction stiffness_t cet")
# fastmath without the NaN/Inf assumptions and without reassociation: reciprocals and FMA contraction only change
# round-off (the conservation and restitution tests pass with the same tolerances). Reassociation would make the
# results depend on Numba's cache: a kernel that calls the force loop (an integrator) holds its own copy of it,
# optimised again inside the caller, and which copy runs depends on the order the compiled code was loaded (a
# run that compiles the kernels calls the loop's own, a run from the cache the integrator's copy); with
# reassociation the two copies differ in their last bits (tests/dem/test_compiled_equals_cached.py).
FAST = {"nsz", "arcp", "contract", "afn"}

HistoryParams.__doc__ = "linear + tangential spring stiffness_t (N/m) with damping ratio cet, Coulomb cap friction."


def damping_ratio(e: float) -> float:
    """gamma_n / omega_0 for a restitution coefficient 0 < e <= 1 (seed 001 eq 18)."""
    if not 0.0 < e <= 1.0:
        raise ValueError(f"restitution coefficient must be in (0, 1], got {e}")
    le = math.log(e)
    return -le / math.sqrt(math.pi**2 + le * le)


def contact_time(kn: float, e: float, m_eff: float) -> float:
    """Duration T_C (s) of a linear spring-dashpot contact (seed 001 eqs 17-19)."""
    w0 = math.sqrt(kn / m_eff)  # seed 001 eq 17
    g = damping_ratio(e) * w0  # seed 001 eq 18
    return math.pi / math.sqrt(w0 * w0 - g * g)  # seed 001 eq 19


def stiffness_from_material(
    young: float,
    poisson: float,
    radius: float,
    overlap: float,
    wall_young: float | None = None,
    wall_poisson: float | None = None,
) -> tuple[float, float]:
    """Linear k_n, k_t (N/m) from E (Pa) and sigma (seed 000 eqs 10-12), as secants at a reference overlap (m).

    Seed 000's kappa_n (eq 10a/11a) is a Hertz coefficient (N/m^1.5) and kappa_t (eq 10b/11b) a Mindlin
    stiffness that grows with sqrt(overlap); a linear law needs N/m, so both are evaluated at `overlap`
    (k_n = kappa_n sqrt(overlap)). With `wall_young`/`wall_poisson` the particle-wall forms (eq 11) are used.
    """
    if young <= 0 or radius <= 0 or overlap <= 0 or not 0 <= poisson <= 0.5:
        raise ValueError("need young > 0, radius > 0, overlap > 0 and 0 <= poisson <= 0.5")
    g = young / (2.0 * (1.0 + poisson))  # seed 000 eq 12
    if wall_young is None:
        kappa_n = math.sqrt(2.0 * radius) * young / (3.0 * (1.0 - poisson**2))  # seed 000 eq 10a
        kt = 2.0 * math.sqrt(2.0 * radius) * g / (2.0 - poisson) * math.sqrt(overlap)  # seed 000 eq 10b
    else:
        sw = poisson if wall_poisson is None else wall_poisson
        kappa_n = 4.0 * math.sqrt(radius) / 3.0 / ((1 - poisson**2) / young + (1 - sw**2) / wall_young)  # eq 11a
        kt = 8.0 * math.sqrt(radius) * g / (2.0 - poisson) * math.sqrt(overlap)  # seed 000 eq 11b
    return kappa_n * math.sqrt(overlap), kt


@dataclass(frozen=True)
class ContactLaw:
    """A registered contact law: its Numba function, parameter class and whether it keeps pair history."""

    name: str
    func: object
    params_class: type
    history: bool

    def params(self, stiffness: float, e: float, friction: float, stiffness_t: float = 0.0) -> tuple:
        """Parameter namedtuple for one pair type: stiffness, stiffness_t (N/m), restitution e, friction."""
        if stiffness <= 0 or friction < 0 or stiffness_t < 0:
            raise ValueError(f"contact law {self.name!r}: need stiffness > 0, stiffness_t >= 0, friction >= 0")
        ce = damping_ratio(e)
        if self.params_class is LinearParams:
            return LinearParams(float(stiffness), ce, float(friction))
        return HistoryParams(float(stiffness), ce, float(friction), float(stiffness_t), ce)

    def tangential_time(self, p: tuple, mt_eff: float) -> float:
        """Half period (s) of the tangential spring for effective tangential mass mt_eff (inf if none)."""
        if not self.history or p.stiffness_t <= 0:
            return math.inf
        return math.pi / math.sqrt(p.stiffness_t / mt_eff)


@njit(cache=True, inline="always", fastmath=FAST, error_model="numpy")
def _normal(p, delta, nx, ny, nz, vx, vy, vz, m_eff):
    vn = vx * nx + vy * ny + vz * nz
    # seed 001 eq 8 (+ eq 18: gamma_n = ce * omega_0, 2 gamma_n M = 2 ce sqrt(kn M)); force on a along n
    fn = -p.stiffness * delta - 2.0 * p.ce * math.sqrt(p.stiffness * m_eff) * vn
    return fn, vx - vn * nx, vy - vn * ny, vz - vn * nz  # seed 001 eqs 13-14


@njit(cache=True, fastmath=FAST, error_model="numpy")
def linear(p, delta, nx, ny, nz, vx, vy, vz, m_eff, mt_eff, hx, hy, hz, dt_eval, dt_store):
    """Spring-dashpot normal force + Coulomb sliding (seed 001 eqs 8-19), force on a (N).

    The sliding force -mu |f_n| t (eq 9) is capped at the force that stops the slip in one step,
    mt_eff |u_t| / dt_store, so friction may stop the tangential slip but never reverse it.
    """
    fn, tx, ty, tz = _normal(p, delta, nx, ny, nz, vx, vy, vz, m_eff)
    fx = fn * nx
    fy = fn * ny
    fz = fn * nz
    vt = math.sqrt(tx * tx + ty * ty + tz * tz)
    if vt > 0.0 and p.friction > 0.0:
        ft = p.friction * abs(fn)  # seed 001 eq 9
        if dt_store > 0.0:
            ft = min(ft, mt_eff * vt / dt_store)
        s = -ft / vt  # t = u_t / |u_t| (seed 001 eq 15)
        fx += s * tx
        fy += s * ty
        fz += s * tz
    return fx, fy, fz, 0.0, 0.0, 0.0


@njit(cache=True, inline="always", fastmath=FAST, error_model="numpy")
def _spring(p, fn_abs, tx, ty, tz, vt_damp, hx, hy, hz, dt):
    ex = hx + dt * tx
    ey = hy + dt * ty
    ez = hz + dt * tz
    fx = -p.stiffness_t * ex - vt_damp * tx
    fy = -p.stiffness_t * ey - vt_damp * ty
    fz = -p.stiffness_t * ez - vt_damp * tz
    f2 = fx * fx + fy * fy + fz * fz
    cap = p.friction * fn_abs
    if f2 > cap * cap:  # Coulomb limit: slide, and reset the spring to the elongation the capped force implies
        s = cap / math.sqrt(f2)
        fx *= s
        fy *= s
        fz *= s
        if p.stiffness_t > 0.0:
            ex = -(fx + vt_damp * tx) / p.stiffness_t
            ey = -(fy + vt_damp * ty) / p.stiffness_t
            ez = -(fz + vt_damp * tz) / p.stiffness_t
    return fx, fy, fz, ex, ey, ez


@njit(cache=True, fastmath=FAST, error_model="numpy")
def linear_history(p, delta, nx, ny, nz, vx, vy, vz, m_eff, mt_eff, hx, hy, hz, dt_eval, dt_store):
    """Normal force of `linear` + tangential spring-dashpot with Coulomb slider (seed 000 eqs 7-9), force on a (N).

    The stored elongation is first projected onto the current tangent plane (as LAMMPS' hooke/history), then
    grows by u_t dt; the tangential damping is 2 cet sqrt(k_t mt_eff) (seed 000 eq 13b with the restitution's ratio).
    """
    fn, tx, ty, tz = _normal(p, delta, nx, ny, nz, vx, vy, vz, m_eff)
    hn = hx * nx + hy * ny + hz * nz  # project the elongation on the current tangent plane
    px = hx - hn * nx
    py = hy - hn * ny
    pz = hz - hn * nz
    damp = 2.0 * p.cet * math.sqrt(p.stiffness_t * mt_eff)
    fabs = abs(fn)
    ftx, fty, ftz, ex, ey, ez = _spring(p, fabs, tx, ty, tz, damp, px, py, pz, dt_eval)
    if dt_store != dt_eval:
        _, _, _, ex, ey, ez = _spring(p, fabs, tx, ty, tz, damp, px, py, pz, dt_store)
    return fn * nx + ftx, fn * ny + fty, fn * nz + ftz, ex, ey, ez


GroupParams = namedtuple("GroupParams", "stiffness ce friction m_ref")
GroupParams.__doc__ = (
    "`linear` of the originals scaled per pair by TM (seed 000 eqs 24-25): stiffness (N/m), ce, friction of one "
    "original pair, "
    "m_ref (kg) the effective mass of an original pair (m_O/2, or m_O for walls)."
)


# Cube roots of the whole numbers of originals a pair of equal groups can have (l^3 = m_eff / m_ref = n), a
# compile-time constant of the kernels: in a PCPM bed most contacts are between groups of one size.
_MAX_TABLED = 128  # largest pair ratio l^3 whose cube root `_pair_ratio` takes from the table
_CUBE_ROOTS = tuple(float(np.cbrt(n)) for n in range(_MAX_TABLED + 1))


@njit(cache=True, inline="always", fastmath=FAST, error_model="numpy")
def _pair_ratio(r):
    """The pair ratio l = r^(1/3) for l^3 = r: from `_CUBE_ROOTS` when r is a whole number to 1e-9, else by pow.

    The table's root is corrected to first order in the rounding of r (relative error (r/n - 1)^2 / 9 < 1e-18,
    below double precision), so both paths give the cube root to rounding; the table spares the pow of every
    contact between equal groups, about a fifth of a PCPM bed's DEM time.
    """
    n = int(r + 0.5)
    if n >= 1 and n <= _MAX_TABLED and abs(r - n) <= 1e-9 * n:
        return _CUBE_ROOTS[n] * (1.0 + (r - n) / (3.0 * n))
    return r ** (1.0 / 3.0)


@njit(cache=True, fastmath=FAST, error_model="numpy")
def linear_groups(p, delta, nx, ny, nz, vx, vy, vz, m_eff, mt_eff, hx, hy, hz, dt_eval, dt_store):
    """`linear` for particle-groups of any sizes: TM scaling with the pair's own ratio l, force on a (N).

    l^3 = m_eff / m_ref (the pair's effective mass in original pairs: l for two groups of l^3 originals, the
    harmonic mean of l_a^3 and l_b^3 otherwise, m_a / m_O against a wall); then k_n = l^2 kn and
    c_e = ce sqrt(l) (capped at 0.99, overdamped otherwise) as `febed.coarse.tm.tm_contact_params`, so that the
    force is l^3 times the original pair's at overlap delta/l (seed 000 eq 24); Coulomb friction unchanged.
    """
    l_ = _pair_ratio(m_eff / p.m_ref)
    kn = p.stiffness * l_ * l_
    ce = min(p.ce * math.sqrt(l_), 0.99)
    vn = vx * nx + vy * ny + vz * nz
    fn = -kn * delta - 2.0 * ce * math.sqrt(kn * m_eff) * vn  # seed 001 eq 8 with seed 000 eq 24 scaling
    fx = fn * nx
    fy = fn * ny
    fz = fn * nz
    tx = vx - vn * nx
    ty = vy - vn * ny
    tz = vz - vn * nz
    vt = math.sqrt(tx * tx + ty * ty + tz * tz)
    if vt > 0.0 and p.friction > 0.0:
        ft = p.friction * abs(fn)  # seed 001 eq 9 / seed 000 eq 25
        if dt_store > 0.0:
            ft = min(ft, mt_eff * vt / dt_store)
        s = -ft / vt
        fx += s * tx
        fy += s * ty
        fz += s * tz
    return fx, fy, fz, 0.0, 0.0, 0.0


_LAWS = {
    GroupParams: ContactLaw("linear-groups", linear_groups, GroupParams, False),
    LinearParams: CONTACT_LAWS.register("linear")(ContactLaw("linear", linear, LinearParams, False)),
    HistoryParams: CONTACT_LAWS.register("linear-history")(
        ContactLaw("linear-history", linear_history, HistoryParams, True)
    ),
}


def pair_force(p, delta, nx, ny, nz, vx, vy, vz, m_eff, mt_eff, hx, hy, hz, dt_eval, dt_store):
    """Force of one contact on a and its new tangential elongation, by the law whose parameters `p` are."""
    law = _LAWS[type(p)]
    return law.func(p, delta, nx, ny, nz, vx, vy, vz, m_eff, mt_eff, hx, hy, hz, dt_eval, dt_store)


@overload(pair_force, jit_options={"cache": True})
def _pair_force_ol(p, delta, nx, ny, nz, vx, vy, vz, m_eff, mt_eff, hx, hy, hz, dt_eval, dt_store):
    cls = getattr(p, "instance_class", None) if isinstance(p, types.BaseTuple) else None
    if cls not in _LAWS:
        return None
    func = _LAWS[cls].func

    def impl(p, delta, nx, ny, nz, vx, vy, vz, m_eff, mt_eff, hx, hy, hz, dt_eval, dt_store):
        return func(p, delta, nx, ny, nz, vx, vy, vz, m_eff, mt_eff, hx, hy, hz, dt_eval, dt_store)

    return impl


def get_law(name: str) -> ContactLaw:
    """The registered contact law called `name` (ValueError listing the valid names otherwise)."""
    try:
        return CONTACT_LAWS.get(name)
    except KeyError as err:
        raise ValueError(str(err)) from None


__all__ = [
    "ContactLaw",
    "GroupParams",
    "HistoryParams",
    "LinearParams",
    "contact_time",
    "damping_ratio",
    "get_law",
    "linear",
    "linear_groups",
    "linear_history",
    "pair_force",
    "stiffness_from_material",
    "np",
]
