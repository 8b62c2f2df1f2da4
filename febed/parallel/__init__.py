"""MPI decomposition of the particles: ownership by mesh partition, migration, ghost particles (seed 001 sec 2.5).

The DEM and the coupling stay unaware of ranks; they meet MPI only through `ParticleExchange`.
"""

from febed.parallel.exchange import ParticleExchange
from febed.parallel.partition import block_partitioner, cell_owners, slab_partitioner

__all__ = ["ParticleExchange", "block_partitioner", "cell_owners", "slab_partitioner"]
