"""Drag closures and the particle forces of the gas (seed 001 eqs 20-27, seed 000 eqs 2-6).

Every drag law has ONE signature and returns ONE quantity:

    K = law(eps, slip, d, rho_g, mu_g)

the momentum-exchange coefficient of one sphere of diameter d (m) in kg/s, K = m_p/τ_p (seed 001 eq 20)
= V_p β/(1 - ε) (seed 000 eq 2), so that the drag force on the particle is F_D = K (u_@p - v_p) (N) and the
gas receives -K (u - v) (implicit: K and K v go to the nodes). Arguments: local void fraction eps (> 0),
slip speed |u_@p - v_p| (m/s), d (m), gas density rho_g (kg/m^3), gas viscosity mu_g (Pa s). The particle
density cancels out of m_p/τ_p. Written with C_D Re_p (finite at zero slip) so K is finite at slip = 0.

Coarse-grained particles representing n_orig originals: K = n_orig * law(eps, slip, d_orig, ...), i.e. the
drag of the parcel is n_orig times that of one original particle at the parcel's velocity (`drag_kernel`); a
piece of a divisible original (n_orig < 1) has the drag of one sphere of its own diameter (the caller passes
d_orig and the count from `febed.coarse.setup.closure_sizes`).

Adding a law is one function with the signature above under `@drag_law("name")` and `@njit(cache=True)`;
nothing else. `drag_law` registers a `DragLaw` (name + function) in `febed.schema.DRAG_LAWS`, which gives
`coupling.drag` its choices. The batched kernels take the `DragLaw` as an argument and call it through
`law_value`, a Numba overload that dispatches at compile time on the law's Numba type `DragLawType(name)`
(as the contact laws dispatch on their parameter type): each kernel is compiled, and cached, once per law.
The type is keyed on the law's name, not on the identity of its Numba function, which differs in every
process: a kernel taking the jitted function itself would be compiled again in every process and its
on-disk cache index would grow until it could no longer be written. Laws belong in this module: the kernel
cache (`febed.kernel_cache`) is keyed on febed's sources, so an edit to a law defined elsewhere would not reach
kernels already cached with it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, types
from numba.core import cgutils
from numba.extending import NativeValue, models, overload, register_model, typeof_impl, unbox

from febed.kernel_records import fast_typeof
from febed.schema import DRAG_LAWS


class DragLaw:
    """A registered drag law: its name and Numba function `K = func(eps, slip, d, rho_g, mu_g)` (kg/s).

    Calling it calls the function; passed to a Numba kernel it has the type `DragLawType(name)`, through
    which `law_value` calls the function (compiled into the kernel).
    """

    def __init__(self, name: str, func):
        """Wrap the Numba function `func` of the law called `name`."""
        self.name = name
        self.func = func
        self.__doc__ = func.__doc__

    def __call__(self, eps, slip, d, rho_g, mu_g):
        """K (kg/s) of one sphere (see the module docstring)."""
        return self.func(eps, slip, d, rho_g, mu_g)

    def __repr__(self) -> str:
        return f"DragLaw({self.name!r})"


class DragLawType(types.Dummy):
    """Numba type of a `DragLaw` argument: one type per law name (so kernels are compiled once per law)."""

    def __init__(self, law_name: str):
        self.law_name = law_name
        super().__init__(name=f"DragLaw({law_name})")


register_model(DragLawType)(models.OpaqueModel)  # carries no data: the law is in the type


@typeof_impl.register(DragLaw)
def _typeof_drag_law(val, c):
    return DragLawType(val.name)


@unbox(DragLawType)
def _unbox_drag_law(typ, obj, c):
    return NativeValue(c.context.get_dummy_value(), is_error=cgutils.false_bit)


def drag_law(name: str):
    """Decorator registering the Numba drag-law function as the `DragLaw` `DRAG_LAWS[name]`; returns the function."""

    def deco(func):
        DRAG_LAWS.register(name)(DragLaw(name, func))
        return func

    return deco


# Layout of the per-particle exchange record `gas_forces_into` writes (row p; the solver keeps it as the FLUID
# auxiliary particle array). Read and write it through these names only.
RECORD_K = 0  # K_p (kg/s)
RECORD_FORCE = slice(1, 4)  # F_D + F_P (N), the fluid force the particle receives
RECORD_VEL = slice(4, 7)  # v_p (m/s) when the record was filled
RECORD_FP = slice(7, 10)  # F_P (N), the pressure-gradient part
RECORD_SET = 10  # 1.0 once the row is filled (rows added since have 0)
RECORD_COLUMNS = 11
_F0, _V0, _P0 = RECORD_FORCE.start, RECORD_VEL.start, RECORD_FP.start  # first columns, for the kernels


@njit(cache=True)
def _cd_re_single(re):
    """C_D Re_p of an isolated sphere: 24 (1 + 0.15 Re^0.687) below Re = 1000, 0.44 Re above (seed 001 eq 24)."""
    if re < 1000.0:
        return 24.0 * (1.0 + 0.15 * re**0.687)
    return 0.44 * re


@njit(cache=True)
def _k_from_cd_re(cd_re, d, mu_g):
    """K = m_p/τ_p = π μ d C_D Re_p / 8 (seed 001 eqs 20-21: τ_p = 4 ρ_p d² / (3 μ C_D Re_p))."""
    return math.pi * mu_g * d * cd_re / 8.0


@drag_law("stokes")
@njit(cache=True)
def stokes(eps, slip, d, rho_g, mu_g):
    """Stokes drag of an isolated sphere: K = 3 π μ d (kg/s); ε, slip and ρ_g unused (C_D = 24/Re)."""
    return 3.0 * math.pi * mu_g * d


@drag_law("schiller-naumann")
@njit(cache=True)
def schiller_naumann(eps, slip, d, rho_g, mu_g):
    """Schiller-Naumann drag of an isolated sphere: K = π μ d C_D Re / 8 (kg/s), ε unused.

    Re = ρ_g |u - v| d / μ; C_D = 24/Re (1 + 0.15 Re^0.687) for Re < 1000, 0.44 otherwise (seed 000 eq 4,
    seed 001 eq 24 without the ε^-2.7 factor); K = 3 π μ d (1 + 0.15 Re^0.687) below Re = 1000.
    """
    re = rho_g * slip * d / mu_g
    return _k_from_cd_re(_cd_re_single(re), d, mu_g)


@drag_law("wen-yu")
@njit(cache=True)
def wen_yu(eps, slip, d, rho_g, mu_g):
    """Wen & Yu drag as in seed 001 eq 24: K = π μ d C_D,WY Re_p / 8 (kg/s).

    Re_p = ε ρ_g |u - v| d / μ (eq 21); C_D,WY = 24/Re_p (1 + 0.15 Re_p^0.687) ε^-2.7 for Re_p < 1000,
    0.44 ε^-2.7 otherwise.
    """
    re = eps * rho_g * slip * d / mu_g
    return _k_from_cd_re(_cd_re_single(re) * eps**-2.7, d, mu_g)


@drag_law("ergun")
@njit(cache=True)
def ergun(eps, slip, d, rho_g, mu_g):
    """Ergun drag as in seed 001 eq 25: K = π μ d C_D,ER Re_p / 8 (kg/s).

    C_D,ER = (200 (1 - ε)/Re_p + 7/3) / ε, Re_p = ε ρ_g |u - v| d / μ, so
    K = π μ d (200 (1 - ε) + 7/3 Re_p) / (8 ε), the classical 150/1.75 Ergun with K = V_p β/(1 - ε).
    """
    re = eps * rho_g * slip * d / mu_g
    return _k_from_cd_re((200.0 * (1.0 - eps) + 7.0 / 3.0 * re) / eps, d, mu_g)


@drag_law("gidaspow-blend")
@njit(cache=True)
def gidaspow_blend(eps, slip, d, rho_g, mu_g):
    """Huilin-Gidaspow blend of Wen-Yu and Ergun, seed 001 eqs 20-25: K = φ K_WY + (1 - φ) K_ER (kg/s).

    φ_gs = arctan(150 * 1.75 (0.2 - (1 - ε))) / π + 0.5 (eq 22); C_D = φ C_D,WY + (1 - φ) C_D,ER (eq 23) with
    eqs 24-25 (see `wen_yu`, `ergun`); K = m_p/τ_p = π μ d C_D Re_p / 8 (eqs 20-21).
    """
    phi = math.atan(150.0 * 1.75 * (0.2 - (1.0 - eps))) / math.pi + 0.5
    return phi * wen_yu(eps, slip, d, rho_g, mu_g) + (1.0 - phi) * ergun(eps, slip, d, rho_g, mu_g)


@njit(cache=True)
def emms_heterogeneity(eps, re):
    """EMMS heterogeneity index H_d = a (Re_p + b)^c with a, b, c from seed 000 Table 1 (eq 6).

    ε is clamped into [0.4, 1], the range of the table (docs/theory.md, drag). Two signs are read differently from
    the printed table, which otherwise gives H_d < 0 for 0.46 < ε < 0.53 and a pole at ε = 0.9942: in 0.46 <= ε <
    0.545, a = 0.0320 + 0.7399/(1 + (ε/0.4912)^54.4265) (printed "-"; "+" joins the neighbouring ranges to within
    4 % at ε = 0.46 and 0.545), and in 0.99 <= ε < 0.9997 the logistic factor is 0.8800/(1 + exp(-(ε -
    0.9942)/0.00218)) (printed "1 - exp", which divides by zero at 0.9942).
    """
    e = min(max(eps, 0.4), 1.0)
    if e < 0.46:
        return 0.8526 - 0.5846 / (1.0 + (e / 0.4325) ** 22.6279)  # c = 0
    if e < 0.545:
        a = 0.0320 + 0.7399 / (1.0 + (e / 0.4912) ** 54.4265)
        b = (
            0.00225
            + 0.02404 / (1.0 + 10.0 ** (53.8948 * (0.5257 - e)))
            + 0.1731 / (1.0 + 10.0 ** (66.3224 * (e - 0.3987)))
        )
        c = 0.1705 - 0.1731 / (1.0 + (e / 0.5020) ** 37.7091)
        return a * (re + b) ** c
    if e < 0.99:
        a = (2124.956 - 2142.3 * e) ** -0.4896
        b = (0.8223 - 0.1293 * e) ** 13.0310
        x = e - 1.0013
        c = x / (-0.06633 + 9.1391 * x + 6.9231 * x * x)
        return a * (re + b) ** c
    if e < 0.9997:
        a = 0.4243 + 0.8800 / (1.0 + math.exp(-(e - 0.9942) / 0.00218)) * (
            1.0 - 1.0 / (1.0 + math.exp(-(e - 0.9989) / 0.00003))
        )
        b = 0.01661 + 0.2436 * math.exp(-0.5 * ((e - 0.9985) / 0.00191) ** 2)
        c = 0.0825 - 0.0574 * math.exp(-0.5 * ((e - 0.9979) / 0.00703) ** 2)
        return a * (re + b) ** c
    return 1.0  # a = 1, c = 0


@drag_law("emms")
@njit(cache=True)
def emms(eps, slip, d, rho_g, mu_g):
    """EMMS drag, seed 000 eqs 2-6 with Table 1: K = V_p β/(1 - ε) = π μ d C_d Re_p ε^-2.65 H_d / 8 (kg/s).

    β = 3/4 ε (1 - ε) ρ_g |u - v| / d ε^-2.65 C_d H_d (eq 3), C_d = 24 (1 + 0.15 Re^0.687)/Re for Re <= 1000,
    0.44 above (eq 4), Re_p = ε ρ_g |u - v| d / μ (eq 5), H_d from `emms_heterogeneity` (eq 6, Table 1).
    """
    re = eps * rho_g * slip * d / mu_g
    cd_re = 24.0 * (1.0 + 0.15 * re**0.687) if re <= 1000.0 else 0.44 * re
    return _k_from_cd_re(cd_re * eps**-2.65 * emms_heterogeneity(eps, re), d, mu_g)


def law_value(law, eps, slip, d, rho_g, mu_g):
    """K (kg/s) of the drag law `law` (a `DragLaw`); in Numba kernels it compiles to a direct call of the law."""
    return law.func(eps, slip, d, rho_g, mu_g)


@overload(law_value, jit_options={"cache": True})
def _law_value_ol(law, eps, slip, d, rho_g, mu_g):
    if not isinstance(law, DragLawType):
        return None
    func = DRAG_LAWS.get(law.law_name).func

    def impl(law, eps, slip, d, rho_g, mu_g):
        return func(eps, slip, d, rho_g, mu_g)

    return impl


def as_drag_law(law) -> DragLaw:
    """The registered `DragLaw` given by name, as a `DragLaw` or as its Numba function (ValueError otherwise)."""
    if isinstance(law, str):
        return get_drag_law(law)
    if isinstance(law, DragLaw):
        if DRAG_LAWS.get(law.name) is not law:
            raise ValueError(f"law: {law!r} is not the registered drag law {law.name!r}")
        return law
    for name in DRAG_LAWS.names():
        entry = DRAG_LAWS.get(name)
        if entry.func is law:
            return entry
    raise ValueError(f"law: {law!r} is not a registered drag law ({', '.join(DRAG_LAWS.names())})")


def _f64(a) -> np.ndarray:
    """`a` as a C-contiguous float64 array (no copy if it is one): each kernel compiles for one signature."""
    return np.ascontiguousarray(a, dtype=np.float64)


def drag_kernel(law, eps, u, v, d_orig, n_orig, rho_g, mu_g, K, F):
    """`_drag_kernel` for a law given by name, `DragLaw` or function (see there)."""
    _drag_kernel(as_drag_law(law), _f64(eps), _f64(u), _f64(v), _f64(d_orig), _f64(n_orig), rho_g, mu_g, K, F)


@njit(cache=True)
def _drag_kernel(law, eps, u, v, d_orig, n_orig, rho_g, mu_g, K, F):
    """Per-particle exchange coefficient K (N,) (kg/s) and drag force F (N, 3) (N) for the `DragLaw` law.

    K_p = n_orig,p law(ε_@p, |u_@p - v_p|, d_orig,p, ρ_g, μ_g) and F_p = K_p (u_@p - v_p) (seed 001 eq 20);
    eps (N,), gas velocity u (N, 3) and particle velocity v (N, 3) at the particles. Particles with ε <= 0
    (unlocated ones: `interpolate` gives them 0) get K = 0 and F = 0.
    """
    for p in range(eps.size):
        if not eps[p] > 0.0:
            K[p] = 0.0
            F[p, 0] = F[p, 1] = F[p, 2] = 0.0
            continue
        s0 = u[p, 0] - v[p, 0]
        s1 = u[p, 1] - v[p, 1]
        s2 = u[p, 2] - v[p, 2]
        slip = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
        k = n_orig[p] * law_value(law, eps[p], slip, d_orig[p], rho_g, mu_g)
        K[p] = k
        F[p, 0] = k * s0
        F[p, 1] = k * s1
        F[p, 2] = k * s2


@njit(cache=True)
def pressure_gradient_kernel(volume, grad_p, F):
    """Pressure-gradient force F_P = -V_p ∇p_@p (seed 001 eq 27): volume (N,) m^3, grad_p (N, g) Pa/m -> F (N, 3) N."""
    g = grad_p.shape[1]
    for p in range(volume.size):
        for a in range(3):
            F[p, a] = -volume[p] * grad_p[p, a] if a < g else 0.0


def get_drag_law(name: str):
    """The registered `DragLaw` called `name` (see the module docstring); ValueError listing the valid names."""
    try:
        return DRAG_LAWS.get(name)
    except KeyError as e:
        raise ValueError(f"drag: {e.args[0]}") from None


def drag_forces(law, eps, u, v, d_orig, n_orig, rho_g: float, mu_g: float, K=None, F=None):
    """Drag coefficients K (N,) kg/s and forces F (N, 3) N of N particles; `law` is a name or a registered law.

    eps (N,) void fraction at the particles, u (N, 3) gas velocity at the particles, v (N, 3) particle
    velocity (m/s), d_orig (N,) original diameter (m), n_orig (N,) originals per particle.
    """
    if isinstance(law, str):
        law = get_drag_law(law)
    n = np.shape(eps)[0]
    for name, a, shape in (("u", u, (n, 3)), ("v", v, (n, 3)), ("d_orig", d_orig, (n,)), ("n_orig", n_orig, (n,))):
        if np.shape(a) != shape:
            raise ValueError(f"{name}: must have shape {shape}, got {np.shape(a)}")
    if not (rho_g > 0.0 and mu_g > 0.0):
        raise ValueError(f"rho_g, mu_g: gas density and viscosity must be > 0, got {rho_g}, {mu_g}")
    K = np.empty(n) if K is None else K
    F = np.empty((n, 3)) if F is None else F
    drag_kernel(law, eps, u, v, d_orig, n_orig, float(rho_g), float(mu_g), K, F)
    return K, F


@fast_typeof
class AtParticles(NamedTuple):
    """The particles as the gas forces see them: their cells and node weights, velocities and sizes.

    `AtParticles.of` makes one with the dtypes the kernels are compiled for (int32 indices, float64 values).
    """

    cell_dofs: np.ndarray  # (cells, nv) int32: each cell's nodes
    cell: np.ndarray  # (N,) int32: each particle's cell (-1: not located)
    w: np.ndarray  # (N, nv): node weights (`febed.coupling.weights`)
    v: np.ndarray  # (N, 3) m/s
    d_orig: np.ndarray  # (N,) m: the diameter the drag law sees
    n_orig: np.ndarray  # (N,): originals each particle carries

    @classmethod
    def of(cls, cell_dofs, cell, w, v, d_orig, n_orig) -> AtParticles:
        """The record with C-contiguous int32 cell_dofs and cell and float64 arrays (no copy where they are)."""
        i32 = np.int32
        return cls(np.ascontiguousarray(cell_dofs, dtype=i32), np.ascontiguousarray(cell, dtype=i32), _f64(w),
                   _f64(v), _f64(d_orig), _f64(n_orig))  # fmt: skip


@fast_typeof
class NodalGas(NamedTuple):
    """The gas at the mesh nodes and its properties."""

    u: np.ndarray  # (nodes, gdim) m/s
    eps: np.ndarray  # (nodes,) void fraction
    gradp: np.ndarray  # (nodes, gdim) Pa/m
    rho: float  # kg/m^3
    mu: float  # Pa s
    pressure_gradient: bool  # add F_P = -V_p grad p (seed 001 eq 27)


@fast_typeof
class GasForces(NamedTuple):
    """What `gas_forces_into` writes; an output with 0 rows is skipped (`GasForces.of` fills those)."""

    K: np.ndarray  # (N,) kg/s
    F_d: np.ndarray  # (N, 3) N: drag
    F_p: np.ndarray  # (N, 3) N: pressure-gradient force
    eps_p: np.ndarray  # (N,): void fraction at the particle
    record: np.ndarray  # (N, RECORD_COLUMNS): the exchange record (`RECORD_*` columns)
    mass: np.ndarray  # (N,) kg, an input: with it the kernel returns min m_p / K_p

    @classmethod
    def of(cls, K=None, F_d=None, F_p=None, eps_p=None, record=None, mass=None) -> GasForces:
        """The outputs given, empty arrays (skipped) for the others."""
        return cls(
            _NONE1 if K is None else K, _NONE3 if F_d is None else F_d, _NONE3 if F_p is None else F_p,
            _NONE1 if eps_p is None else eps_p, _NO_RECORD if record is None else record,
            _NONE1 if mass is None else mass,
        )  # fmt: skip


_NONE1 = np.empty(0)
_NONE3 = np.empty((0, 3))
_NO_RECORD = np.empty((0, RECORD_COLUMNS))


def gas_forces_kernel(law, parts: AtParticles, gas: NodalGas, out: GasForces) -> float:
    """`gas_forces_into` for a law given by name, `DragLaw` or function (see there)."""
    return gas_forces_into(as_drag_law(law), AtParticles.of(*parts), gas, out)


@njit(cache=True)
def gas_forces_into(law, parts, gas, out):
    """Fused per-sub-step kernel: interpolate u, ε, ∇p (seed 001 eq 28), then drag (eq 20) and -V_p ∇p (eq 27).

    parts: `AtParticles`; gas: `NodalGas`; out: `GasForces`. Same results as `interpolate` + `drag_kernel` +
    `pressure_gradient_kernel`, in one pass; unlocated particles (cell < 0) get zero K, forces and ε.
    If out.record has N rows, row p gets K_p, F_D + F_P, v_p, F_P and 1 in the `RECORD_*` columns; if out.mass
    (N,) kg is given, returns min_p m_p / max(K_p, 1e-300) (the shortest particle relaxation time τ_p; NaN if
    any is NaN, inf without particles), else inf.
    """
    cell_dofs, cell, w, v, d_orig, n_orig = parts
    u_nodes, eps_nodes, gradp_nodes, rho_g, mu_g, with_pressure = gas
    K, F_d, F_p, eps_p, aux, mass = out
    nv = w.shape[1]
    g = u_nodes.shape[1]
    with_k = K.shape[0] > 0
    with_fd = F_d.shape[0] > 0
    with_fp = F_p.shape[0] > 0
    with_eps = eps_p.shape[0] > 0
    with_aux = aux.shape[0] > 0
    with_tau = mass.shape[0] > 0
    tau = math.inf
    nan_tau = False
    for p in range(cell.size):
        c = cell[p]
        k = e = 0.0
        fd0 = fd1 = fd2 = fp0 = fp1 = fp2 = 0.0
        if c >= 0:
            u0 = u1 = u2 = 0.0
            g0 = g1 = g2 = 0.0
            for i in range(nv):
                wi = w[p, i]
                dof = cell_dofs[c, i]
                e += wi * eps_nodes[dof]
                u0 += wi * u_nodes[dof, 0]
                u1 += wi * u_nodes[dof, 1]
                g0 += wi * gradp_nodes[dof, 0]
                g1 += wi * gradp_nodes[dof, 1]
                if g == 3:
                    u2 += wi * u_nodes[dof, 2]
                    g2 += wi * gradp_nodes[dof, 2]
            s0 = u0 - v[p, 0]
            s1 = u1 - v[p, 1]
            s2 = u2 - v[p, 2]
            if e > 0.0:
                k = n_orig[p] * law_value(law, e, math.sqrt(s0 * s0 + s1 * s1 + s2 * s2), d_orig[p], rho_g, mu_g)
            fd0 = k * s0
            fd1 = k * s1
            fd2 = k * s2
            vol = n_orig[p] * (math.pi / 6.0) * d_orig[p] ** 3 if with_pressure else 0.0
            fp0 = -vol * g0
            fp1 = -vol * g1
            fp2 = -vol * g2
        if with_k:
            K[p] = k
        if with_eps:
            eps_p[p] = e
        if with_fd:
            F_d[p, 0] = fd0
            F_d[p, 1] = fd1
            F_d[p, 2] = fd2
        if with_fp:
            F_p[p, 0] = fp0
            F_p[p, 1] = fp1
            F_p[p, 2] = fp2
        if with_aux:
            aux[p, RECORD_K] = k
            aux[p, _F0] = fd0 + fp0
            aux[p, _F0 + 1] = fd1 + fp1
            aux[p, _F0 + 2] = fd2 + fp2
            aux[p, _V0] = v[p, 0]
            aux[p, _V0 + 1] = v[p, 1]
            aux[p, _V0 + 2] = v[p, 2]
            aux[p, _P0] = fp0
            aux[p, _P0 + 1] = fp1
            aux[p, _P0 + 2] = fp2
            aux[p, RECORD_SET] = 1.0
        if with_tau:
            r = mass[p] / (k if not k < 1e-300 else 1e-300)  # np.maximum(K, 1e-300): NaN stays NaN
            if r != r:
                nan_tau = True
            elif r < tau:
                tau = r
    return math.nan if nan_tau else tau


def terminal_velocity(law, d: float, rho_p: float, rho_g: float, mu_g: float, g: float = 9.81, eps: float = 1.0):
    """Settling speed (m/s) of one sphere in still gas: K(v_t) v_t = (ρ_p - ρ_g) V g (drag = weight - buoyancy).

    Buoyancy is the pressure-gradient force -V ∇p of the hydrostatic gas (seed 001 eq 27). `law` is a name or
    a registered law; solved by bisection to 1e-12 relative. Reference value for the settling checks.
    """
    if isinstance(law, str):
        law = get_drag_law(law)
    if not (d > 0 and rho_p > rho_g > 0 and mu_g > 0 and g > 0 and 0 < eps <= 1):
        raise ValueError("d, rho_p, rho_g, mu_g, g, eps: need d > 0, rho_p > rho_g > 0, mu_g > 0, g > 0, 0 < eps <= 1")
    net = (rho_p - rho_g) * math.pi * d**3 / 6.0 * g
    lo, hi = 0.0, 1.0
    while law(eps, hi, d, rho_g, mu_g) * hi < net:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if law(eps, mid, d, rho_g, mu_g) * mid < net:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-12 * hi:
            break
    return 0.5 * (lo + hi)
