# # The simpler coarse grain (SCG) of seed 003 in prescribed flows
#
# Seed 003 (Kushimoto et al. 2021) enlarges particles by a ratio l and lowers their density so that
# $\rho_{CG} d_{CG}^2 = \rho_O d_O^2$ (its eq 7). With Stokes drag the drag acceleration of a sphere is
# $18\mu(\mathbf u - \mathbf v)/(\rho_p d^2)$, so CG particles accelerate exactly like the originals.
# This script reproduces the paper's three checks with febed's one-way driver (`febed.coarse.oneway`: DEM
# particles in a prescribed gas, `febed.gas.prescribed`):
#
# 1. single particles of 1, 2, 4, 8 mm in a uniform flow (Table 1, Fig 3),
# 2. single particles of 10, 20, 40, 80 um in a forced vortex with 10 % radial inflow (Table 2, Fig 6),
# 3. a classifier (Table 3): a forced vortex of 5000 rpm with a radial inflow five times the vortex speed and an
#    axial outlet flow of 1 m/s in the nozzle core; radial-position distributions per size (Fig 10) and run
#    times (Fig 8) for originals, SCG particles (2x, eq 7) and enlarged particles of unchanged density.
#
# Run: `python demos/scg/scg_demo.py [--full] [--out DIR]`. The default run takes well under a minute;
# `--full` runs the paper's durations (3 s vortex, 0.3 s classifier sampled over 0.2-0.3 s). The figures and
# results.json go to demos/scg/out/; `--out demos/scg` (`--full --out demos/scg/full`) updates the ones shown
# in the documentation. One process: the one-way driver does not run under mpirun.

import argparse
import json
import math
import sys
import time
from pathlib import Path

from mpi4py import MPI

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from febed.coarse.oneway import OneWay
from febed.coarse.scg import scg_density
from febed.dem import DEM, DEMParams, Walls
from febed.gas.prescribed import make_prescribed_gas

RHO_G, MU = 1.2, 1.8e-5  # seed 003: air
RATIOS = np.array([1.0, 2.0, 4.0, 8.0])


def cylinder_walls(radius, sides=64, z=None):
    """A regular polygon prism (inward planes) approximating a cylinder about the z axis, plus z planes."""
    planes = []
    r_in = radius  # the polygon's inscribed radius is the vessel radius
    for k in range(sides):
        a = 2 * math.pi * k / sides
        nrm = np.array([-math.cos(a), -math.sin(a), 0.0])
        planes.append((-r_in * nrm, nrm))
    if z is not None:
        planes += [((0, 0, z[0]), (0, 0, 1.0)), ((0, 0, z[1]), (0, 0, -1.0))]
    return Walls(planes=planes)


# ## 1-2. Single particles: speed against time with and without the rule
#
# The four particles of each table start at rest on a line along which the flow does not vary: across the
# uniform flow (U = 1 m/s along x, a value we chose: the paper's Fig 1 gives it only graphically) and along the
# vortex axis at r = 0.4 mm (vessel radius 0.5 mm). No gravity; Stokes drag. With the rule the four speed
# histories must coincide; without it the larger particles lag.


def single_particles(flow, d0, rho0, pos, t_end, h, walls=None, stiffness=1.0):
    """Speed histories (n_windows + 1, 4) of the four Table 1/2 particles, with and without eq 7."""
    out = {}
    for rule in (True, False):
        d = d0 * RATIOS
        rho = scg_density(rho0, d0, d) if rule else np.full(4, rho0)
        dem = DEM(DEMParams(stiffness=stiffness, gravity=0.0, rotation=False, restitution_pw=0.5), walls=walls)
        dem.add_particles(pos, d, rho)
        ow = OneWay(dem, flow, "stokes")
        t, s = [0.0], [np.zeros(4)]

        def rec(o, t=t, s=s):
            P = o.dem.particles
            t.append(o.t)
            s.append(np.linalg.norm(P.vel[np.argsort(P.gid)], axis=1))

        ow.advance(t_end, h, rec)
        out[rule] = (np.array(t), np.array(s))
    return out


def spread(s):
    """Largest relative difference of the CG particles' speeds from the original's (after t = 0)."""
    s = s[1:]
    return float(np.max(np.abs(s[:, 1:] - s[:, :1]) / s[:, :1]))


def plot_speeds(res, title, unit, scale, path, labels):
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for ax, rule in zip(axes, (False, True), strict=True):
        t, s = res[rule]
        for k in range(4):
            ax.plot(t, s[:, k] * scale, ["-", "--", "-.", ":"][k], lw=2, label=labels[k])
        ax.set_title(f"{title}: {'with' if rule else 'without'} SCG")
        ax.set_xlabel("t (s)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(f"speed ({unit})")
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ## 3. The classifier (Table 3)
#
# Geometry (the paper's Fig 7 is not in the text; our choice): a cylindrical vessel of radius R = 5 mm and
# height H = 100 mm (the 7 m/s feed jet of the small particles is stopped by the gas long before the bottom),
# axis z, gravity -z; an outlet nozzle of radius r_o = 1.5 mm in the centre of the top wall.
# Gas: forced vortex omega = 5000 rpm, radial inflow u_r = -5 omega r, axial u_z = 1 m/s for r < r_o
# (`vortex` flow). A particle whose centre is inside the nozzle radius and within one radius of the top wall
# leaves through the outlet. Particles are fed at a constant volume rate, equal for the four sizes (Table 3),
# at random positions of the top annulus r_o + 0.5 mm < r < R - d, with 7 m/s downwards. The Stokes cut size is
# d_c = sqrt(18 mu a / (rho_p omega)) = 176 um for the originals (0.1 g/cm^3): 100 and 160 um drift in and
# leave, 220 and 280 um are flung to the wall - as the paper finds (cut between 160 and 220 um).
# Contacts: linear spring-dashpot, e = 0.5, mu = 0.3, k_n = 0.1 N/m in the default run (soft: the largest
# particles reach the bottom at a few m/s and overlap by more than a diameter there; the drag-dominated radial
# motion is what matters here) and 10 N/m with `--full` (overlaps of a few per cent, 10x smaller DEM step).
# The pair-list skin is 2 diameters: fed particles move at 7 m/s and would otherwise rebuild it every few steps.

R, H, R_O = 5e-3, 0.1, 1.5e-3
D_ORIG = np.array([100e-6, 160e-6, 220e-6, 280e-6])
RHO_ORIG = 100.0


def classifier(model, t_end, t_sample, n_big, stiffness=0.1, seed=1, dt_sample=5e-4):
    """Run one classifier case; model: 'original', 'scg' or 'plain' (2x, unchanged density)."""
    ratio = 1.0 if model == "original" else 2.0
    d = D_ORIG * ratio
    rho = np.full(4, RHO_ORIG)
    if model == "scg":
        rho = scg_density(RHO_ORIG, D_ORIG, d)
    # equal volume per size; the CG runs carry the same total volume (1/ratio^3 as many particles)
    n_feed = np.rint(n_big * (D_ORIG[-1] / D_ORIG) ** 3 / ratio**3).astype(int)
    n_feed = np.maximum(n_feed, 1)
    rng = np.random.default_rng(seed)
    sizes = np.concatenate([np.full(k, i) for i, k in enumerate(n_feed)])
    rng.shuffle(sizes)
    feed_t = np.sort(rng.uniform(0.0, t_end, sizes.size))
    params = DEMParams(contact_model="linear", stiffness=stiffness, restitution_pp=0.5, restitution_pw=0.5,
                       friction_pp=0.3, friction_pw=0.3, gravity=9.81, rotation=False, skin=2.0)  # fmt: skip
    dem = DEM(params, walls=cylinder_walls(R, z=(0.0, H)))
    gas = make_prescribed_gas("vortex", RHO_G, MU, rpm=5000.0, inflow_ratio=5.0, outlet_radius=R_O,
                              outlet_velocity=1.0)  # fmt: skip

    def sink(pos, diam):
        r2 = pos[:, 0] ** 2 + pos[:, 1] ** 2
        return (r2 < R_O**2) & (pos[:, 2] > H - 0.5 * diam - 1e-9)

    ow = OneWay(dem, gas, "stokes", sink=sink)
    size_of = {}  # gid -> size class
    fed = [0]
    samples = [[] for _ in range(4)]
    next_sample = [t_sample]
    drained = np.zeros(4, int)

    def feed(o):
        P = o.dem.particles
        k = int(np.searchsorted(feed_t, o.t, side="right"))
        new = []
        for q in range(fed[0], k):
            c = sizes[q]
            for _ in range(50):
                r = math.sqrt(rng.uniform((R_O + 5e-4) ** 2, (R - d[c]) ** 2))
                a = rng.uniform(0, 2 * math.pi)
                x = np.array([r * math.cos(a), r * math.sin(a), H - 0.6 * d.max()])
                n = P.n_owned
                ok = n == 0 or np.all(np.linalg.norm(P.pos[:n] - x, axis=1) > 0.5 * (P.diameter[:n] + d[c]))
                ok = ok and all(np.linalg.norm(y - x) > d.max() for y, _ in new)
                if ok:
                    new.append((x, c))
                    break
        fed[0] = k
        if new:
            cls = np.array([c for _, c in new])
            gids = o.dem.add_particles(np.array([x for x, _ in new]), d[cls], rho[cls],
                                       vel=np.tile([0.0, 0.0, -7.0], (len(new), 1)))  # fmt: skip
            size_of.update(zip(gids.tolist(), cls.tolist(), strict=True))

    prev = [set()]

    def after_window(o):
        P = o.dem.particles
        now = set(P.gid[: P.n_owned].tolist())
        for g in prev[0] - now:  # left through the outlet during this window
            drained[size_of[g]] += 1
        feed(o)
        if o.t + 1e-12 >= next_sample[0]:
            n = P.n_owned
            r = np.hypot(P.pos[:n, 0], P.pos[:n, 1])
            cls = np.array([size_of[g] for g in P.gid[:n].tolist()], dtype=int)
            for c in range(4):
                samples[c].extend(r[cls == c].tolist())
            next_sample[0] += dt_sample
        prev[0] = set(P.gid[: P.n_owned].tolist())

    t0 = time.perf_counter()
    feed(ow)
    prev[0] = set(ow.dem.particles.gid[: ow.dem.particles.n_owned].tolist())
    tau_min = rho.min() * d.min() ** 2 / (18 * MU)
    ow.advance(t_end, min(tau_min / 20, 2e-4), after_window)
    wall = time.perf_counter() - t0
    return {
        "model": model,
        "wall_s": wall,
        "fed": n_feed.tolist(),
        "drained": drained.tolist(),
        "samples": [np.array(s) for s in samples],
        "max_overlap": float(dem.max_overlap),
        "dem_steps": int(dem.steps),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--full", action="store_true", help="the paper's durations (several minutes)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "out"),
                    help="folder for the PNG figures and results.json (default: out/ beside this script)")  # fmt: skip
    args = ap.parse_args(argv)
    if MPI.COMM_WORLD.size > 1:
        sys.exit("scg_demo.py runs on one process (the one-way driver is serial): start it without mpirun")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}

    # 1. uniform flow, Table 1: tau_O = rho d^2 / (18 mu) = 3.09 s
    d0, rho0 = 1e-3, 1000.0
    tau = rho0 * d0**2 / (18 * MU)
    flow = make_prescribed_gas("uniform", RHO_G, MU, velocity=(1.0, 0.0, 0.0))
    pos = np.array([[0.0, 0.02 * k, 0.0] for k in range(4)])
    res = single_particles(flow, d0, rho0, pos, 3 * tau, tau / 50)
    plot_speeds(res, "uniform flow (Table 1)", "m/s", 1.0, out / "fig3_uniform_speed.png",
                [f"{d0 * r * 1e3:g} mm" for r in RATIOS])  # fmt: skip
    t, s = res[True]
    results["uniform"] = {
        "spread_with_scg": spread(s),
        "spread_without": spread(res[False][1]),
        "speed_at_3tau_with": s[-1].tolist(),
        "speed_at_3tau_without": res[False][1][-1].tolist(),
        "analytic_at_3tau": 1 - math.exp(-3.0),
    }

    # 2. vortex flow, Table 2: 300 rpm, inflow 10 %, vessel radius 0.5 mm; tau_O = 0.31 ms
    d0 = 10e-6
    tau = rho0 * d0**2 / (18 * MU)
    flow = make_prescribed_gas("vortex", RHO_G, MU, rpm=300.0, inflow_ratio=0.1)
    pos = np.array([[0.4e-3, 0.0, 0.2e-3 * (k + 1)] for k in range(4)])
    t_v = 3.0 if args.full else 0.5
    res = single_particles(flow, d0, rho0, pos, t_v, tau / 5, walls=cylinder_walls(0.5e-3), stiffness=1e-3)
    plot_speeds(res, "vortex flow (Table 2)", "mm/s", 1e3, out / "fig6_vortex_speed.png",
                [f"{d0 * r * 1e6:g} um" for r in RATIOS])  # fmt: skip
    results["vortex"] = {
        "t_end": t_v,
        "spread_with_scg": spread(res[True][1]),
        "spread_without": spread(res[False][1]),
        "speed_end_with_mm_s": (res[True][1][-1] * 1e3).tolist(),
        "speed_end_without_mm_s": (res[False][1][-1] * 1e3).tolist(),
    }

    # 3. classifier, Table 3
    t_end, t_sample, n_big, stiffness = (0.3, 0.2, 64, 10.0) if args.full else (0.15, 0.1, 16, 0.1)
    runs = {m: classifier(m, t_end, t_sample, n_big, stiffness) for m in ("original", "scg", "plain")}
    bins = np.linspace(0.0, R, 26)
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.6), sharey=True)
    hist = {}
    for c in range(4):
        ax = axes[c]
        for m, style in (("original", "-k"), ("scg", "--C0"), ("plain", ":C3")):
            smp = runs[m]["samples"][c]
            h, _ = np.histogram(smp, bins=bins)
            h = h / max(1, h.sum())
            hist[(m, c)] = h
            ax.plot(0.5 * (bins[1:] + bins[:-1]) * 1e3, h, style, lw=2, drawstyle="steps-mid",
                    label={"original": "original", "scg": "CG with SCG", "plain": "CG without SCG"}[m])  # fmt: skip
        ax.set_title(f"{D_ORIG[c] * 1e6:.0f} um original / {2 * D_ORIG[c] * 1e6:.0f} um CG")
        ax.set_xlabel("radial distance (mm)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("number fraction")
    axes[-1].legend()
    fig.tight_layout()
    fig.savefig(out / "fig10_classifier_radial.png", dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(4.5, 3.5))
    w0 = runs["original"]["wall_s"]
    ax.bar(["original", "CG with SCG", "CG without SCG"], [runs[m]["wall_s"] / w0 for m in runs], color="0.5")
    ax.set_ylabel("run time / original")
    ax.set_title(f"classifier, {t_end:g} s simulated")
    fig.tight_layout()
    fig.savefig(out / "fig8_runtime.png", dpi=110)
    plt.close(fig)
    l1 = {m: [float(np.abs(hist[(m, c)] - hist[("original", c)]).sum()) for c in range(4)] for m in ("scg", "plain")}
    mean_r = {m: [float(np.mean(runs[m]["samples"][c]) * 1e3) if runs[m]["samples"][c].size else float("nan")
                  for c in range(4)] for m in runs}  # fmt: skip
    results["classifier"] = {
        "t_end": t_end,
        "t_sample": t_sample,
        "runs": {m: {k: v for k, v in r.items() if k != "samples"} for m, r in runs.items()},
        "runtime_ratio": {m: runs[m]["wall_s"] / w0 for m in runs},
        "drained_fraction": {
            m: [dr / f for dr, f in zip(runs[m]["drained"], runs[m]["fed"], strict=True)] for m in runs
        },  # fmt: skip
        "mean_radius_mm": mean_r,
        "histogram_L1_vs_original": l1,
    }
    with open(out / "results.json", "w") as f:
        json.dump(results, f, indent=1)
    print(json.dumps(results, indent=1))

    # ## Checks
    assert results["uniform"]["spread_with_scg"] < 1e-8 < 0.1 < results["uniform"]["spread_without"]
    assert abs(results["uniform"]["speed_at_3tau_with"][0] - (1 - math.exp(-3.0))) < 1e-9
    assert results["vortex"]["spread_with_scg"] < 1e-8 < 0.1 < results["vortex"]["spread_without"]
    # the SCG distributions are closer to the originals' than those of the enlarged particles without the rule
    assert sum(l1["scg"]) < sum(l1["plain"])
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
