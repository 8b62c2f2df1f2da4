"""What a case's `[coarse_grain]` section does to the particles, the contact law and the coupled loop.

`[particles]` always describes the *original* particles (diameter, density, count or bed mass). Then:

* `none`: the originals (n_orig = 1), contacts as given.
* `tm`: round(N / l³) parcels of diameter l d and n_orig = l³; contact k_n -> l² k_n and the dashpot of
  `tm_damping` (`febed.coarse.tm`).
* `scg`: round(N / l³) particles of diameter l d and density ρ d² / (l d)² (seed 003 eq 7), n_orig = 1;
  contacts as given.
* `pcpm`: groups of l³ originals to start with (as `tm`); contacts scaled per pair by the two groups' sizes
  (`linear_groups`); groups crush and merge every `event_interval` of simulated time (`GroupDynamics`), down to
  `min_group` originals (below 1: divisible originals).

The drag of a particle of n_orig >= 1 originals is n_orig times that of one original of d / n_orig^(1/3) at its
velocity, a piece of an original (n_orig < 1) has its own sphere's drag (the coupling does this for every
model, `closure_sizes`). A packed bed file holds the particles as inserted, so a
coarse-grained case needs its own `bed_file`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from febed.coarse.scg import scg_count, scg_particles
from febed.schema import MIN_GROUPS


@dataclass
class ParcelSpec:
    """The particles to insert: diameter (m), material density (kg/m^3), number and originals each."""

    diameter: float
    density: float
    count: int
    n_orig: int


def check_case(case) -> list[str]:
    """Problems of a case's `[coarse_grain]` section (for `febed check` and the case loader)."""
    cg = case.coarse_grain
    problems = []
    n = round(cg.ratio**3)
    if cg.model in ("tm", "pcpm") and abs(cg.ratio**3 - n) > 1e-9 * n:  # as febed.coarse.tm.check_ratio
        problems.append(
            f"[coarse_grain] ratio = {cg.ratio}: a parcel stands for l^3 whole originals, l^3 = {cg.ratio**3:.6g}; "
            "use l = k^(1/3) for an integer k (1, 2, 3, ...)"
        )
    if cg.model == "pcpm" and case.contact.model != "linear":
        problems.append(
            f"[coarse_grain] model = 'pcpm' scales each contact by its groups' sizes with the 'linear' law: set "
            f"[contact] model = 'linear' (got {case.contact.model!r})"
        )
    if cg.model == "pcpm" and cg.min_group not in MIN_GROUPS:
        problems.append(
            f"[coarse_grain] min_group = {cg.min_group}: the smallest group is 1 original or a power-of-two "
            f"fraction of one: one of {', '.join(f'{x:g}' for x in MIN_GROUPS)}"
        )
    if cg.model == "pcpm" and cg.eps_max <= cg.eps_mf:
        problems.append(f"[coarse_grain] eps_max = {cg.eps_max} must exceed eps_mf = {cg.eps_mf}")
    return problems


def parcels(case, count_orig: int, dim: int = 3) -> ParcelSpec:
    """The particles standing for `count_orig` originals under the case's coarse-grain model.

    In 2D (`dim` = 2) TM and PCPM insert round(N / l²) parcels: the bed is a layer one particle thick (the
    depth, `particle_depth`), so N / l² parcels of l d cover the same area as N originals and the layer,
    l times thicker, keeps the bed's height, solid fraction and weight per unit area.
    """
    p, cg = case.particles, case.coarse_grain
    if cg.model in ("tm", "pcpm"):
        from febed.coarse.tm import parcel_count, tm_parcels

        d, n = tm_parcels(p.diameter, cg.ratio)
        count = parcel_count(count_orig, cg.ratio) if dim == 3 else max(1, round(count_orig / cg.ratio**2))
        return ParcelSpec(d, p.density, count, n)
    if cg.model == "scg":
        d, rho = scg_particles(p.diameter, p.density, cg.ratio)
        return ParcelSpec(d, rho, scg_count(count_orig, cg.ratio), 1)
    return ParcelSpec(p.diameter, p.density, count_orig, 1)


def closure_sizes(diameter: np.ndarray, n_orig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(d_orig, count) of particles of `diameter` (m) standing for `n_orig` originals each, for the closures.

    A group of n >= 1 originals: n times one original of diameter d / n^{1/3}. A piece of an original (n < 1,
    PCPM with divisible originals) is a particle of its own: once the drag of a sphere of its own diameter d.
    The solid volume count π d_orig³ / 6 is n π d_O³ / 6 either way. Views of the inputs when no particle
    stands for other than one whole original.
    """
    if n_orig.size == 0 or (n_orig.min() == 1.0 and n_orig.max() == 1.0):
        return diameter, n_orig
    count = np.maximum(n_orig, 1.0)
    return diameter / np.cbrt(count), count


def particle_depth(case) -> float:
    """2D depth (m) turning areas into volumes: `[mesh] depth`, or one inserted particle's diameter."""
    if case.mesh.depth > 0:
        return case.mesh.depth
    cg = case.coarse_grain
    return case.particles.diameter * (cg.ratio if cg.model != "none" else 1.0)


def dem_params(case, params):
    """DEM parameters of the inserted particles: the TM parcel law for `tm`, unchanged otherwise."""
    cg = case.coarse_grain
    if cg.model == "tm":
        from febed.coarse.tm import tm_dem_params

        return tm_dem_params(params, cg.ratio, cg.tm_damping)
    return params


def configure_dem(case, dem) -> None:
    """Per-pair group contact scaling for `pcpm` (after the DEM is built); nothing for the other models."""
    if case.coarse_grain.model == "pcpm":
        from febed.coarse.tm import use_group_contacts

        use_group_contacts(dem, case.particles.diameter, case.particles.density)


def group_dynamics(case):
    """The `GroupDynamics` of a `pcpm` case (crush and merge every `event_interval`), else None."""
    cg = case.coarse_grain
    if cg.model != "pcpm":
        return None
    from febed.coarse.pcpm import GroupDynamics

    return GroupDynamics(
        case.particles.diameter, case.particles.density, case.gas.density, case.gas.viscosity, cg.eps_mf,
        gravity=case.run.gravity, u_mf=cg.u_mf if cg.u_mf > 0 else None, eps_max=cg.eps_max,
        max_group=cg.max_group, min_group=cg.min_group, overlap_tolerance=cg.overlap_tolerance,
        merge_tolerance=cg.merge_tolerance,
        contact_power=cg.contact_power, tries=cg.placement_tries, interval=cg.interval,
        event_interval=cg.event_interval if cg.event_interval > 0 else None, seed=case.run.seed,
    )  # fmt: skip
