# # A 2D bubbling bed: the seed-000 case
#
# Wang et al. (2020, "seed 000") fluidize 4,080 particles of 1.5 mm and 1,150 kg/m³ in a 90 mm × 500 mm
# two-dimensional bed (18 × 100 cells of 5 mm) with air-like gas (1.28 kg/m³, 1.7e-5 Pa s) at a
# superficial velocity of 0.9 m/s; contacts: k = 800 N/m, μ = 0.3, e = 0.9 (their Table 2). This demo runs
# that case with plain DEM in febed (`wang2d.toml`), then plots what the paper plots: the pressure drop at
# the section 45 mm above the distributor, the bed height over time, and particle snapshots.
#
# Usage: `.venv/bin/python demos/wang2d/demo_wang2d.py [--end-time 1.0]` (`make demo` runs 0.3 s), or the
# same under `mpirun -n 2`: the run is shared by the ranks, rank 0 draws the figures and checks. The run and
# the figures go to `out/` beside this script. The packed bed `wang2d-bed.npz` is loaded from this folder
# (delete it to re-pack: ~1.5 min).
#
# The Wen–Yu/Ergun minimum fluidization velocity of these particles is about 0.49 m/s, so at 0.9 m/s the
# bed must fluidize: once started, the gas carries the whole bed, so the time-averaged pressure drop across
# it equals the bed weight per cross-section, W/A = N m_p g / (L_x × depth), with the depth of a 2D case one
# particle diameter (docs/theory.md, 2D cases).

import argparse
import logging
import math
import sys
from pathlib import Path

from mpi4py import MPI

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from febed.case import load_case
from febed.io.particles import read_vtp
from febed.io.probes import read_probes
from febed.io.rundir import get_logger, prepare_output, release_output
from febed.runs.coupled import run_coupled

HERE = Path(__file__).parent
parser = argparse.ArgumentParser()
parser.add_argument("--end-time", type=float, default=1.0, help="simulated seconds (s)")
args = parser.parse_args()

# ## Run the case
#
# The case file holds the physics; only the end time and the output folder are set here. `prepare_output`
# clears the previous run of `out/` (rank 0, for every rank) and locks the folder until the demo ends.

out = HERE / "out"
case = load_case(HERE / "wang2d.toml", [f"run.end_time={args.end_time}", f"output.directory={out}"])
log = get_logger(prepare_output(case, overwrite=True))
run = run_coupled(case, out, log)
MPI.COMM_WORLD.barrier()  # the output files are complete
if MPI.COMM_WORLD.rank != 0:  # the figures and checks read the output files: rank 0 alone makes them
    sys.exit()

# ## Pressure drop and bed height
#
# Probes are a CSV time series (`out/probes.csv`). The pressure drop "at 45 mm" is the cross-section
# averaged pressure at 45 mm minus that at the outlet; `dp_bed` is the bottom-to-top drop less the gas
# column's weight.

pr = {k: np.asarray(v) for k, v in read_probes(out / "probes.csv").items()}
t = pr["time"]
p = case.particles
n = int(pr["particles"][-1])
weight = n * p.density * math.pi / 6 * p.diameter**3 * case.run.gravity / (0.09 * p.diameter)
fig, ax = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
ax[0].plot(t, pr["p_0.045"] - pr["p_top"], label="at 45 mm above the distributor")
ax[0].plot(t, pr["dp_bed"], label="across the bed (bottom − top − gas weight)", alpha=0.7)
ax[0].axhline(weight, color="k", ls="--", lw=1, label="bed weight / cross-section")
ax[0].set(ylabel="pressure drop [Pa]")
ax[0].legend(fontsize=8)
ax[1].plot(t, 1e3 * pr["bed_height"])
ax[1].set(xlabel="t [s]", ylabel=f"bed height [mm] ({case.output.bed_fraction:.0%} of the volume below)")
fig.tight_layout()
fig.savefig(out / "pressure_and_bed_height.png", dpi=120)

# ## Particle snapshots
#
# Every particle output (`out/particles/*.vtp`, open `particles.pvd` in ParaView); here a few of them,
# coloured by vertical velocity.

files = sorted((out / "particles").glob("particles_*.vtp"))
picks = [files[i] for i in np.linspace(0, len(files) - 1, min(6, len(files))).astype(int)]
fig, axes = plt.subplots(1, len(picks), figsize=(2.0 * len(picks), 6), sharey=True)
for a, f in zip(np.atleast_1d(axes), picks, strict=True):
    d = read_vtp(f)
    x, vy = 1e3 * d["Points"], d["velocity"][:, 1]
    a.scatter(x[:, 0], x[:, 1], s=1.5, c=vy, cmap="coolwarm", vmin=-0.5, vmax=0.5)
    k = int(f.stem.split("_")[-1])
    a.set(xlim=(0, 90), ylim=(0, 350), aspect="equal", title=f"t = {k * case.output.particle_interval:.2f} s")
    a.set_xlabel("x [mm]")
np.atleast_1d(axes)[0].set_ylabel("y [mm]")
fig.suptitle("particles, coloured by vertical velocity (−0.5 … 0.5 m/s)")
fig.tight_layout()
fig.savefig(out / "snapshots.png", dpi=120)
print(f"figures: {out / 'pressure_and_bed_height.png'} and {out / 'snapshots.png'}")

# ## Checks
#
# The bed lifts above its packed height, no particle is lost, and the gas mass balance closes every step.
# Over a long enough run (≥ 1 s), the time-averaged pressure drop after start-up carries the bed's weight.

if args.end_time >= 0.2:
    assert pr["bed_height"][-10:].mean() > pr["bed_height"][0] * 1.05, "the bed did not expand"
assert int(pr["particles"][-1]) == case.particles.count and pr["left_outlet"][-1] == 0
assert np.abs(pr["gas_mass_imbalance"]).max() < 1e-6 * np.abs(pr["gas_inflow"]).max()
if args.end_time >= 1.0:
    late = t >= 0.3
    ratio = pr["dp_bed"][late].mean() / weight
    print(f"time-averaged bed pressure drop / weight over t >= 0.3 s: {ratio:.3f}")
    assert abs(ratio - 1) < 0.05
release_output(out)
logging.shutdown()
