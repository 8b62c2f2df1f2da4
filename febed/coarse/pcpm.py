r"""Dynamic coarse grain (PCPM): particle-groups that crush and merge, seed 000 sec 2.3.

A group is a count n of original particles (diameter d_O, material density ρ_p): diameter d_O n^{1/3}, mass
n m_O, `Particles.n_orig` = n; the drag is n times the drag on one original at the group's velocity
(`febed.coupling.drag`, the Coupler passes d_O = d / n^{1/3}). n is a whole number >= 1 by default. With
divisible originals (`min_group` = 2^-j < 1, seed 000 sec 4: PCPM at l = 1 "under the assumption that the
particles are divisible") a crush may also split an original, down to pieces of `min_group` of one (diameter
d_O min_group^{1/3}); every n is then a multiple of `min_group`, so sums of n stay exact in floating point. A
piece (n < 1) is a particle of its own: its drag is that of one sphere of its diameter
(`febed.coarse.setup.closure_sizes`), its contacts follow the same per-pair scaling as groups (k_n l², with l³
the pair's effective mass over an original pair's). `GroupDynamics.update` is called by the coupled loop once
per gas step:

1. d_cl per group (eqs 32-39, `equivalent_diameter`): eq 37 read as power per unit mass,
   E_st = F_drag · u / m (W/kg); E_cc of eq 38 from the current contacts (optional, `contact_power`);
   U_p = (1 - ε)|v|; U_mf from Wen–Yu unless given; ε_max = 0.9997. d_cl is "no crushing" (inf) unless both
   K > 0 and E_input > 0.
2. Crushing (eqs 40-43) then merging (eqs 44-46) in one pass over the groups (`group_events`).
3. The DEM's particles are changed only through `DEM.remove_particles` / `DEM.add_particles`.

Choices where the paper is silent (documented and tested):
* How often: once per call of `update`. The coupled loop calls it at the gas steps that cross a multiple of
  `event_interval` (`due`), by default a tenth of τ_mf = U_mf/g, the relaxation time of a group at minimum
  fluidization (see `GroupDynamics.__init__`), and `update` evaluates every `interval`-th of those calls.
* Crush sizes in whole units (an original, or `min_group` of one): n_new - 1 = floor(d²/d_cl²) children of
  k = max(1, floor((d_cl/d_u)³)) units of diameter d_u, the remainder n - (n_new - 1) k >= 1 unit in the last
  child (eqs 41-43); a single unit never crushes.
* Where children go: centres in the parent's sphere (disk in 2D): best of `tries` random draws per child
  (largest gap to the siblings placed), then the siblings are relaxed apart with their centres kept in the
  parent's sphere (until apart with `conserve_energy`, else to half the tolerance); after 4 failed attempts the
  crush is deferred if any child would overlap a sibling, another group or a wall by more than
  `overlap_tolerance` of the smaller diameter.
* Merging: touching groups (overlap > 0) meeting eq 44 (|v_i - v_j| < 0.01 max(|v_i|, |v_j|)), with
  n_i + n_j <= `max_group` and a merged diameter not above either group's d_cl (so a merge is never undone by the
  next crush test); the merged group sits at the centre of mass with the mass-weighted velocity (exact momentum,
  instead of eq 46's "v_i or v_j") and the spin of summed I ω; its centre is then pushed out of its overlaps
  with the other groups and the walls by at most half the smaller parent's radius (gravitational energy
  accounted); deferred if it would still overlap beyond the tolerance.
* Events in one pass never touch the same region (a later event intersecting an earlier one waits).
* MPI: each rank evaluates its own groups; the other ranks' groups near the partition (ghosts) are obstacles in
  the overlap checks and never take part in an event, so two groups on different ranks do not merge while they
  are on different ranks. A group within two largest radii of a ghost takes part in events only on its rank's
  turn (every `size`-th evaluation, by rank), so that two ranks never place groups in the same region in one
  evaluation; it waits at most `size` evaluations (counted as conflicts).
* Energy (`conserve_energy`, on by default): an event is accepted only if it does not increase the kinetic
  (translation + spin) + elastic contact + gravitational energy of the groups it removes and creates, their
  contacts included, with each spring's own group-scaled stiffness; otherwise it is deferred. A merge loses
  the pair's relative kinetic energy (eq 44 keeps it small) and some spin energy and frees the springs of both
  parents, which pay for the springs of the merged group; a crush keeps the translational kinetic energy, loses
  some spin energy, and its children's springs (with siblings, other groups, walls) must not exceed the
  parent's. Count and momentum stay exact. Events therefore only dissipate energy; each update reports the
  measured change of the whole bed's kinetic + elastic + gravitational energy (J, `EventStats.energy_injected`,
  probe column `event_energy`, cumulative).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from febed.coarse.pcpm_kernels import (
    NO_CRUSH,
    EventRules,
    Events,
    Groups,
    Springs,
    crush_sizes,
    equivalent_diameter,
    group_events,
)
from febed.dem.forces import contact_power
from febed.schema import MIN_GROUPS

__all__ = ["NO_CRUSH", "EventStats", "GroupDynamics", "crush_sizes", "equivalent_diameter", "u_mf_wen_yu"]


def u_mf_wen_yu(d: float, rho_p: float, rho_g: float, mu_g: float, g: float = 9.81) -> float:
    """Minimum fluidization velocity (m/s) of Wen & Yu: Re_mf = sqrt(33.7² + 0.0408 Ar) - 33.7."""
    if not (d > 0 and rho_p > rho_g > 0 and mu_g > 0 and g > 0):
        raise ValueError("u_mf_wen_yu: need d > 0, rho_p > rho_g > 0, mu_g > 0, g > 0")
    ar = rho_g * (rho_p - rho_g) * g * d**3 / mu_g**2
    re = math.sqrt(33.7**2 + 0.0408 * ar) - 33.7
    return re * mu_g / (rho_g * d)


@dataclass
class EventStats:
    """What one `GroupDynamics.update` did.

    Attributes:
        groups: particles (groups) after the update; originals: Σ n_orig (unchanged by events; fractional on a
            rank when the originals are divisible).
        crushed: groups crushed; children: groups they became; merged: merge events (2 groups -> 1).
        crush_deferred, merge_deferred: events refused for overlap (or capacity); conflicts: events that waited
            because an earlier event of the same update touched their region.
        energy_injected: change (J) of the whole bed's kinetic + elastic contact + gravitational energy caused by
            the events (0 if not measured).
        d_cl_min: smallest finite d_cl (m) seen (inf if none).
    """

    groups: int = 0
    originals: float = 0.0
    crushed: int = 0
    children: int = 0
    merged: int = 0
    crush_deferred: int = 0
    merge_deferred: int = 0
    conflicts: int = 0
    energy_injected: float = 0.0
    d_cl_min: float = math.inf

    def add(self, other: EventStats) -> None:
        """Accumulate the event counts and energy of `other` (groups/originals take other's values)."""
        for name in ("crushed", "children", "merged", "crush_deferred", "merge_deferred", "conflicts"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        self.energy_injected += other.energy_injected
        self.groups, self.originals = other.groups, other.originals
        self.d_cl_min = min(self.d_cl_min, other.d_cl_min)


class GroupDynamics:
    """Crushing and merging of particle-groups (seed 000 sec 2.3) driven by the local flow; see module docstring."""

    def __init__(self, d_orig: float, rho_p: float, rho_g: float, mu_g: float, eps_mf: float, gravity: float = 9.81,
                 u_mf: float | None = None, eps_max: float = 0.9997, max_group: int = 27, min_group: float = 1.0,
                 overlap_tolerance: float = 0.05, merge_tolerance: float = 0.01, crush: bool = True,
                 merge: bool = True, contact_power: bool = True, tries: int = 32, interval: int = 1,
                 event_interval: float | None = None, measure_energy: bool = True, conserve_energy: bool = True,
                 seed: int = 12345):  # fmt: skip
        """Set the original particle (d_orig m, rho_p kg/m^3), gas (rho_g, mu_g) and the model's parameters.

        min_group: smallest group a crush may make, in originals: 1 (originals are whole), or 1/2, 1/4, ... 1/64
            (divisible originals, seed 000 sec 4): an original crushes into pieces of whole multiples of it.

        event_interval: simulated time (s) between evaluations of the criteria in the coupled loop (`due`; 0:
            every gas step). None: 0.1 τ_mf with τ_mf = U_mf/g, the time a group takes to relax to the gas
            when its drag at the minimum-fluidization slip carries its weight (K U_mf = m g, so m/K = U_mf/g).
            A group of n originals has n times an original's drag and mass, so τ_mf is the same for every
            group size: it is the time on which a group's velocity, hence U_p, E_st and the merge test of
            eq 44, follows a change of the flow around it (ε and the gas velocity change no faster in a bubbling
            bed). Evaluating every tenth of it delays an event by at most 0.1 τ_mf, during which a group's
            velocity moves by at most about a tenth of the way to the new flow: the same margin as the coupled
            loop's drag updates (every 0.1 τ_p, `febed.solver`). The contact time scale would be the wrong one:
            contacts change E_cc within T_C, but events follow the state of a region, which lasts for τ_mf.
            For 1.5 mm, 1,150 kg/m^3 originals in air (seed 000), U_mf = 0.494 m/s: τ_mf = 50 ms, an evaluation
            every 5.0 ms (25 gas steps of 2e-4 s) instead of every gas step.
        """
        checks = {
            "d_orig": d_orig > 0, "rho_p": rho_p > rho_g > 0, "mu_g": mu_g > 0, "eps_mf": 0 < eps_mf < 1,
            "gravity": gravity > 0, "eps_max": eps_mf < eps_max < 1, "max_group": int(max_group) >= 1,
            "min_group": min_group in MIN_GROUPS,
            "overlap_tolerance": 0 <= overlap_tolerance < 1, "merge_tolerance": merge_tolerance >= 0,
            "tries": int(tries) >= 1, "interval": int(interval) >= 1,
            "u_mf": u_mf is None or u_mf > 0, "event_interval": event_interval is None or event_interval >= 0,
        }  # fmt: skip
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(
                f"GroupDynamics: invalid {bad[0]} (need d_orig > 0, rho_p > rho_g > 0, mu_g > 0, 0 < eps_mf < "
                "eps_max < 1, gravity > 0, max_group >= 1, min_group one of 1, 1/2, ..., 1/64, "
                "0 <= overlap_tolerance < 1, merge_tolerance >= 0, tries >= 1, interval >= 1, u_mf > 0 or None, "
                "event_interval >= 0 or None)"
            )
        self.d_orig = float(d_orig)
        self.rho_p, self.rho_g, self.mu_g = float(rho_p), float(rho_g), float(mu_g)
        self.g = float(gravity)
        self.eps_mf, self.eps_max = float(eps_mf), float(eps_max)
        self.u_mf = float(u_mf) if u_mf is not None else u_mf_wen_yu(d_orig, rho_p, rho_g, mu_g, gravity)
        self.max_group = int(max_group)
        self.min_group = float(min_group)
        self.tol = float(overlap_tolerance)
        self.merge_tol = float(merge_tolerance)
        self.crush, self.merge = bool(crush), bool(merge)
        self.use_contact_power = bool(contact_power)
        self.tries = int(tries)
        self.interval = int(interval)
        self.tau_mf = self.u_mf / self.g
        self.event_interval = 0.1 * self.tau_mf if event_interval is None else float(event_interval)
        self.measure_energy = bool(measure_energy)
        self.conserve_energy = bool(conserve_energy)
        self.rng = np.random.default_rng(seed)
        self.calls = 0
        self.evaluations = 0  # calls of `apply`: with MPI, whose turn it is at the partition
        self.total = EventStats()
        self._interval = EventStats()

    # ------------------------------------------------------------------ when
    def due(self, t0: float, t1: float) -> bool:
        """True if a gas step from t0 to t1 (s) crosses a multiple of `event_interval` (always if it is 0)."""
        if self.event_interval <= 0.0:
            return True
        return math.floor(t1 / self.event_interval) > math.floor(t0 / self.event_interval)

    @staticmethod
    def prepare(dem) -> bool:
        """Rebuild the DEM's pair lists if rows changed since the last build; True if rebuilt (collective with MPI).

        A rebuild may reorder (and with MPI migrate) the rows: call this before taking any per-row value that
        `update` or `equivalent_diameter` is given.
        """
        ex = getattr(dem, "exchange", None)
        dirty = bool(dem._dirty)
        if ex.any(dirty) if ex is not None else dirty:
            dem.rebuild()
            return True
        return False

    # ------------------------------------------------------------------ d_cl (eqs 32-39)
    def contact_power(self, dem) -> np.ndarray:
        """E_cc (W/kg) of the owned particles from their current contacts (seed 000 eq 38)."""
        self.prepare(dem)  # the pair list of the current rows (a no-op if `prepare` was called before)
        P = dem.particles
        n = P.n_owned
        out = np.zeros(n)
        if n == 0:
            return out
        contact_power(dem.bodies(), dem.lists(), dem.pp, out)
        return out

    def equivalent_diameter(self, dem, eps_at_p, u_at_p, f_drag, e_cc=None) -> np.ndarray:
        """d_cl (m) of each owned group from ε, gas velocity u (m/s) and drag F (N) at the particles (eqs 32-39)."""
        P = dem.particles
        n = P.n_owned
        eps = np.ascontiguousarray(eps_at_p, dtype=float)
        u = np.ascontiguousarray(u_at_p, dtype=float)
        f = np.ascontiguousarray(f_drag, dtype=float)
        for name, a, shape in (("eps_at_p", eps, (n,)), ("u_at_p", u, (n, 3)), ("f_drag", f, (n, 3))):
            if a.shape != shape:
                raise ValueError(f"{name}: must have shape {shape} (owned particles), got {a.shape}")
        if e_cc is None:
            e_cc = self.contact_power(dem) if self.use_contact_power else np.zeros(n)
        out = np.empty(n)
        equivalent_diameter(eps, u, np.ascontiguousarray(P.vel[:n]), f, np.ascontiguousarray(P.mass[:n]), e_cc,
                            self.d_orig, self.rho_p, self.rho_g, self.g, self.u_mf, self.eps_mf, self.eps_max,
                            out)  # fmt: skip
        return out

    # ------------------------------------------------------------------ events
    def apply(self, dem, d_cl: np.ndarray) -> EventStats:
        """Crush and merge the owned groups given their d_cl (m); changes the DEM's particles; returns the stats."""
        P = dem.particles
        n = P.n_owned
        d_cl = np.ascontiguousarray(d_cl, dtype=float)
        if d_cl.shape != (n,):
            raise ValueError(f"d_cl: must have shape ({n},), got {d_cl.shape}")
        stats = EventStats(d_cl_min=float(d_cl[np.isfinite(d_cl)].min()) if np.isfinite(d_cl).any() else math.inf)
        ex = getattr(dem, "exchange", None)
        if n == 0 and ex is None:
            return stats
        e0 = self._energy(dem) if self.measure_energy else 0.0  # (collective with MPI)
        n_all = n + P.n_ghost  # MPI: the other ranks' groups near the partition are obstacles, not events
        pos, diam = np.ascontiguousarray(P.pos[:n_all]), np.ascontiguousarray(P.diameter[:n_all])
        turn = ex is None or (self.evaluations % ex.comm.size) == ex.rank
        self.evaluations += 1
        if P.n_ghost:  # the ghost rows go (they are refreshed at the next step), the history is kept
            dem.save_history()
            P.n_ghost = 0
            dem.touch()
        cap = int(round(P.n_orig[:n].sum() / self.min_group)) + n  # at most one child per unit
        new_pos = np.empty((cap, 3))
        new_vel = np.empty((cap, 3))
        new_omega = np.empty((cap, 3))
        new_n = np.empty(cap)
        removed = np.zeros(n, dtype=bool)
        counts = np.zeros(6, dtype=np.int64)
        de = np.zeros(2)
        groups = Groups(
            pos, np.ascontiguousarray(P.vel[:n]), np.ascontiguousarray(P.omega[:n]), diam,
            np.ascontiguousarray(P.mass[:n_all]), np.ascontiguousarray(P.n_orig[:n]), n, n_all,
        )  # fmt: skip
        rules = EventRules(self.d_orig, self.min_group, dem.params.dim == 2, self.crush, self.merge, self.max_group,
                           self.merge_tol, self.tol, self.tries, self.conserve_energy)  # fmt: skip
        springs = Springs(*self._springs(dem.pp), *self._springs(dem.pw), np.asarray(dem.gvec, dtype=float))
        out = Events(removed, new_pos, new_vel, new_omega, new_n, counts, de)
        seed = int(self.rng.integers(0, 2**31 - 1))
        m = group_events(groups, d_cl, turn, seed, rules, dem.walls.geometry, springs, out)
        stats.crushed, stats.children, stats.merged = int(counts[0]), int(counts[1]), int(counts[2])
        stats.crush_deferred, stats.merge_deferred, stats.conflicts = int(counts[3]), int(counts[4]), int(counts[5])
        if m:
            dem.remove_particles(removed)
            nn = new_n[:m]
            dem.add_particles(new_pos[:m], self.d_orig * np.cbrt(nn), self.rho_p, vel=new_vel[:m],
                              omega=new_omega[:m], n_orig=nn)  # fmt: skip
        if self.measure_energy and (ex.any(m > 0) if ex is not None else m):
            stats.energy_injected = self._energy(dem) - e0  # (global with MPI: every rank reports the total)
        stats.groups = P.n_owned
        stats.originals = float(P.n_orig[: P.n_owned].sum())
        return stats

    def update(self, dem, eps_at_p, u_at_p, f_drag) -> EventStats:
        """Once per gas step: d_cl from the flow at the particles, then crush/merge (every `interval`-th call)."""
        self.calls += 1
        P = dem.particles
        if (self.calls - 1) % self.interval:
            return EventStats(groups=P.n_owned, originals=float(P.n_orig[: P.n_owned].sum()))
        stats = self.apply(dem, self.equivalent_diameter(dem, eps_at_p, u_at_p, f_drag))
        self.total.add(stats)
        self._interval.add(stats)
        return stats

    def interval_stats(self) -> EventStats:
        """Events accumulated since the previous call (per output interval, seed 000 Figs 8-9), then reset."""
        out = self._interval
        self._interval = EventStats(groups=out.groups, originals=out.originals)
        return out

    def state_dict(self) -> dict:
        """Restartable state (random generator, call count, totals) as plain Python values for a checkpoint."""
        return {"rng": self.rng.bit_generator.state, "calls": self.calls, "evaluations": self.evaluations,
                "total": vars(self.total).copy(),
                "interval": vars(self._interval).copy()}  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        """Restore the state saved by `state_dict` (the group sizes themselves live in `Particles.n_orig`)."""
        self.rng.bit_generator.state = state["rng"]
        self.calls = int(state["calls"])
        self.evaluations = int(state.get("evaluations", 0))
        self.total = EventStats(**state["total"])
        self._interval = EventStats(**state["interval"])

    @staticmethod
    def _energy(dem) -> float:
        """Kinetic + elastic contact + gravitational energy (J) of the whole bed (collective with MPI)."""
        return dem.kinetic_energy() + dem.elastic_energy() + dem.potential_energy()

    @staticmethod
    def _springs(params) -> tuple[float, float]:
        """(k_n, m_ref) of a contact law's parameters: m_ref > 0 for per-pair group scaling, 0 for a fixed k_n."""
        return float(params.stiffness), float(getattr(params, "m_ref", 0.0))

    def crush_sizes(self, n: float, d: float, d_cl: float) -> tuple[float, int, float]:
        """(originals per full child, number of full children, originals in the remainder) of a crush (eqs 40-42)."""
        u = self.min_group
        k, n_full, rem = crush_sizes(int(round(n / u)), float(d), float(d_cl), self.d_orig * u ** (1.0 / 3.0))
        return k * u, n_full, rem * u
