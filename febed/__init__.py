"""febed: CFD-DEM for gas-solid fluidized beds.

The gas is a volume-averaged Navier-Stokes solver in DOLFINx, the particles a Numba DEM, the coupling
node-based as in YALES2 (seed 001), with the coarse-graining models of seeds 000 and 003.
See DESIGN.md-derived module docstrings and README.md for the layout.
"""

__version__ = "0.1.0"
