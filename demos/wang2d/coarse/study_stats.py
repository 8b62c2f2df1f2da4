# # The seed-000 coarse-graining study with statistics: several independently packed beds per case
#
# One run of a bubbling bed is one sample of a chaotic flow: a TM-PCPM difference means something only
# against the spread between runs that differ by nothing but their initial packing. This script runs every
# case of the study (the case files of this folder) from `--beds` beds, each packed from its own random seed
# (`run.seed`; TM and PCPM at the same l share a bed), for `--end-time` seconds, then reports per case the
# mean ± standard deviation over the beds of:
#
# - the bed height (95 % of the particles below it, `bed_height` probe) and the bed pressure drop over W/A;
# - the pressure drop between 45 mm and the outlet (seed 000 Figs 6 and 11): mean, standard deviation in time
#   and dominant frequency (the largest peak of its periodogram between 0.5 and 20 Hz);
# - the PCPM group count and crush/merge events per second (Figs 8-9), and the energy the events injected
#   over the bed's mean kinetic energy;
#
# all averaged over `--from` s to the end of each run (a run that failed, e.g. on `run.max_overlap`, up to
# 30 ms before its failure, if that leaves at least 1 s; the table says how many failed and when). It then
# states, for each l, whether PCPM and TM differ by more than their spread: |mean_PCPM - mean_TM| against
# 2 sqrt(s_PCPM² + s_TM²)/sqrt(beds).
#
# Usage: `.venv/bin/python demos/wang2d/coarse/study_stats.py [--beds 3] [--end-time 5] [--jobs 1]
# [--cases tm1 tm2 ...] [--no-run] [--out DIR]`. Runs go to `out/stats/<case>-b<k>/`, beds to
# `out/stats/beds/`, the table to `out/stats/stats.md` and `stats.csv`. Runs made to the same end time
# (finished or failed) are reused.

import argparse
import csv
import json
import math
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
FEBED = Path(sys.executable).parent / "febed"

# case: (case file, l, label); the 9,600-particle cases at 1.9 m/s are opt-in (--cases).
CASES = {
    "tm1": ("tm1.toml", 1, "TM l = 1 (DEM)"),
    "pcpm1": ("pcpm1.toml", 1, "PCPM from l = 1"),
    "tm2": ("tm2.toml", 2, "TM l = 2"),
    "pcpm2": ("pcpm2.toml", 2, "PCPM from l = 2"),
    "tm3": ("tm3.toml", 3, "TM l = 3"),
    "pcpm3": ("pcpm3.toml", 3, "PCPM from l = 3"),
    "dem9600-emms": ("dem9600-emms.toml", 9600, "9,600 at 1.9 m/s, DEM"),
    "pcpm9600": ("pcpm9600.toml", 9600, "9,600 at 1.9 m/s, PCPM from l = 1"),
}
DEFAULT = ("tm1", "pcpm1", "tm2", "pcpm2", "tm3", "pcpm3")

parser = argparse.ArgumentParser()
parser.add_argument("--beds", type=int, default=3, help="independently packed beds per case (default 3)")
parser.add_argument("--end-time", type=float, default=5.0, help="simulated seconds per run (default 5)")
parser.add_argument("--from", dest="t_from", type=float, default=1.0, help="start of the averaging (s, default 1)")
parser.add_argument("--jobs", type=int, default=1, help="runs at once (default 1)")
parser.add_argument("--cases", nargs="*", default=list(DEFAULT), choices=list(CASES), metavar="CASE",
                    help=f"cases to run and report (default: {' '.join(DEFAULT)})")  # fmt: skip
parser.add_argument("--no-run", action="store_true", help="only report the finished runs")
parser.add_argument("--out", default=str(HERE / "out" / "stats"), help="folder of the runs and tables")
args = parser.parse_args()
if args.beds < 1 or args.end_time <= args.t_from:
    sys.exit("study_stats.py: need --beds >= 1 and --end-time > --from")
OUT = Path(args.out)
(OUT / "beds").mkdir(parents=True, exist_ok=True)
SEEDS = [1000 + k for k in range(args.beds)]  # bed k is packed from run.seed = 1000 + k


def run_dir(case: str, k: int) -> Path:
    return OUT / f"{case}-b{k}"


def status(case: str, k: int) -> dict:
    """The run's status.json ({} if there is none)."""
    try:
        return json.loads((run_dir(case, k) / "status.json").read_text())
    except (OSError, ValueError):
        return {}


def attempted(case: str, k: int) -> bool:
    """True if the run was made to this end time: it finished, or it failed (a rerun would fail the same way)."""
    info = status(case, k)
    return info.get("state") in ("finished", "failed") and math.isclose(info.get("end_time", -1), args.end_time)


def bed_file(case: str, k: int) -> Path:
    """The packed bed of case `case`, bed k: shared by TM and PCPM at the same l (and by the two 9,600 cases)."""
    return OUT / "beds" / f"bed-l{CASES[case][1]}-s{SEEDS[k]}.npz"


def run(case: str, k: int) -> None:
    """Run `case` from bed k into its folder (its bed packed first if missing); skipped if finished."""
    if attempted(case, k):
        return
    d = run_dir(case, k)
    cmd = [str(FEBED), "run", str(HERE / CASES[case][0]), "--overwrite", "--set", f"output.directory={d}",
           "--set", f"run.end_time={args.end_time}", "--set", f"run.seed={SEEDS[k]}",
           "--set", f"particles.bed_file={bed_file(case, k)}", "--set", "output.field_interval=0.5",
           "--set", "output.particle_interval=0.5"]  # fmt: skip
    t0 = time.time()
    with open(OUT / f"{case}-b{k}.stderr", "w") as err:
        rc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=err).returncode
    print(f"{case}-b{k}: exit {rc} after {time.time() - t0:.0f} s", flush=True)


if not args.no_run:
    # the first run of each bed packs it: run bed by bed so that two jobs never pack the same bed at once
    todo = [(c, k) for k in range(args.beds) for c in args.cases]
    first = {}
    for c, k in todo:
        first.setdefault(bed_file(c, k), (c, k))
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        list(pool.map(lambda ck: run(*ck), list(first.values())))
        list(pool.map(lambda ck: run(*ck), [ck for ck in todo if ck not in first.values()]))


# ## Statistics of one run


def read_probes(path: Path) -> dict:
    """Columns of a probes.csv as float arrays (a line being written is skipped)."""
    with open(path) as f:
        rows = list(csv.reader(f))
    head = rows[0]
    data = np.array([r for r in rows[1:] if len(r) == len(head) and all(r)], dtype=float)
    return {h: data[:, i] for i, h in enumerate(head)}


def dominant_frequency(t: np.ndarray, x: np.ndarray, lo: float = 0.5, hi: float = 20.0) -> float:
    """Frequency (Hz) of the largest periodogram peak of x(t) between lo and hi (Hann window, mean removed)."""
    dt = float(np.median(np.diff(t)))
    grid = np.arange(t[0], t[-1], dt)
    y = np.interp(grid, t, x)
    y = (y - y.mean()) * np.hanning(len(y))
    f = np.fft.rfftfreq(len(y), dt)
    p = np.abs(np.fft.rfft(y)) ** 2
    band = (f >= lo) & (f <= hi)
    return float(f[band][np.argmax(p[band])]) if band.any() else math.nan


D, RHO, G, WIDTH = 1.5e-3, 1150.0, 9.81, 0.09  # the seed-000 bed (../wang2d.toml)
M_O = RHO * math.pi / 6 * D**3


def run_stats(case: str, k: int) -> dict | None:
    """Statistics of run (case, bed k) over [--from, end]; a run that failed (e.g. an overlap above
    `run.max_overlap`) over [--from, its failure - 30 ms] if that is at least 1 s long, else None."""
    d = run_dir(case, k)
    if not attempted(case, k):
        return None
    pr = read_probes(d / "probes.csv")
    t = pr["time"]
    failed = status(case, k)["state"] == "failed"
    if failed:
        if t[-1] - 0.03 < args.t_from + 1.0:
            return None
        pr = {key: v[t <= t[-1] - 0.03] for key, v in pr.items()}
        t = pr["time"]
    w = t >= args.t_from
    ratio = CASES[case][1] if CASES[case][1] < 100 else 1
    n_orig = pr["originals"][0] if "originals" in pr else pr["particles"][0] * ratio**3
    wa = n_orig * M_O * G / (WIDTH * ratio * D)  # W/A: a 2D case's depth is one inserted particle's diameter
    dp45 = pr["p_0.045"] - pr["p_top"]
    span = t[w][-1] - t[w][0]
    out = {
        "bed_height_mm": 1e3 * pr["bed_height"][w].mean(),
        "dp_bed_over_W": pr["dp_bed"][w].mean() / wa,
        "dp45_over_W": dp45[w].mean() / wa,
        "dp45_std_over_W": dp45[w].std() / wa,
        "dp45_freq_Hz": dominant_frequency(t[w], dp45[w]),
        "lost_percent": 100.0 * pr["left_outlet"][-1] / pr["particles"][0],
        "wall_per_sim_s": sum(pr[f"wall_{p}"][-1] for p in ("dem", "coupling", "gas", "output")) / t[-1],
        "t_end_s": t[-1],
        "failed": float(failed),
    }
    if "groups" in pr:
        i0 = int(np.argmax(w))
        out["groups_mean"] = pr["groups"][w].mean()
        out["crushes_per_s"] = (pr["crushed"][-1] - pr["crushed"][i0]) / span
        out["merges_per_s"] = (pr["merged"][-1] - pr["merged"][i0]) / span
        out["event_energy_over_ke"] = (pr["event_energy"][-1] - pr["event_energy"][i0]) / pr["kinetic_energy"][w].mean()
    return out


# ## Mean ± spread over the beds, and TM against PCPM

KEYS = ("bed_height_mm", "dp_bed_over_W", "dp45_over_W", "dp45_std_over_W", "dp45_freq_Hz", "lost_percent",
        "groups_mean", "crushes_per_s", "merges_per_s", "event_energy_over_ke", "wall_per_sim_s")  # fmt: skip
table = {}
for c in args.cases:
    samples = [s for k in range(args.beds) if (s := run_stats(c, k)) is not None]
    if not samples:
        continue
    table[c] = {"beds": len(samples), "failed": int(sum(x["failed"] for x in samples)),
                "t_min": min(x["t_end_s"] for x in samples)}  # fmt: skip
    for key in KEYS:
        v = np.array([s[key] for s in samples if key in s])
        if v.size:
            table[c][key] = (float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else math.nan)
if not table:
    sys.exit("no finished runs to report")

with open(OUT / "stats.csv", "w", newline="") as f:
    wr = csv.writer(f)
    wr.writerow(["case", "beds"] + [f"{k}_{s}" for k in KEYS for s in ("mean", "std")])
    for c, r in table.items():
        wr.writerow([c, r["beds"]] + [x for k in KEYS for x in r.get(k, (math.nan, math.nan))])


def fmt(r: dict, key: str, digits: int) -> str:
    if key not in r:
        return "–"
    m, s = r[key]
    return f"{m:.{digits}f}" + ("" if math.isnan(s) else f" ± {s:.{digits}f}")


COLS = (("bed height [mm]", "bed_height_mm", 1), ("Δp bed / W", "dp_bed_over_W", 3), ("Δp45 / W", "dp45_over_W", 3),
        ("std Δp45 / W", "dp45_std_over_W", 3), ("Δp45 peak [Hz]", "dp45_freq_Hz", 2),
        ("groups", "groups_mean", 0), ("crushes /s", "crushes_per_s", 0), ("merges /s", "merges_per_s", 0),
        ("event energy / KE", "event_energy_over_ke", 4), ("lost [%]", "lost_percent", 2),
        ("wall s / sim s", "wall_per_sim_s", 0))  # fmt: skip
lines = [f"Mean ± standard deviation over the beds, each averaged over {args.t_from:g}-{args.end_time:g} s "
         "(a run that failed: up to 30 ms before its failure; beds: how many, and how many failed, and when).", "",
         "| case | beds | " + " | ".join(c[0] for c in COLS) + " |", "|---|---|" + "---|" * len(COLS)]  # fmt: skip
for c, r in table.items():
    beds = f"{r['beds']}" + (f" ({r['failed']} to ≥ {r['t_min']:.2f} s)" if r["failed"] else "")
    lines.append(f"| {CASES[c][2]} | {beds} | " + " | ".join(fmt(r, k, n) for _, k, n in COLS) + " |")
lines += ["", "PCPM against TM at the same l: difference of the means over twice its standard error "
          "(above 1: the difference stands out of the spread between beds).", "",
          "| l | " + " | ".join(c[0] for c in COLS[:5]) + " |", "|---|" + "---|" * 5]  # fmt: skip
for lev in (1, 2, 3):
    a, b = table.get(f"pcpm{lev}"), table.get(f"tm{lev}")
    if not (a and b) or min(a["beds"], b["beds"]) < 2:
        continue
    cells = []
    for _, key, n in COLS[:5]:
        (ma, sa), (mb, sb) = a[key], b[key]
        se = math.sqrt(sa**2 / a["beds"] + sb**2 / b["beds"])
        cells.append(f"{ma - mb:+.{n}f} ({abs(ma - mb) / (2 * se):.1f})" if se > 0 else f"{ma - mb:+.{n}f}")
    lines.append(f"| {lev} | " + " | ".join(cells) + " |")
(OUT / "stats.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
print(f"table in {OUT / 'stats.md'} and {OUT / 'stats.csv'}")
