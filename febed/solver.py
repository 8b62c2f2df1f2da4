"""The coupled CFD-DEM time loop: the one place that knows the order of operations (seed 001 sec 2.4).

One gas step of size Δt (time-staggered; docs/theory.md, data flow):

1. **Particles** (`advance_particles`): with the gas fields of step n frozen, `n_sub` DEM sub-steps of
   Δt/n_sub ≤ T_C/dt_factor. The particles are located in the mesh (walk from the previous cell) and u, ε,
   ∇p interpolated with the node weights once per gas step; the drag coefficient K_p and the pressure
   force are then frozen over the step and the drag K_p (u@p − v_p) is re-evaluated with the current
   particle velocity every `chunk` sub-steps, where chunks are short against the particle relaxation time
   τ_p = m_p/K_p (at most 0.1 τ_p). Relocating every sub-step would change nothing measurable: in a gas
   step a particle moves |v| Δt ≤ CFL·Δx/ε-scaled ≪ one cell, while costing a search per sub-step.
   Gravity and contacts are the DEM's. Particles leaving through an `outlet` are removed and counted;
   anywhere else, the run stops naming the particle.
2. **Projection** (`project`): particle volume, K_p and K_p v_p onto the nodes of each particle's cell with
   the same weights, the conservative neighbour filter, division by the node volumes → α_p, ε^{n+1} (with a
   floor), K_i, K_i v̄_i.
3. **Gas** (`febed.gas.vans.VANSSolver.step`): predictor with −K_i(u_i − v̄_i) implicit, pressure Poisson
   with the ∂ε/∂t source, correction.
4. **Probes and output** on their own intervals (`febed.runs.coupled.CoupledRun`).

Momentum exchange (seed 001 eq 29): a particle receives the drag K_p (u@p − v_p) and the pressure-gradient
force F_P = −V_p ∇p@p; the gas receives minus both, −Σ_p ω_{p,i} K_p (u_i − v_p) implicitly through K_i and
K_i v̄_i, and −Σ_p ω_{p,i} F_P,p explicitly. Because the gas momentum carries the full −∇P, returning F_P
is what makes the bed's weight appear in the pressure drop. Without filtering, what the particles receive
and what the gas gives are the same sum, since interpolation and projection share their weights
(tested in tests/test_solver.py).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

from mpi4py import MPI

import numpy as np
from numba import njit

from febed.bed import build_dem
from febed.coarse import setup as coarse
from febed.coupling.drag import (
    RECORD_COLUMNS,
    RECORD_FORCE,
    RECORD_FP,
    RECORD_K,
    RECORD_SET,
    RECORD_VEL,
)
from febed.coupling.exchange import Coupler
from febed.coupling.locate import OUTSIDE_DOMAIN, OUTSIDE_LOCAL
from febed.coupling.mesh_arrays import extract_mesh_arrays
from febed.coupling.owners import OwnerCoupler
from febed.gas.pressure import PressureSolveError
from febed.gas.vans import StepInfo, VANSSolver
from febed.io.state import dem_arrays, gas_arrays, load_dem, restore_gas
from febed.meshing import load_msh
from febed.parallel.box_exchange import BoxExchange
from febed.parallel.exchange import ParticleExchange
from febed.parallel.partition import cell_owners

FLUID = "fluid"  # auxiliary particle array: the exchange record, columns `febed.coupling.drag.RECORD_*`
FLUID_COLUMNS = RECORD_COLUMNS


@njit(cache=True)
def _all_finite(a):
    """True if every entry of the flat array `a` is finite (no NaN, no ±inf)."""
    for x in a:
        if not math.isfinite(x):
            return False
    return True


@njit(cache=True)
def _all_set(a, j):
    """True if column j of the 2D array `a` is nonzero in every row (`a[:, j].all()` without temporaries)."""
    for i in range(a.shape[0]):
        if a[i, j] == 0.0:
            return False
    return True


def all_finite(a: np.ndarray) -> bool:
    """True if every entry of `a` is finite: `np.isfinite(a).all()` in one pass without temporaries."""
    return bool(_all_finite(np.ascontiguousarray(a, dtype=np.float64).reshape(-1)))


class RunFailure(RuntimeError):
    """The simulation went wrong (a particle escaped, NaN, ...); the message says what, where and when."""


@dataclass
class Limits:
    """When a run is declared failed (`[run]` keys of the same names; see `CoupledSolver.check`).

    Attributes:
        max_overlap: largest particle overlap allowed, as a fraction of the pair's smaller diameter.
        max_clipped_fraction: largest share of the nodes whose void fraction may sit at the floor.
    """

    max_overlap: float = 0.1
    max_clipped_fraction: float = 0.05

    @classmethod
    def from_case(cls, case) -> Limits:
        """The limits of a case's `[run]` section."""
        return cls(case.run.max_overlap, case.run.max_clipped_fraction)


@dataclass
class Timers:
    """Wall-clock seconds spent per part of the loop (DEM / coupling / gas / output)."""

    dem: float = 0.0
    coupling: float = 0.0
    gas: float = 0.0
    output: float = 0.0

    def as_dict(self) -> dict[str, float]:
        """The split as a dict of seconds."""
        return {"wall_dem": self.dem, "wall_coupling": self.coupling, "wall_gas": self.gas, "wall_output": self.output}


class CoupledSolver:
    """Gas (DOLFINx VANS) + particles (Numba DEM) + node-based coupling of one case.

    Attributes:
        gas: the `VANSSolver`; dem: the `DEM`; ma: the coupling's `MeshArrays` over the gas's nodal space.
        t: simulated time (s); steps: gas steps done; left_outlet: particles removed at the outlet.
        clipped: nodes whose void fraction was clipped to the floor at the last projection.
    """

    def __init__(self, case, md, dem, gas, log=None):
        """Couple an already built DEM and gas solver on mesh `md` (see `build_solver`)."""
        self.case = case
        self.md = md
        self.dem = dem
        self.gas = gas
        self.log = log
        self.gdim = md.gdim
        self.depth = coarse.particle_depth(case) if md.gdim == 2 else 1.0
        self.ma = extract_mesh_arrays(md.mesh, gas.Q, depth=self.depth)
        cp = case.coupling
        law = dict(drag=cp.drag, rho_g=case.gas.density, mu_g=case.gas.viscosity, filter_passes=cp.filter_passes,
                   void_floor=cp.void_fraction_floor, pressure_gradient=cp.pressure_gradient)  # fmt: skip
        self.law = law  # the coupler's drag law and options (a coupler built apart takes the same)
        located_on = md  # the mesh the particles are located on
        if md.comm.size > 1 and case.run.particle_partition == "work":  # boxes of equal DEM work
            if not md.source:
                raise ValueError("[run] particle_partition = 'work': the coupling reads the whole mesh on every rank "
                                 "from its .msh file, and this mesh was not read from one (use 'mesh')")  # fmt: skip
            located_on = load_msh(md.source, MPI.COMM_SELF, gdim=md.gdim)  # the whole mesh, on every rank
            self.coupler = OwnerCoupler.build(self.ma, md.mesh, gas.Q, located_on.mesh, self.depth, **law)
            dem.attach_exchange(BoxExchange(md.comm, dim=md.gdim), distribute=True)
        else:
            self.coupler = Coupler(self.ma, **law)
            if md.comm.size > 1:  # particles live with the mesh partition (seed 001 sec 2.5)
                dem.attach_exchange(ParticleExchange(self.ma, cell_owners(md.mesh)), distribute=True)
        self.fixed = case.particles.fixed
        self._located = -1  # the DEM's `layout` the coupler's cells and weights were found for (`located`)
        self._fluid_tau = None  # min m_p/K_p if the FLUID record is already that of the next step (PCPM)
        self.outlet_facets = self._outlet_facet_mask(located_on)  # the whole mesh's DOLFINx objects go after it
        self.t = 0.0
        self.steps = 0
        self.left_outlet = 0
        self.clipped = 0
        self.n_sub = 0
        self.timers = Timers()
        self.last_gas = None
        self.limits = Limits.from_case(case)
        self.groups = coarse.group_dynamics(case)  # PCPM particle-groups, or None
        self.rng = np.random.default_rng(case.run.seed)  # checkpointed with the run (coarse-grain events)
        self._failure = None  # first problem met inside a step, raised collectively by `check`
        self._n_nodes = md.comm.allreduce(self.ma.num_owned_dofs)
        eps0 = self.project()[0]
        gas.set_void_fraction(eps0)

    @property
    def num_nodes(self) -> int:
        """Gas nodes of the whole mesh (every rank's owned nodes)."""
        return self._n_nodes

    def partition_line(self) -> str:
        """How the mesh and the particles are shared among the ranks (for the log)."""
        if isinstance(self.coupler, OwnerCoupler):
            return ("the mesh in blocks, the particles in boxes of equal DEM work (run.particle_partition = "
                    "'work'), each coupled on its own rank over the whole mesh")  # fmt: skip
        return "the mesh in columns, each particle on the rank owning its cell (run.particle_partition = 'mesh')"

    # ------------------------------------------------------------------------------------------ setup
    def _outlet_facet_mask(self, md) -> np.ndarray:
        """Boolean over the local facets of `md`: True on facets whose tag is an `outlet` boundary."""
        mesh = md.mesh
        fdim = mesh.topology.dim - 1
        mesh.topology.create_entities(fdim)
        nf = mesh.topology.index_map(fdim).size_local + mesh.topology.index_map(fdim).num_ghosts
        mask = np.zeros(nf, dtype=bool)
        for tag, b in self.case.boundary.items():
            if b.type == "outlet":
                mask[md.facets(tag)] = True
        return mask

    # ----------------------------------------------------------------------------------- the algorithm
    def step(self) -> None:
        """One gas step: particle sub-steps with the gas frozen → projection → gas step (seed 001 sec 2.4)."""
        dt = self.gas.compute_dt()
        self.n_sub = max(1, math.ceil(dt / self.dem.dt * (1 - 1e-12)))
        if self.fixed:  # the particles do not move, but the gas they see does: their K_p, F_P for this step
            t0 = time.perf_counter()
            self._fluid(relocate=self._must_relocate())
            self.timers.coupling += time.perf_counter() - t0
        else:
            self.advance_particles(dt, self.n_sub)  # times itself (DEM / coupling)
        t1 = time.perf_counter()
        eps, K, Kv, force = self.project()
        share = eps if self._nodal_reaction() else None  # the gas carries −ε∇p^{n+1} (VANSSolver: the share)
        t2 = time.perf_counter()
        try:
            self.last_gas = self.gas.step(dt, eps=eps, K=K, Kv=Kv, force=force, pressure_share=share)
        except PressureSolveError as e:  # raised on every rank (the Krylov solve is collective)
            self._failure = self._failure or self._local_problem()  # name the cause if the particles show it
            self._failure = self._failure or f"gas step from t = {self.t:.6g} s (dt = {dt:.3g} s): {e}"
            self.check()
        t3 = time.perf_counter()
        self.timers.coupling += t2 - t1
        self.timers.gas += t3 - t2
        self.t += dt
        self.steps += 1
        if self.groups is not None:
            self.group_events(dt)

    def advance_particles(self, dt: float, n_sub: int) -> None:
        """`n_sub` DEM steps of dt/n_sub with drag and pressure-gradient forces from the frozen gas.

        K_p, F_D + F_P and v_p at the step start travel with the particles as an auxiliary array (through the
        DEM's reordering and, with MPI, migration), so each chunk's force K_p (u − v) = F_D + K_p (v0 − v) is
        formed in the current row order.
        """
        t0 = time.perf_counter()
        tau = self._fluid_tau  # the record `group_events` made from this gas, if the particles are unchanged since
        relocate = self._must_relocate()
        if tau is None or relocate:
            tau = self._fluid(relocate=relocate)  # min_p m_p/K_p (inf without particles)
        self._fluid_tau = None
        P = self.dem.particles
        if self.md.comm.size > 1:  # every rank steps the same chunks (the DEM exchanges ghosts per step)
            tau = self.md.comm.allreduce(tau, op=MPI.MIN)
        ratio = dt / (0.1 * tau) if tau > 0 else math.inf  # tau 0 or NaN: a failing run (the check names it)
        chunks = max(1, math.ceil(ratio)) if ratio < n_sub else n_sub  # NaN (a failing run): every sub-step
        h = dt / n_sub
        done = 0
        for k in range(chunks):
            steps = (n_sub * (k + 1)) // chunks - done
            n = P.n_owned
            a = P.aux(FLUID)[:n]
            f = a[:, RECORD_FORCE]
            if k > 0:  # the drag relaxed to the particles' current velocity
                f = f + a[:, RECORD_K, None] * (a[:, RECORD_VEL] - P.vel[:n])
            t1 = time.perf_counter()
            self.timers.coupling += t1 - t0
            self.dem.advance(steps, h, f)
            t0 = time.perf_counter()
            self.timers.dem += t0 - t1
            done += steps
        self.timers.coupling += time.perf_counter() - t0

    def group_events(self, dt: float) -> None:
        """PCPM: crush and merge the particle-groups in the flow of the gas step of dt (s) just made (seed 000 sec 2.3).

        Only at the gas steps that cross a multiple of `coarse_grain.event_interval` (`GroupDynamics.due`).
        The particles were located by `project` and have not moved since; the drag F_D evaluated here from the
        new gas is the record the next step starts from, so that step reuses it unless the events (or, with
        MPI, the ghost refresh) changed the particle rows.
        """
        gd = self.groups
        if not gd.due(self.t - dt, self.t):
            return
        dem = self.dem
        if gd.calls % gd.interval:  # due, but not this one of every `interval` (nothing is evaluated)
            gd.update(dem, None, None, None)
            return
        t0 = time.perf_counter()
        gd.prepare(dem)  # a rebuild may reorder the rows
        if not self.located:
            self.locate_particles()
        f_d = np.empty((dem.particles.n_owned, 3))
        tau = self._fluid(relocate=False, drag=f_d)
        u_p, eps_p, _ = self.coupler.gas_at_particles(self.gas.u, self.gas.eps, self.gas.grad_p)
        gd.update(dem, eps_p, u_p, f_d)
        if dem.exchange is None and not dem._dirty:  # no event: the same rows, so the same record next step
            self._fluid_tau = tau
        self.timers.coupling += time.perf_counter() - t0

    def _must_relocate(self) -> bool:
        """Whether the particles must be located again, agreed over the ranks (collective).

        Locating is collective with MPI (its migration check), and one rank's rows can change alone: PCPM events,
        or the ghost rows they drop, on some ranks only. Then every rank locates its particles again.
        """
        stale = not self.located
        return bool(self.md.comm.allreduce(stale, op=MPI.LOR)) if self.md.comm.size > 1 else stale

    @property
    def located(self) -> bool:
        """True if the coupler's cells and weights are those of the particles' current rows and positions."""
        return self._located == self.dem.layout

    def locate_particles(self) -> None:
        """Locate the owned particles (walk from their previous cell); remove those that left by an outlet."""
        P = self.dem.particles
        n = P.n_owned
        c = self.coupler
        c.reset_cells(P.cell[:n])  # the DEM may have reordered its rows: cells travel with the particles
        missing = c.locate(P.pos[:n])
        if self.md.comm.size > 1 and self.dem.exchange is not None:
            n_beyond = int(np.count_nonzero(c.status[missing] == OUTSIDE_LOCAL)) if missing.size else 0
            if self.md.comm.allreduce(n_beyond, op=MPI.SUM):
                # a particle left its rank's local cells (owned + ghost) between two migrations, e.g. across a
                # corner of a staircase partition boundary whose diagonal neighbour is not a ghost cell:
                # migrate now (collective; the owner is found by asking every rank), then locate again
                self.dem.rebuild()
                P = self.dem.particles
                n = P.n_owned
                c.reset_cells(P.cell[:n])
                missing = c.locate(P.pos[:n])
        if missing.size:
            facet = c.exit_facet[missing]
            by_outlet = (c.status[missing] == OUTSIDE_DOMAIN) & (facet >= 0)
            by_outlet[by_outlet] = self.outlet_facets[facet[by_outlet]]
            nonfinite = missing[~np.isfinite(P.pos[missing]).all(axis=1)]
            if nonfinite.size and self._failure is None:
                k = int(nonfinite[0])
                self._failure = (
                    f"particle {int(P.gid[k])} has a non-finite position/velocity at t = {self.t:.6g} s "
                    f"({nonfinite.size} such particle(s))"
                )
            beyond = missing[c.status[missing] == OUTSIDE_LOCAL]
            if beyond.size and self._failure is None:
                k = int(beyond[0])
                self._failure = (
                    f"particle {int(P.gid[k])} at {P.pos[k].tolist()} m is beyond rank {self.md.comm.rank}'s "
                    f"local cells at t = {self.t:.6g} s even after a migration (no rank's cells hold it)"
                )
            if not by_outlet.all() and self._failure is None:  # raised by `check` on every rank
                k = int(missing[~by_outlet][0])
                self._failure = (
                    f"particle {int(P.gid[k])} at {P.pos[k].tolist()} m left the mesh other than through an "
                    f"outlet at t = {self.t:.6g} s ({int((~by_outlet).sum())} such particle(s))"
                )
            keep = np.ones(n, dtype=bool)
            keep[missing] = False
            self.left_outlet += int(by_outlet.sum())
            self.dem.remove_particles(~keep)
            n = P.n_owned
            c.reset_cells(c.cell[keep])
            c.locate(P.pos[:n])  # compacts the coupler's arrays; every cell is known, so no search
        P.cell[:n] = c.cell
        self._located = self.dem.layout

    # ------------------------------------------------------------------------------------ state
    def get_state(self) -> tuple[dict[str, np.ndarray], dict]:
        """This rank's state (copies): checkpoint arrays and a JSON-able record of the loop (collective).

        The arrays are `febed.io.state`'s `gas/...` and `dem/...`; the record holds the time, gas steps, particles
        removed at the outlet (the total over the ranks), timers, last gas step, random generator and groups.
        """
        arrays = gas_arrays(self.gas)
        arrays.update(dem_arrays(self.dem))
        record = {
            "time": self.t,
            "step": self.steps,
            "left_outlet": self.md.comm.allreduce(self.left_outlet),
            "n_sub": self.n_sub,
            "timers": self.timers.as_dict(),
            "last_gas": dataclasses.asdict(self.last_gas) if self.last_gas is not None else None,
            "rng": self.rng.bit_generator.state,
            "groups": self.groups.state_dict() if self.groups is not None else None,
        }
        return arrays, record

    def set_state(self, arrays: dict[str, np.ndarray], record: dict, ranks: int) -> None:
        """Take back a state of `get_state` written by `ranks` processes (every rank holds all of it; collective)."""
        restore_gas(self.gas, arrays, float(record["time"]), self.md.comm)
        self.load_particles(arrays, ranks)
        self.t, self.steps = float(record["time"]), int(record["step"])
        self.left_outlet = int(record["left_outlet"]) if self.md.comm.rank == 0 else 0  # the total, counted once
        self.n_sub = int(record["n_sub"])
        for k, v in record["timers"].items():
            setattr(self.timers, k.removeprefix("wall_"), float(v))
        self.last_gas = StepInfo(**record["last_gas"]) if record["last_gas"] is not None else None
        self.rng.bit_generator.state = record["rng"]
        if self.groups is not None and record.get("groups"):
            self.groups.load_state_dict(record["groups"])

    def load_particles(self, arrays: dict[str, np.ndarray], ranks: int) -> None:
        """Put a checkpoint's particles into the DEM (`febed.io.state.load_dem`), then locate them afresh."""
        load_dem(self.dem, arrays, {"ranks": ranks}, self.md.comm.size)
        self.reset_coupling()  # locate the particles and recompute α_p as at the end of the last step

    def reset_coupling(self) -> None:
        """Locate the particles afresh and recompute α_p (after the particles were replaced, e.g. a restart)."""
        self._failure = None
        self._located = -1
        self._fluid_tau = None
        self.project()

    # ------------------------------------------------------------------------------------ health
    def check(self) -> None:
        """Raise RunFailure on every rank if any rank finds a problem (collective; call after each step).

        Checks: a particle that left the mesh other than by an outlet; non-finite particle or gas values;
        an overlap above `max_overlap` of the pair's smaller diameter during the last step; more than
        `max_clipped_fraction` of the nodes with ε at its floor. The message says what, where and when.
        """
        msg = self._failure or self._local_problem()
        self.dem.max_overlap = 0.0
        if self.md.comm.size > 1:
            msgs = [m for m in self.md.comm.allgather(msg) if m]
            msg = msgs[0] if msgs else None
        if msg:
            raise RunFailure(msg)

    def _local_problem(self) -> str | None:
        P = self.dem.particles
        n = P.n_owned
        when = f"at t = {self.t:.6g} s (gas step {self.steps})"
        if not (all_finite(P.pos[:n]) and all_finite(P.vel[:n])):  # one pass while all is well
            bad = ~(np.isfinite(P.pos[:n]).all(axis=1) & np.isfinite(P.vel[:n]).all(axis=1))
            k = int(np.flatnonzero(bad)[0])
            return f"particle {int(P.gid[k])} has a non-finite position/velocity {when} (last cell {int(P.cell[k])})"
        for name, a in (("velocity u", self.gas.u), ("pressure p", self.gas.p)):
            if all_finite(a):
                continue
            ok = np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)
            if not ok.all():
                k = int(np.flatnonzero(~ok)[0])
                return f"gas {name} is not finite at the node at {self.ma.x_dofs[k].tolist()} m {when}"
        if self.dem.max_overlap > self.limits.max_overlap:
            return (
                f"a particle overlap reached {100 * self.dem.max_overlap:.3g} % of a diameter during the gas step "
                f"ending {when}, above run.max_overlap = {100 * self.limits.max_overlap:g} %"
                f"{self._worst_pair()}; lower the DEM step (contact.dt_factor) or stiffen the contacts"
            )
        if self.clipped > self.limits.max_clipped_fraction * self._n_nodes:
            floor = self.case.coupling.void_fraction_floor
            low = np.flatnonzero(self.gas.eps[: self.ma.num_owned_dofs] <= floor)
            where = f"; e.g. the node at {self.ma.x_dofs[low[0]].tolist()} m" if low.size else ""
            return (
                f"the void fraction sits at its floor {floor:g} on {self.clipped} of {self._n_nodes} nodes {when}, "
                f"more than run.max_clipped_fraction = {self.limits.max_clipped_fraction:g}{where}: particles are "
                "packed more densely than the mesh can represent (coarsen the mesh or add filter passes)"
            )
        return None

    def _worst_pair(self) -> str:
        """Where the largest current particle-particle overlap is (for failure messages)."""
        P = self.dem.particles
        pl = self.dem.pairs
        if pl.n == 0 or pl.n != P.n:
            return ""
        i = np.repeat(np.arange(pl.n), np.diff(pl.start[: pl.n + 1]))
        j = pl.nbr[: i.size]
        delta = 0.5 * (P.diameter[i] + P.diameter[j]) - np.linalg.norm(P.pos[j] - P.pos[i], axis=1)
        if delta.size == 0:
            return ""
        k = int(np.argmax(delta))
        a, b = int(i[k]), int(j[k])
        return f" (now largest between particles {int(P.gid[a])} and {int(P.gid[b])} near {P.pos[a].tolist()} m)"

    def _originals(self):
        """Closure diameter (m) and count of each owned particle (`febed.coarse.setup.closure_sizes`)."""
        P = self.dem.particles
        n = P.n_owned
        return coarse.closure_sizes(P.diameter[:n], P.n_orig[:n])

    def fluid_state(self, relocate: bool = True):
        """Drag coefficient K_p (kg/s), drag F_D and pressure-gradient force F_P (N, 3) per owned particle.

        Locates the particles first (unless `relocate` is False: they have not moved since the last call);
        one fused pass interpolates the current gas fields and applies the law (see `_fluid`).
        """
        f_d = np.empty((self.dem.particles.n_owned, 3))
        self._fluid(relocate, f_d)
        a = self.dem.particles.aux(FLUID)[: f_d.shape[0]]
        return a[:, RECORD_K].copy(), f_d, a[:, RECORD_FP].copy()

    def _fluid(self, relocate: bool, drag: np.ndarray | None = None) -> float:
        """Fill the FLUID record of every owned particle from the current gas; returns min m_p/K_p (s).

        One fused kernel interpolates u, ε, ∇p, applies the drag law and writes K_p, F_D + F_P, v_p, F_P and
        the valid flag (rows added later, e.g. by coarse-grain events, have 0: no coefficients yet); F_D goes
        to `drag` (n_owned, 3) if given.
        """
        if relocate:
            self.locate_particles()
        gas = self.gas
        P = self.dem.particles
        n = P.n_owned
        d_orig, n_orig = self._originals()
        record = P.attach(FLUID, FLUID_COLUMNS)[:n]
        u, eps, grad_p = gas.u, gas.eps, self._particles_grad_p()
        return self.coupler.forces_into(u, eps, grad_p, P.vel[:n], d_orig, n_orig, record, P.mass[:n], drag)

    def _nodal_reaction(self) -> bool:
        """Whether the gas receives the pressure-gradient force as (1 − ε_i)∇p_i (`pressure_gradient_reaction`)."""
        cp = self.case.coupling
        return cp.pressure_gradient and cp.pressure_gradient_reaction == "nodal"

    def _particles_grad_p(self) -> np.ndarray:
        """The nodal ∇p the particles interpolate (collective).

        The gas's, or with the nodal reaction its average by the void-fraction filter's transpose, so that the
        gas's (1 − ε_i)∇p_i sums to minus their F_P exactly.
        """
        if self._nodal_reaction():
            return self.coupler.filter_transpose(self.gas.grad_p)
        return self.gas.grad_p

    def _last_exchange(self):
        """K_p and F_P (views) the particles were given for this step, in the current row order (fresh if missing).

        Made fresh on every rank if any rank misses some (`_fluid` is collective): e.g. a checkpoint's rows that
        PCPM events added after the record was made, now spread over the ranks.
        """
        P = self.dem.particles
        n = P.n_owned
        missing = not (FLUID in P.aux_names and _all_set(P.aux(FLUID)[:n], RECORD_SET))
        if self.md.comm.size > 1:
            missing = self.md.comm.allreduce(missing, op=MPI.LOR)
        if missing:
            self._fluid(relocate=False)
        a = P.aux(FLUID)[:n]
        return a[:, RECORD_K], a[:, RECORD_FP]

    def project(self):
        """ε^{n+1} (with its floor), K_i [kg/(m^3 s)], K_i v̄_i and the explicit force density at the nodes.

        The particles are located at their new positions (weights ω_{p,i}); K_p and F_P are those the
        particles were given for the step (`fluid_state` at its start), so the gas is handed the same
        coefficients, −Σ_p ω_{p,i} K_p (u_i − v_p) implicitly and −Σ_p ω_{p,i} F_P,p / ΔV_i explicitly: with
        the drag, the gas receives minus every fluid force the particles receive (seed 001 eq 29). It also
        saves a second interpolation pass per gas step. With `coupling.pressure_gradient_reaction = "nodal"`
        the explicit force is instead (1 − ε_i)∇p_i from the gas's own nodal ∇p^n, and the gas step is given
        the pressure's share ε (`step`), so that the gas carries −ε∇p^{n+1} node by node, consistent with the ε
        and K it is given, while the particles interpolate ∇p^n averaged by the filter's transpose
        (`_particles_grad_p`): the totals agree to round-off for particles at rest in a steady flow
        (docs/theory.md, "Pressure-gradient force").
        """
        self.locate_particles()
        K, f_p = self._last_exchange()
        P = self.dem.particles
        d_orig, n_orig = self._originals()
        nodal = self._nodal_reaction()
        x = self.coupler.project_to_gas(d_orig, n_orig, K, P.vel[: P.n_owned], F_explicit=None if nodal else f_p)
        self.alpha, self.clipped = x.alpha, x.clipped
        F = (1.0 - x.eps)[:, None] * self.gas.grad_p if nodal else x.F  # nodal: the gas's own ∇p^n, explicit
        return x.eps, x.K, np.ascontiguousarray(x.Kv), np.ascontiguousarray(F)


def build_solver(case, md, log) -> CoupledSolver:
    """The coupled solver of a case on a mesh: DEM (walls, bed) + gas + coupling arrays.

    Args:
        case: a validated `Case` of mode "cfd-dem".
        md: the case's mesh (`febed.load_case_mesh`).
        log: the logger to report to.

    Returns:
        A `CoupledSolver` at t = 0 (or the bed's state): `step()` advances one gas step.
    """
    dem = build_dem(case, md, log)
    gas = VANSSolver.from_case(case, md)
    return CoupledSolver(case, md, dem, gas, log)
