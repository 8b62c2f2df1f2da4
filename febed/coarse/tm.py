r"""Traditional coarse grain (TM): parcels of l^3 original particles, seed 000 eqs 17-25.

A parcel of ratio l has diameter l d_O, the material density, mass l^3 m_O and `n_orig` = l^3. Gravity (eq 23),
the drag (eq 21: n_orig times the drag of one original at the parcel velocity, with d_O in the closure, see
`febed.coupling.drag.drag_kernel`) and the pressure-gradient force (eq 22) then follow from the particle
arrays alone. Only the contact law needs new parameters, which this module derives.

Contact scaling (eqs 24-25). Read the parcel's overlap as the originals' overlap magnified by the geometric
similarity, delta_CG = l delta_O, at the same relative velocity (eq 19). Eq 24 then asks for

    F_CG = l^3 (-kappa_n delta_O - eta_n v_n) = -(l^2 kappa_n) delta_CG - (l^3 eta_n) v_n,

so the parcel law is the same spring-dashpot with

* stiffness k_n' = l^2 kappa_n (and k_t' = l^2 kappa_t, eq 25; the wall stiffness likewise);
* dashpot eta_n' = l^3 eta_n. With eta = 2 c_e sqrt(m_eff k) (seed 001 eq 18) and m_eff' = l^3 m_eff this is
  c_e' = c_e sqrt(l): the damping ratio grows as sqrt(l) and the parcel restitution
  e' = exp(-pi c_e' / sqrt(1 - c_e'^2)) is *lower* than e (e = 1 stays 1);
* natural frequency omega_0' = sqrt(k_n'/m_eff') = omega_0 / sqrt(l), decay rate gamma' = c_e' omega_0' = gamma
  (unchanged), so the contact time is

      T_C' = pi / sqrt(omega_0^2 / l - gamma^2)  ->  sqrt(l) T_C for elastic contacts (e = 1),

  and the DEM step T_C'/dt_factor grows with it (`febed.dem.solver.DEM.dt` follows from the parameters);
* Coulomb friction mu unchanged (eq 25: l^3 mu |F_n,O| = mu |F_n,CG|).

The parcel contact is overdamped when c_e sqrt(l) >= 1 (e = 0.9: l < 890; e = 0.5: l < 21): refused with a
ValueError. `damping="restitution"` is offered instead of the literal eq 24 (eta' = l^2.5 eta: same e,
T_C' = sqrt(l) T_C for every e), the common choice in later coarse-grain work.

Rotation needs nothing: I_CG = l^5 I_O and the torque r_CG x F_t = l^4 torque_O give omega_CG = omega_O / l
(eq 20). For l = 1 every function here returns its input unchanged, so TM at l = 1 is plain DEM bit for bit.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from febed.dem.contact import GroupParams, LinearParams, damping_ratio

DAMPING_MODES = ("force", "restitution")


def check_ratio(ratio: float) -> int:
    """The integer number of originals l^3 of a parcel of ratio l (ValueError unless l >= 1 and l^3 is integral)."""
    if not (isinstance(ratio, int | float) and math.isfinite(ratio) and ratio >= 1.0):
        raise ValueError(f"coarse_grain.ratio: l must be a finite number >= 1, got {ratio!r}")
    n = round(ratio**3)
    if abs(ratio**3 - n) > 1e-9 * n:
        raise ValueError(
            f"coarse_grain.ratio: a parcel stands for l^3 whole originals; l = {ratio} gives l^3 = {ratio**3:.6g}. "
            "Use l = k^(1/3) for an integer k (e.g. 1, 2, 3, or 2**(1/3))"
        )
    return int(n)


def restitution_from_ratio(ce: float) -> float:
    """Restitution e of a linear spring-dashpot whose damping ratio gamma/omega_0 is ce (inverse of damping_ratio)."""
    if not 0.0 <= ce < 1.0:
        raise ValueError(f"damping ratio must be in [0, 1) for a contact that ends, got {ce}")
    return math.exp(-math.pi * ce / math.sqrt(1.0 - ce * ce))


def tm_damping_ratio(ce: float, ratio: float, damping: str = "force") -> float:
    """Parcel damping ratio c_e' for ratio l: c_e sqrt(l) (literal eq 24, `force`) or c_e (`restitution`)."""
    if damping not in DAMPING_MODES:
        raise ValueError(f"damping must be one of {DAMPING_MODES}, got {damping!r}")
    c = ce * math.sqrt(ratio) if damping == "force" else ce
    if c >= 1.0:
        raise ValueError(
            f"coarse_grain.ratio: with l = {ratio} the parcel contact is overdamped (c_e sqrt(l) = {c:.3f} >= 1); "
            "use a larger restitution, a smaller ratio, or damping='restitution'"
        )
    return c


def tm_contact_params(p: tuple, ratio: float, damping: str = "force") -> tuple:
    """Parcel contact-law parameters (LinearParams/HistoryParams) from the originals' `p`: k * l^2, c_e * sqrt(l)."""
    check_ratio(ratio)
    if ratio == 1.0:
        return p
    l2 = ratio * ratio
    f = p._asdict()
    f["stiffness"] = p.stiffness * l2
    f["ce"] = tm_damping_ratio(p.ce, ratio, damping)
    if "stiffness_t" in f:
        f["stiffness_t"] = p.stiffness_t * l2
        f["cet"] = tm_damping_ratio(p.cet, ratio, damping)
    return type(p)(**f)


def tm_dem_params(params, ratio: float, damping: str = "force"):
    """DEMParams of the parcels from those of the originals (seed 000 eqs 24-25); `params` itself when l = 1.

    k_n -> l^2 k_n, k_n,wall -> l^2 k_n,wall (k_t = ratio k_n follows), restitutions -> the e' of c_e sqrt(l).
    """
    check_ratio(ratio)
    if ratio == 1.0:
        return params
    kw = None if params.stiffness_wall is None else params.stiffness_wall * ratio * ratio
    e_pp = restitution_from_ratio(tm_damping_ratio(damping_ratio(params.restitution_pp), ratio, damping))
    e_pw = restitution_from_ratio(tm_damping_ratio(damping_ratio(params.restitution_pw), ratio, damping))
    kn = params.stiffness * ratio * ratio
    return dataclasses.replace(params, stiffness=kn, stiffness_wall=kw, restitution_pp=e_pp, restitution_pw=e_pw)


def tm_contact_time(kn: float, e: float, m_eff: float, ratio: float, damping: str = "force") -> float:
    """Analytic parcel contact time T_C' (s) = pi / sqrt(omega_0^2/l - gamma^2) for originals' kn (N/m), e, m_eff."""
    check_ratio(ratio)
    w0 = math.sqrt(kn / m_eff)
    if damping == "force":
        g = damping_ratio(e) * w0  # gamma is unchanged by the scaling
        return math.pi / math.sqrt(w0 * w0 / ratio - g * g)
    ce = damping_ratio(e)
    return math.pi * math.sqrt(ratio) / (w0 * math.sqrt(1.0 - ce * ce))


def tm_parcels(d_orig: float, ratio: float) -> tuple[float, int]:
    """Diameter (m) and n_orig of a parcel of l^3 originals of diameter d_orig (m): (l d_orig, l^3)."""
    n = check_ratio(ratio)
    if not d_orig > 0:
        raise ValueError(f"d_orig must be > 0, got {d_orig}")
    return (d_orig if ratio == 1.0 else ratio * d_orig), n


def parcel_count(n_orig_total: int, ratio: float) -> int:
    """Number of parcels (rounded to nearest, at least 1) that carry n_orig_total originals at ratio l."""
    n = check_ratio(ratio)
    return max(1, int(np.rint(n_orig_total / n)))


def use_group_contacts(dem, d_orig: float, rho: float) -> None:
    """Give `dem` per-pair TM contact scaling for groups of any sizes (PCPM; `febed.dem.contact.linear_groups`).

    The DEM's particle-particle and wall parameters (of the originals, law `linear`) become `GroupParams` with
    the original pair's effective mass m_O/2 (walls: m_O), m_O = rho pi d_orig^3 / 6. No kernel signature
    changes: the law reads each pair's ratio from the effective mass it already receives. The DEM step follows
    the same scaling (`febed.dem.integrate.critical_time`: the lightest pair present with its k_n l^2).
    """
    if not isinstance(dem.pp, LinearParams):
        raise ValueError("use_group_contacts: contact.model must be 'linear' (the history law is not scaled per pair)")
    if not (d_orig > 0 and rho > 0):
        raise ValueError(f"d_orig, rho: must be > 0, got {d_orig}, {rho}")
    m_o = rho * math.pi / 6.0 * d_orig**3
    dem.pp = GroupParams(dem.pp.stiffness, dem.pp.ce, dem.pp.friction, 0.5 * m_o)
    dem.pw = GroupParams(dem.pw.stiffness, dem.pw.ce, dem.pw.friction, m_o)
    dem.touch()
