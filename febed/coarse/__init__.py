"""Coarse-graining: traditional parcels (TM, seed 000 eqs 17-25), the rho d^2 rule (SCG, seed 003 eq 7), PCPM.

Dynamic particle-groups that crush and merge (PCPM, seed 000 sec 2.3) and the one-way driver that moves
particles in a prescribed gas (seed 003 sec 4-5).

Public entry points: `tm_dem_params`, `tm_contact_params`, `tm_parcels`, `tm_contact_time`,
`use_group_contacts` (febed.coarse.tm);
`scg_density` (febed.coarse.scg); `OneWay`, `OneWayCase` (febed.coarse.oneway; a one-way case runs through
`febed.runs.oneway`); `GroupDynamics`, `equivalent_diameter` (febed.coarse.pcpm).
"""
