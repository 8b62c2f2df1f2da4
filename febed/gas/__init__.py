"""The gas phase: a node-based VANS projection solver (seed 001 §2.4.1) on DOLFINx P1/Q1 nodes.

Public API: `VANSSolver`, `VANSParameters`, `BoundarySpec`, `StepInfo` (see `febed.gas.vans`); gas-only
cases run through `febed.runs.gas.run`.
"""

from febed.gas.boundary import BoundarySpec
from febed.gas.vans import StepInfo, VANSParameters, VANSSolver

__all__ = ["BoundarySpec", "StepInfo", "VANSParameters", "VANSSolver"]
