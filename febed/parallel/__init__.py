"""MPI decomposition of the particles: ownership by mesh partition, migration, ghost particles (seed 001 sec 2.5).

The DEM and the coupling stay unaware of ranks; they meet MPI only through `ParticleExchange` (particles owned
by the rank of their mesh cell) or `BoxExchange` (by work-balanced boxes, pure-DEM runs).
"""

from febed.parallel.box_exchange import BoxExchange
from febed.parallel.exchange import ParticleExchange
from febed.parallel.partition import block_partitioner, cell_owners, slab_partitioner

__all__ = ["BoxExchange", "ParticleExchange", "block_partitioner", "cell_owners", "slab_partitioner"]
