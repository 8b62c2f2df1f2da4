"""Gas-particle coupling: location in cells, P1/Q1 weights, projection + neighbour filter, interpolation, drag."""
