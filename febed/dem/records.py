"""The named records the DEM's Numba kernels take (`febed.dem.forces`, `febed.dem.integrate`).

Each record is a NamedTuple of plain numpy arrays and scalars: Numba compiles field access like a local
variable, so naming the kernels' inputs costs nothing at run time. A kernel is called as

    compute_forces(bodies, bodies.vel, bodies.omega, lists, lists.hist, lists.whist, walls, model, dt, dt)

with `bodies` from `DEM.bodies()`, `lists` from `DEM.lists()`, `walls` a `febed.dem.walls.WallGeometry` and
`model` from `DEM.model()`. The records hold references to the DEM's arrays, not copies: a rebuild of the
pair list or a sort of the rows replaces those arrays, so fetch the records again after one
(`DEM.kernel_args`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from febed.kernel_records import fast_typeof


@fast_typeof
class Bodies(NamedTuple):
    """The particle rows a kernel works on: [0, n_owned) owned, [n_owned, n) ghost copies of other ranks' rows."""

    pos: np.ndarray  # (n, 3) m
    vel: np.ndarray  # (n, 3) m/s
    omega: np.ndarray  # (n, 3) rad/s
    force: np.ndarray  # (n, 3) N: gravity + contacts, written by the force loop
    torque: np.ndarray  # (n, 3) N m: contacts, written by the force loop
    fext: np.ndarray  # (n, 3) N: external force held over the steps (drag + pressure gradient)
    diameter: np.ndarray  # (n,) m
    mass: np.ndarray  # (n,) kg
    inertia: np.ndarray  # (n,) kg m^2
    n_owned: int
    n: int


@fast_typeof
class Lists(NamedTuple):
    """The candidate contacts of the owned rows (CSR) and their tangential elongations (m)."""

    start: np.ndarray  # (n_owned + 1,) int: row i's partners are nbr[start[i]:start[i + 1]] (half list)
    nbr: np.ndarray  # int: partner rows (owned or ghost)
    hist: np.ndarray  # (pairs, 3) m: tangential elongation of each listed pair
    wstart: np.ndarray  # (n_owned + 1,) int: row i's walls are wid[wstart[i]:wstart[i + 1]]
    wid: np.ndarray  # int: wall indices of `febed.dem.walls.WallGeometry`
    whist: np.ndarray  # (wall pairs, 3) m: tangential elongation of each listed particle-wall pair


@fast_typeof
class Model(NamedTuple):
    """The contact laws and the options of the equations of motion."""

    pp: tuple  # particle-particle law parameters (`febed.dem.contact`; their type selects the law)
    pw: tuple  # particle-wall law parameters
    rotation: bool  # integrate the angular velocity (contact torques)
    gvec: np.ndarray  # (3,) m/s^2 gravity
    dim2: bool  # 2D: v_z = 0 and omega_x = omega_y = 0 are kept


@fast_typeof
class Scratch(NamedTuple):
    """Work arrays of the integrators (the RK2 start-of-step state, or Verlet's predicted velocities)."""

    pos: np.ndarray  # (n, 3)
    vel: np.ndarray  # (n, 3)
    omega: np.ndarray  # (n, 3)
    hist: np.ndarray  # (pairs, 3): RK2's first-stage elongations
    whist: np.ndarray  # (wall pairs, 3)

    @classmethod
    def sized(cls, n: int, pairs: int, wall_pairs: int) -> Scratch:
        """Zeroed work arrays for n rows and the given list lengths."""
        return cls(
            np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((pairs, 3)), np.zeros((wall_pairs, 3))
        )

    def fits(self, n: int, pairs: int, wall_pairs: int) -> bool:
        """Whether these arrays are large enough for n rows and the given list lengths."""
        return self.pos.shape[0] >= n and self.hist.shape[0] >= pairs and self.whist.shape[0] >= wall_pairs
