"""The DEM: particles + walls + contact law + integrator, advanced by `DEM.advance(n_steps, dt, f_ext)`.

This is the one entry point the pure-DEM driver and the coupled loop call. Row order of the particle
arrays may change inside `advance` (particles are sorted by linked cell for memory locality when the pair
list is rebuilt): identify particles by `particles.gid`, and pass `f_ext` in the current row order.

With MPI, `attach_exchange` gives the DEM a `febed.parallel.ParticleExchange`, its only contact with ranks:
`advance` then steps stage by stage (ghost rows refreshed before every force evaluation, the rebuild
decision taken over all ranks, particles migrating at rebuilds with their history and auxiliary arrays),
and every call that changes or reads the global state (advance, rebuild, dt, the energies) is collective.
Without an exchange the serial loop runs unchanged, compiled over many steps.

A run that must stay responsive to stop signals sets `DEM.stop_check`: a long `advance` then asks it
between chunks of STOP_CHECK_WORK particle steps (a fraction of a second of compiled stepping, however
small the step) and stops at a whole step if it says so (`StopRequested`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from febed.dem.contact import ContactLaw, get_law, stiffness_from_material
from febed.dem.forces import compute_forces
from febed.dem.integrate import (
    critical_time,
    get_integrator,
)
from febed.dem.neighbours import (
    PairList,
    carry_wall_history,
    cell_index,
    farthest_move,
    grid_of,
    restore_wall_history,
    wall_keys,
)
from febed.dem.particles import Particles
from febed.dem.records import Bodies, Lists, Model, Scratch
from febed.dem.walls import Walls, build_wall_pairs, wall_overlap_squares
from febed.schema import check_fields, schema_field

BLOW_UP_JUMP = 1000.0  # a jump in one step beyond this many times the cloud's size is a blow-up (`DEM._blow_up`)
STOP_CHECK_WORK = 1_000_000  # particle steps between two questions to `DEM.stop_check` (a fraction of a second)


class DEMFailure(RuntimeError):
    """The particles blew up: a position is no longer finite, or a particle jumped absurdly far in one step.

    Found when the pair list is rebuilt (`DEM._blow_up`), agreed over the ranks: raised on every rank.
    """


class StopRequested(Exception):
    """`DEM.stop_check` asked `advance` to stop early (a stop signal reached the run).

    The particles are at the end of a whole step and `time` and `steps` count the steps made; the rest of the
    steps asked for were not made. Raised on every rank (the ranks agree through `stop_check`).
    """


@dataclass
class DEMParams:
    """Plain DEM parameters (SI units); `DEM.from_case` fills them from a case.

    Each field but `NOT_IN_CASE`'s is a case key of the same name (`contact.stiffness` -> `stiffness`;
    `contact_model` is `contact.model`): its default and allowed range are that key's in `febed/schema.py`.

    Attributes:
        dim: 3, or 2 for spheres moving in the x-y plane (gravity along -y).
        contact_model: registered contact law ("linear", "linear-history").
        stiffness: normal stiffness k_n (N/m) of particle-particle contacts; stiffness_wall for walls (None: the
            same as stiffness).
        tangential_ratio: k_t / k_n (linear-history).
        restitution_pp, restitution_pw: normal restitution e_p, e_w.
        friction_pp, friction_pw: Coulomb friction mu_p, mu_w.
        integrator: registered integrator ("rk2", "verlet").
        dt_factor: default step = T_C / dt_factor (seed 001 eq 42).
        skin: pair-list skin as a fraction of the largest diameter.
        gravity: magnitude (m/s^2), along -z (3D) or -y (2D).
        rotation: integrate angular velocities.
        sort: reorder particles by linked cell (memory locality) ...
        sort_every: ... at every sort_every-th pair-list rebuild (and whenever rows change anyway).
    """

    # fields that are no case key, and why
    NOT_IN_CASE: ClassVar[dict[str, str]] = {
        "dim": "the mesh's dimension",
        "sort": "a memory-layout setting of the Python API",
        "sort_every": "a memory-layout setting of the Python API",
    }

    dim: int = 3
    contact_model: str = schema_field("contact.model")
    stiffness: float = schema_field("contact.stiffness")
    stiffness_wall: float | None = schema_field("contact.stiffness_wall")
    tangential_ratio: float = schema_field("contact.tangential_ratio")
    restitution_pp: float = schema_field("contact.restitution_pp")
    restitution_pw: float = schema_field("contact.restitution_pw")
    friction_pp: float = schema_field("contact.friction_pp")
    friction_pw: float = schema_field("contact.friction_pw")
    integrator: str = schema_field("contact.integrator")
    dt_factor: float = schema_field("contact.dt_factor")
    skin: float = schema_field("contact.skin")
    gravity: float = schema_field("run.gravity")
    rotation: bool = schema_field("particles.rotation")
    sort: bool = True
    sort_every: int = 20

    def validate(self) -> None:
        """Raise ValueError naming the first parameter out of range (the ranges of `febed/schema.py`)."""
        if self.dim not in (2, 3):
            raise ValueError(f"DEMParams.dim must be 2 or 3, got {self.dim!r}")
        check_fields(self)
        if not isinstance(self.sort, bool):
            raise ValueError(f"DEMParams.sort must be true or false, got {self.sort!r}")
        if isinstance(self.sort_every, bool) or not isinstance(self.sort_every, int) or self.sort_every < 1:
            raise ValueError(f"DEMParams.sort_every must be an integer >= 1, got {self.sort_every!r}")


class DEM:
    """Soft-sphere DEM of one process's particles (seed 001 sec 2.2, 2.4.2)."""

    def __init__(self, params: DEMParams | None = None, particles: Particles | None = None, walls: Walls | None = None):
        """Set up the law, integrator, walls and pair list; particles can be added later."""
        self.params = p = params or DEMParams()
        p.validate()
        self.law: ContactLaw = get_law(p.contact_model)
        self.integrator = get_integrator(p.integrator)
        kw = p.stiffness if p.stiffness_wall is None else p.stiffness_wall
        self.pp = self.law.params(p.stiffness, p.restitution_pp, p.friction_pp, p.tangential_ratio * p.stiffness)
        self.pw = self.law.params(kw, p.restitution_pw, p.friction_pw, p.tangential_ratio * kw)
        self.particles = particles if particles is not None else Particles()
        self.walls = walls if walls is not None else Walls()
        self.gvec = np.zeros(3)
        self.gvec[1 if p.dim == 2 else 2] = -p.gravity
        self.pairs = PairList(skin=1e-12)
        self.wstart = np.zeros(1, dtype=np.int64)
        self.wid = np.zeros(64, dtype=np.int64)
        self.whist = np.zeros((64, 3))
        self.time = 0.0
        self.steps = 0
        self.max_overlap = 0.0  # largest overlap / smaller diameter of the pair seen since the last reset
        self._dirty = True
        self._forces_valid = False
        self.layout = 0  # changes whenever the rows may have moved, been reordered, added or removed
        self._dt = None
        self.exchange = None  # febed.parallel.ParticleExchange when running on several ranks
        self._saved = None  # contact history keyed by gid pairs, carried over a change of rows
        self._lists_valid = False  # pair and wall lists index the current rows
        self._since_sort = 0
        self.pos_ref = np.zeros((0, 3))
        # `stop_check() -> bool`, asked every STOP_CHECK_WORK particle steps within a long `advance` (collective
        # with MPI: it must give every rank the same answer); True stops the advance (StopRequested)
        self.stop_check = None

    # ------------------------------------------------------------------ construction from a case
    @classmethod
    def from_case(cls, case, walls: Walls | None = None, dim: int = 3, particles: Particles | None = None) -> DEM:
        """A DEM with the parameters of `case` ([contact], [particles], [run]) and the given walls."""
        c = case.contact
        stiffness = c.stiffness
        kt_ratio = c.tangential_ratio
        if c.from_material:
            d = case.particles.diameter
            stiffness, kt = stiffness_from_material(c.young_modulus, c.poisson, 0.5 * d, c.reference_overlap * d)
            kt_ratio = kt / stiffness
        params = DEMParams(
            dim=dim,
            contact_model=c.model,
            stiffness=stiffness,
            stiffness_wall=c.stiffness_wall,
            tangential_ratio=kt_ratio,
            restitution_pp=c.restitution_pp,
            restitution_pw=c.restitution_pw,
            friction_pp=c.friction_pp,
            friction_pw=c.friction_pw,
            integrator=c.integrator,
            dt_factor=c.dt_factor,
            skin=c.skin,
            gravity=case.run.gravity,
            rotation=case.particles.rotation,
        )
        return cls(params, particles=particles, walls=walls)

    # ------------------------------------------------------------------ particles
    def add_particles(self, pos, diameter, density, vel=None, omega=None, n_orig=1) -> np.ndarray:
        """Insert spheres (m, kg/m^3, m/s) and return their gids; the pair list is rebuilt on the next step."""
        self.save_history()
        gids = self.particles.add(pos, diameter, density, vel=vel, omega=omega, n_orig=n_orig)
        self.touch()
        self._dt = None
        return gids

    def remove_particles(self, which) -> None:
        """Remove particles by boolean mask or row indices; their contact history is dropped."""
        self.save_history()
        self.particles.remove(which)
        self.touch()
        self._dt = None

    def touch(self) -> None:
        """Declare that positions/velocities were changed from outside: rebuild and recompute forces."""
        self._dirty = True
        self._forces_valid = False
        self.layout += 1

    # ------------------------------------------------------------------ time step
    def critical_time(self) -> float:
        """Contact time T_C (s) of the stiffest, lightest pair type present (seed 001 eq 19; collective with MPI)."""
        P = self.particles
        m, d = P.mass[: P.n_owned], P.diameter[: P.n_owned]
        if self.exchange is not None:
            two = np.argsort(m)[:2]
            m, d = self.exchange.concat(m[two]), self.exchange.concat(d[two])
        return critical_time(self.law, self.pp, self.pw, m, d, self.params.rotation, self.walls.count > 0)

    # ------------------------------------------------------------------ MPI
    def attach_exchange(self, exchange, distribute: bool = False) -> None:
        """Run on several ranks through `exchange` (a `febed.parallel.ParticleExchange`; collective).

        distribute: every rank holds the same particles now; keep only this rank's share (ignored when the DEM
            already runs distributed: its particles then migrate to their owners at the next step).
        """
        distribute = distribute and self.exchange is None
        self.save_history()
        self.exchange = exchange
        if distribute:
            exchange.distribute(self.particles)  # the gid-keyed history (e.g. of set_state) stays valid
        else:
            exchange.set_next_gid(self.particles)
        self.touch()
        self._dt = None

    def global_max(self, x: float) -> float:
        """Maximum of x over the ranks (x itself without MPI; collective)."""
        return self.exchange.max(x) if self.exchange is not None else x

    def global_sum(self, x: float) -> float:
        """Sum of x over the ranks (x itself without MPI; collective)."""
        return self.exchange.sum(x) if self.exchange is not None else x

    @property
    def dt(self) -> float:
        """Default DEM step T_C / dt_factor (s, seed 001 eq 42; collective with MPI)."""
        stale = self._dt is None
        if self.exchange is not None:
            stale = self.exchange.any(stale)  # particles added/removed on some rank only
        if stale:
            self._dt = self.critical_time() / self.params.dt_factor
        return self._dt

    # ------------------------------------------------------------------ neighbour lists
    def _dmax(self) -> float:
        P = self.particles
        d = float(P.diameter[: P.n_owned].max()) if P.n_owned else 0.0
        return self.global_max(d)

    def _skin(self) -> float:
        d = self._dmax()
        return self.params.skin * d if d > 0 else 1e-12

    def rebuild(self) -> None:
        """Rebuild the pair and wall lists, keeping the contact history.

        Every `sort_every` builds (or when rows changed anyway) the particles are first sorted by linked cell
        for memory locality; otherwise the history is merged row by row (no key search).
        """
        self.layout += 1  # rows may be reordered (and with MPI migrated)
        if self.exchange is not None:
            self._rebuild_parallel()
            return
        problem = self._blow_up()
        if problem:
            raise DEMFailure(problem)
        P = self.particles
        n = P.n
        p = self.params
        sort = p.sort and P.n_ghost == 0 and P.n_owned > 1 and np.all(np.isfinite(P.pos))
        sort = sort and (self._since_sort + 1 >= p.sort_every or not self._lists_valid)
        same_rows = self._lists_valid and self._saved is None and not sort and self.pairs.n == n
        saved = wsaved = None
        if not same_rows:
            self.save_history()
            saved, wsaved = self._saved if self._saved is not None else (None, None)
        self._saved = None
        skin = self._skin()
        if sort:
            lo, size, dims = grid_of(P.pos, n, 2.0 * skin / p.skin)
            perm = np.argsort(cell_index(P.pos, n, lo, size, dims), kind="stable")
            P.reorder(perm)  # auxiliary arrays (the external force) follow
            self._since_sort = 0
        else:
            self._since_sort += 1
        self.pairs.skin = skin
        self.pairs.build(P.pos, 0.5 * P.diameter, P.gid, saved, same_rows=same_rows)
        old = (self.wstart, self.wid, self.whist)
        self._build_walls(skin)
        if same_rows:
            carry_wall_history(old[0], old[1], old[2], self.wstart, self.wid, self.whist, n)
        elif wsaved is not None:
            restore_wall_history(self.wstart, self.wid, P.gid, n, wsaved[0], wsaved[1], self.whist)
        else:
            self.whist[:] = 0.0
        if self.pos_ref.shape == P.pos.shape:
            self.pos_ref[:] = P.pos
        else:
            self.pos_ref = P.pos.copy()
        self._dirty = False
        self._lists_valid = True

    def _rebuild_parallel(self) -> None:
        """Collective rebuild: migrate (with history), sort the owned rows, refresh the ghosts, build the lists."""
        P = self.particles
        p = self.params
        ex = self.exchange
        problem = self._blow_up()
        if ex.any(problem is not None):
            found = [m for m in ex.comm.allgather(problem) if m]
            raise DEMFailure(found[0] + (f" (and on {len(found) - 1} other rank(s))" if len(found) > 1 else ""))
        listed = self._lists_valid and self.pairs.n == P.n  # the last lists index the current rows
        work = 1.0 + 0.5 * self.pairs.pair_counts(P.n_owned) if listed and ex.balances_work else None
        self.save_history()
        saved, wsaved = self._saved if self._saved is not None else (None, None)
        self._saved = None
        saved, wsaved = ex.migrate(P, saved, wsaved, work=work)
        dmax = self._dmax()
        skin = p.skin * dmax if dmax > 0 else 1e-12
        n = P.n_owned
        due = self._since_sort + 1 >= p.sort_every or self.pairs.builds == 0
        if p.sort and n > 1 and due and np.all(np.isfinite(P.pos)):
            lo, size, dims = grid_of(P.pos, n, 2.0 * dmax)
            P.reorder(np.argsort(cell_index(P.pos, n, lo, size, dims), kind="stable"))
            self._since_sort = 0
        else:
            self._since_sort += 1
        ex.refresh_ghosts(P, dmax + skin)
        n = P.n
        self.pairs.skin = skin
        self.pairs.build(P.pos, 0.5 * P.diameter, P.gid, saved, same_rows=False)
        self._build_walls(skin)
        if wsaved is not None:
            restore_wall_history(self.wstart, self.wid, P.gid, n, wsaved[0], wsaved[1], self.whist)
        else:
            self.whist[:] = 0.0
        self.pos_ref = P.pos.copy()
        self._dirty = False
        self._lists_valid = True

    def _blow_up(self) -> str | None:
        """What went wrong if an owned particle's position is not finite or it jumped absurdly far (else None).

        Called at a rebuild, before the rows change; the jump is measured since the last build. A rebuild not
        asked for from outside (`touch`) comes when a particle moved more than half the skin since the last
        build, and it was within half the skin one step earlier. "Absurdly far" is BLOW_UP_JUMP times the larger
        of the largest diameter and the spread of the particles at that build: a speed no drag or contact force
        produces (a lone particle may cross several diameters per step in free flight), which would only make
        the linked-cell grid of the next pair search explode. Smaller excesses show as overlaps or escaped
        particles (`CoupledSolver.check`).
        """
        P = self.particles
        n = P.n_owned
        if self._dirty or not self._lists_valid or n == 0 or self.pos_ref.shape[0] < n:
            return None
        row, dist, spread = farthest_move(P.pos, self.pos_ref, n)
        scale = max(float(P.diameter[:n].max()), spread)
        if dist <= 0.5 * self.pairs.skin + BLOW_UP_JUMP * scale:
            return None
        where = f"particle {int(P.gid[row])} at {np.array2string(P.pos[row], precision=4)} m"
        when = f"during the DEM steps from t = {self.time:.6g} s"
        if not np.all(np.isfinite(P.pos[row])):
            return f"{where} has a non-finite position {when}"
        return (
            f"{where} moved {f'{dist:.3g} m' if np.isfinite(dist) else 'beyond 1e154 m'} since the last pair-list "
            f"build {when}, more than {BLOW_UP_JUMP:g} times the size of the particle cloud ({scale:.3g} m) in one "
            f"step (velocity {np.array2string(P.vel[row], precision=3)} m/s): a force far too large for the DEM "
            "step (check contact.stiffness and contact.dt_factor) or a gas field that blew up"
        )

    def save_history(self) -> None:
        """Key the contact history by gid pairs now; call before changing particle rows from outside."""
        P = self.particles
        if self._saved is not None or not self._lists_valid or self.pairs.n != P.n:
            return
        self._saved = self._history_keys()
        self._lists_valid = False

    def _history_keys(self):
        """Pair and wall history keyed by gids, of the contacts of owned particles (ghost pairs are not integrated)."""
        P = self.particles
        saved = self.pairs.saved_history(P.gid, P.n_owned)
        keys, vals = wall_keys(self.wstart, self.wid, P.gid, P.n_owned, self.whist)
        order = np.argsort(keys)
        return saved, (keys[order], vals[order])

    def _build_walls(self, skin: float) -> None:
        """New particle-wall candidate lists (fresh arrays: the old ones may still be needed for the history)."""
        P = self.particles
        W = self.walls
        n = P.n
        rmax = 0.5 * float(P.diameter.max()) if n else 0.0
        W.prepare(rmax + skin)
        self.wstart = np.zeros(n + 1, dtype=np.int64)
        args = (P.pos, 0.5 * P.diameter, n, skin, W.geometry, W.grid, self.wstart)
        wid = np.zeros(max(64, self.wid.size), dtype=np.int64)
        need = build_wall_pairs(*args, wid)
        if need > wid.size:
            wid = np.zeros(int(need * 1.25) + 16, dtype=np.int64)
            need = build_wall_pairs(*args, wid)
        self.wid = wid
        self.whist = np.zeros((wid.size, 3))

    # ------------------------------------------------------------------ stepping

    def compute_forces(self, dt_eval: float = 0.0, dt_store: float = 0.0) -> float:
        """Evaluate force and torque of every particle now (history kept); returns the largest relative overlap.

        Collective with MPI (a rebuild if any rank's rows changed); the ghost rows must be current.
        """
        if self.exchange.any(self._dirty) if self.exchange is not None else self._dirty:
            self.rebuild()
        b, lists = self.bodies(), self.lists()
        w = compute_forces(b, b.vel, b.omega, lists, lists.hist, lists.whist, self.walls.geometry, self.model(),
                           dt_eval, dt_store)  # fmt: skip
        self._forces_valid = True
        return w

    def advance(self, n_steps: int, dt: float | None = None, f_ext: np.ndarray | None = None) -> None:
        """Advance n_steps steps of dt (s; default T_C/dt_factor) with external forces f_ext (N, (n_owned, 3))."""
        if n_steps < 0:
            raise ValueError(f"n_steps must be >= 0, got {n_steps}")
        P = self.particles
        dt = self.dt if dt is None else float(dt)
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        if f_ext is not None:
            f_ext = np.asarray(f_ext, dtype=float)
            if f_ext.shape != (P.n_owned, 3):
                raise ValueError(f"f_ext must have shape ({P.n_owned}, 3), got {f_ext.shape}")
        self.layout += n_steps > 0
        if self.exchange is not None:
            self._advance_parallel(n_steps, dt, f_ext)
            return
        if P.n_owned == 0:
            self.time += n_steps * dt
            self.steps += n_steps
            return
        fext = P.attach("_fext", 3)  # an auxiliary array: it follows the rows when they are sorted
        fext[:] = 0.0
        if f_ext is not None:
            fext[: P.n_owned] = f_ext
        if self._dirty:
            self.rebuild()
        if self.integrator.needs_initial_forces and not self._forces_valid:
            self.compute_forces()
        every = self._stop_every()
        done = since = 0
        resume = False
        while done < n_steps:
            k, worst, code = self._run(min(n_steps - done, max(1, every - since)), dt, resume)
            done += k
            since += k
            self.max_overlap = max(self.max_overlap, worst)
            if code:
                self.rebuild()
            resume = code == 2  # the next step's drift is made: only a whole step may end the call
            if since >= every and not resume and done < n_steps:
                since = 0
                self._ask_stop(done, dt)
        self._forces_valid = True
        self.time += n_steps * dt
        self.steps += n_steps

    def _stop_every(self) -> int:
        """Steps between two questions to `stop_check` (collective with MPI); never asked without one."""
        if self.stop_check is None:
            return 1 << 62
        ex = self.exchange
        n = self.count() // ex.comm.size if ex is not None else self.particles.n_owned  # a rank's share of the work
        return max(1, STOP_CHECK_WORK // max(n, 1))

    def _ask_stop(self, done: int, dt: float) -> None:
        """Raise StopRequested after `done` steps of dt if `stop_check` says so (collective with MPI)."""
        if not self.stop_check():
            return
        self._forces_valid = True
        self.time += done * dt
        self.steps += done
        raise StopRequested(f"stopped after {done} DEM steps, at t = {self.time:.6g} s")

    def _run(self, n_steps: int, dt: float, resume: bool):
        b, lists, walls, model, s = self.kernel_args()
        return self.integrator.steps(
            n_steps, dt, b, lists, walls, model, self.pos_ref, 0.5 * self.pairs.skin, resume, s
        )

    def _advance_parallel(self, n_steps: int, dt: float, f_ext) -> None:
        """`advance` with ghosts: the same kernels as the serial loop, split at each force evaluation (collective)."""
        ex = self.exchange
        P = self.particles
        fext = P.attach("_fext", 3)
        fext[:] = 0.0
        if f_ext is not None:
            fext[: P.n_owned] = f_ext
        if ex.any(self._dirty):
            self.rebuild()
        if n_steps == 0:
            return
        verlet = self.integrator.name == "verlet"
        if verlet and ex.any(not self._forces_valid):
            ex.update_ghosts(P, P.vel, P.omega, spin=self.params.rotation)
            self.compute_forces()
        every = self._stop_every()
        done = 0
        while done < n_steps:
            k = min(every, n_steps - done)
            worst = self.integrator.staged(self, k, dt)
            self.max_overlap = max(self.max_overlap, worst)
            done += k
            if done < n_steps:
                self._ask_stop(done, dt)
        self._forces_valid = True
        self.time += n_steps * dt
        self.steps += n_steps

    def bodies(self) -> Bodies:
        """The current rows as the kernels take them (`febed.dem.records.Bodies`; refetch after a rebuild)."""
        P = self.particles
        return Bodies(P.pos, P.vel, P.omega, P.force, P.torque, P.attach("_fext", 3), P.diameter, P.mass, P.inertia,
                      P.n_owned, P.n)  # fmt: skip

    def lists(self) -> Lists:
        """The pair and wall lists of the current rows with their histories (`febed.dem.records.Lists`)."""
        pl = self.pairs
        return Lists(pl.start, pl.nbr, pl.hist, self.wstart, self.wid, self.whist)

    def model(self) -> Model:
        """The contact laws, rotation, gravity and 2D flag (`febed.dem.records.Model`)."""
        p = self.params
        return Model(self.pp, self.pw, bool(p.rotation), self.gvec, p.dim == 2)

    def kernel_args(self) -> tuple[Bodies, Lists, object, Model, Scratch]:
        """(bodies, lists, wall geometry, model, scratch) for the current rows (refetch after a rebuild)."""
        lists = self.lists()
        s = getattr(self, "_scratch", None)
        n, pairs, wall_pairs = self.particles.n, lists.hist.shape[0], lists.whist.shape[0]
        if s is None or not s.fits(n, pairs, wall_pairs):
            s = self._scratch = Scratch.sized(n, pairs, wall_pairs)
        return self.bodies(), lists, self.walls.geometry, self.model(), s

    # ------------------------------------------------------------------ checkpoint
    def get_state(self) -> dict:
        """The whole stepping state as plain numpy arrays / ints / floats (for np.savez checkpoints).

        Owned particle rows (all fields, forces included for Verlet), pair and wall lists with their contact
        history, the list reference positions, sort counters, step size, time, steps, max overlap and the number
        of walls. A new DEM with the same parameters and walls continues bit for bit after `set_state`; with
        other walls it rebuilds its wall lists and restarts the wall history. Ghost rows are not
        saved (the parallel layer rebuilds them).
        """
        P = self.particles
        s = {f"p_{k}": v for k, v in P.to_dict().items()}
        for name in P.aux_names:
            if not name.startswith("_"):
                s[f"aux_{name}"] = P.aux(name)[: P.n_owned].copy()
        s["p_next_gid"] = int(P.next_gid)
        keep_lists = self._lists_valid and self.pairs.n == P.n and self.exchange is None
        s["lists_valid"] = int(keep_lists)
        if keep_lists:
            pl = self.pairs
            m = pl.size
            s["pl_start"] = pl.start[: pl.n + 1].copy()
            s["pl_nbr"] = pl.nbr[: max(m, 1)].copy()
            s["pl_hist"] = pl.hist[: max(m, 1)].copy()
            s["w_start"] = self.wstart.copy()
            s["w_id"] = self.wid.copy()
            s["w_hist"] = self.whist.copy()
        s["pl_builds"] = int(self.pairs.builds)
        s["pl_skin"] = float(self.pairs.skin)
        saved = self._saved
        if saved is None and not keep_lists and self._lists_valid and self.pairs.n == P.n:
            saved = self._history_keys()  # lists index ghost rows: keep the history by gid pairs only
        s["has_saved"] = int(saved is not None)
        if saved is not None:
            (k, v), (wk, wv) = saved
            s.update(saved_keys=k.copy(), saved_vals=v.copy(), saved_wkeys=wk.copy(), saved_wvals=wv.copy())
        s["pos_ref"] = self.pos_ref[: P.n_owned].copy()
        s["dirty"] = int(self._dirty or not keep_lists)
        s["forces_valid"] = int(self._forces_valid and keep_lists)
        s["since_sort"] = int(self._since_sort)
        s["dt"] = float(self._dt) if self._dt is not None else -1.0
        s["time"] = float(self.time)
        s["steps"] = int(self.steps)
        s["max_overlap"] = float(self.max_overlap)
        s["walls_count"] = int(self.walls.count)  # wall ids index these walls (see set_state)
        return s

    def set_state(self, state: dict) -> None:
        """Restore a state of `get_state` (arrays as loaded by np.load are fine) into this DEM."""
        self.layout += 1
        missing = [k for k in ("p_pos", "p_gid", "time", "steps", "dt") if k not in state]
        if missing:
            raise ValueError(f"state misses {missing}: pass a dict from DEM.get_state()")
        data = {k[2:]: np.asarray(v) for k, v in state.items() if k.startswith("p_") and k != "p_next_gid"}
        P = Particles.from_dict(data)
        P.next_gid = max(int(state.get("p_next_gid", P.next_gid)), P.next_gid)
        for k, v in state.items():
            if k.startswith("aux_"):
                v = np.asarray(v, dtype=float).reshape(P.n_owned, -1)
                P.attach(k[4:], v.shape[1])[:] = v
        self.particles = P
        n = P.n
        self.pairs = PairList(skin=float(state.get("pl_skin", 1e-12)))
        self.pairs.builds = int(state.get("pl_builds", 0))
        self._lists_valid = bool(int(state.get("lists_valid", 0)))
        if self._lists_valid:
            pl = self.pairs
            pl.start = np.array(state["pl_start"], dtype=np.int64)
            pl.nbr = np.array(state["pl_nbr"], dtype=np.int64)
            pl.hist = np.array(state["pl_hist"], dtype=float).reshape(-1, 3)
            pl.n = n
            self.wstart = np.array(state["w_start"], dtype=np.int64)
            self.wid = np.array(state["w_id"], dtype=np.int64)
            self.whist = np.array(state["w_hist"], dtype=float).reshape(-1, 3)
            self.walls.prepare(0.5 * float(P.diameter.max()) + pl.skin if n else 0.0)
        self._saved = None
        if int(state.get("has_saved", 0)):
            self._saved = (
                (np.array(state["saved_keys"], dtype=np.int64), np.array(state["saved_vals"]).reshape(-1, 3)),
                (np.array(state["saved_wkeys"], dtype=np.int64), np.array(state["saved_wvals"]).reshape(-1, 3)),
            )
        other_walls = int(state.get("walls_count", -1)) != self.walls.count
        if other_walls:  # other walls (or a checkpoint from before the bounding-box planes)
            self._forget_wall_history()
        other_skin = False
        if self._lists_valid and P.n_owned:  # lists built with another skin (a restart that changed it): rebuild
            skin = self.params.skin * float(P.diameter[: P.n_owned].max())
            other_skin = not np.isclose(self.pairs.skin, skin, rtol=1e-12, atol=0.0)
            if other_skin:
                self._saved = self._history_keys()
                self._lists_valid = False
        self.pos_ref = np.array(state["pos_ref"], dtype=float).reshape(-1, 3)
        self._dirty = bool(int(state.get("dirty", 1))) or other_walls or other_skin
        self._forces_valid = bool(int(state.get("forces_valid", 0)))
        self._since_sort = int(state.get("since_sort", 0))
        dt = float(state["dt"])
        self._dt = dt if dt > 0 else None
        self.time = float(state["time"])
        self.steps = int(state["steps"])
        self.max_overlap = float(state.get("max_overlap", 0.0))

    def _forget_wall_history(self) -> None:
        """Drop the restored particle-wall lists and history (their wall ids mean other walls); keep the pairs'."""
        if self._lists_valid:
            P = self.particles
            self._saved = (self.pairs.saved_history(P.gid, P.n_owned), None)
            self._lists_valid = False
        if self._saved is not None:
            self._saved = (self._saved[0], (np.zeros(0, dtype=np.int64), np.zeros((0, 3))))
        self.wstart = np.zeros(1, dtype=np.int64)
        self.wid = np.zeros(64, dtype=np.int64)
        self.whist = np.zeros((64, 3))

    # ------------------------------------------------------------------ diagnostics
    def kinetic_energy(self) -> float:
        """Kinetic energy (J) of the particles (of every rank: collective with MPI), translation + rotation."""
        return self.global_sum(self.particles.kinetic_energy())

    def count(self) -> int:
        """Number of particles over all ranks (collective with MPI)."""
        return int(self.global_sum(self.particles.n_owned))

    def mean_kinetic_energy(self) -> float:
        """Mean kinetic energy per particle (J; collective with MPI)."""
        n = self.count()
        return self.kinetic_energy() / n if n else 0.0

    def elastic_energy(self) -> float:
        """Energy (J) stored in the normal springs of the particle-particle and particle-wall contacts (collective).

        Each spring has the stiffness the force law gives it: k_n, or with per-pair group scaling
        (`febed.dem.contact.GroupParams`, PCPM) k_n l² with l³ = m_eff / m_ref of that pair (a wall: m_i / m_ref).
        """
        if self.exchange.any(self._dirty) if self.exchange is not None else self._dirty:
            self.rebuild()  # with MPI it may migrate rows: the counts below are taken after it
        P = self.particles
        n = P.n_owned
        pl = self.pairs
        m = int(pl.start[n])
        i = np.repeat(np.arange(n), np.diff(pl.start[: n + 1]))
        j = pl.nbr[:m]
        r = 0.5 * P.diameter
        delta = r[i] + r[j] - np.linalg.norm(P.pos[j] - P.pos[i], axis=1)
        share = np.where(j < n, 1.0, 0.5)  # a contact with a ghost is counted half here, half by its owner
        k = share * self.pp.stiffness
        m_ref = getattr(self.pp, "m_ref", None)
        if m_ref is not None:  # per-pair group scaling: k_n (m_eff / m_ref)^(2/3)
            k = k * (1.0 / (m_ref / P.mass[i] + m_ref / P.mass[j])) ** (2.0 / 3.0)
        e = 0.5 * float(np.sum(k * np.maximum(delta, 0.0) ** 2))
        W = self.walls
        if W.count:  # the nearest wall among each particle's candidates (the wall lists are current)
            m_ref = getattr(self.pw, "m_ref", None)
            scale = None if m_ref is None else (P.mass[:n] / m_ref) ** (2.0 / 3.0)
            sq = wall_overlap_squares(P.pos, r, n, self.wstart, self.wid, W.geometry,
                                      np.ones(n) if scale is None else scale)  # fmt: skip
            e += 0.5 * self.pw.stiffness * sq
        return self.global_sum(e)

    def potential_energy(self) -> float:
        """Gravitational potential energy (J) relative to the origin (collective with MPI)."""
        P = self.particles
        n = P.n_owned
        return self.global_sum(-float(np.dot(P.mass[:n], P.pos[:n] @ self.gvec)))
