"""Numba discrete element method: particles, contact laws, walls, neighbour search, integrators, insertion.

Public entry points: `DEM`, `DEMParams`, `DEMFailure` (febed.dem.solver), `Particles`, `Walls`.
"""

from febed.dem.particles import Particles
from febed.dem.solver import DEM, DEMFailure, DEMParams
from febed.dem.walls import Walls

__all__ = ["DEM", "DEMFailure", "DEMParams", "Particles", "Walls"]
