"""The loops of pseudo-2D runs over consecutive windows, on one figure: when does each bed settle, and how far apart?

    python demos/pseudo2d/loops_in_time.py RUN_DIR [RUN_DIR ...] [--labels A B ...] [--from T0 [T0 ...]]
        [--split DT] [-o FIGURE.png]

For each run folder, the bed-averaged vertical solid flux of the central third and of the outer 15 % over
consecutive windows of DT s (default 1 s) from T0 (one for every run, or one per run) to the end of its
output (`febed.post.windows`, what `febed post RUN_DIR --window T0 T1 --split DT` gives), drawn against time,
one colour per run; also the bubble fraction. Prints each run's windows. A run continued from another run's
checkpoint in a copy of its folder holds the other run's times too: give it its own T0.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from febed.post.rundata import list_snapshots
from febed.post.windows import split_window


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, metavar="RUN_DIR")
    ap.add_argument("--labels", nargs="+", help="one name per run (default the folder names)")
    ap.add_argument("--from", dest="t0", type=float, nargs="+", default=[1.0],
                    help="first window's start [s]: one for every run or one per run (default 1)")  # fmt: skip
    ap.add_argument("--split", type=float, default=1.0, help="window length [s] (default 1)")
    ap.add_argument("-o", "--output", type=Path, default=Path("loops_in_time.png"), help="the figure (PNG)")
    args = ap.parse_args()
    labels = args.labels or [r.name for r in args.runs]
    if len(labels) != len(args.runs):
        ap.error(f"{len(labels)} label(s) for {len(args.runs)} run folder(s)")
    starts = args.t0 * len(args.runs) if len(args.t0) == 1 else args.t0
    if len(starts) != len(args.runs):
        ap.error(f"--from: {len(args.t0)} start(s) for {len(args.runs)} run folder(s)")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(8.0, 5.6), sharex=True)
    for k, (run, label, start) in enumerate(zip(args.runs, labels, starts, strict=True)):
        snaps = list_snapshots(run)
        t0 = max(start, snaps[0][0])
        if snaps[-1][0] - t0 < args.split:
            end, dt = snaps[-1][0], args.split
            print(f"{label}: its output from {t0:g} s ends at {end:g} s, short of one {dt:g} s window; left out")
            continue
        rows = split_window(run, (t0, snaps[-1][0]), args.split)
        print(f"{label}:")
        for r in rows:
            print(
                f"  {r['window_t0']:6.2f}-{r['window_t1']:<6.2f} s  centre {r['bed_flux_centre/rhoUf']:+6.1f}  "
                f"walls {r['bed_flux_walls/rhoUf']:+6.1f}  dp/W {r['dp_bed_over_weight']:.3f}  "
                f"bubbles {r['bubble_fraction']:.3f}"
            )
        edges = [r["window_t0"] for r in rows] + [rows[-1]["window_t1"]]
        colour = f"C{k}"
        for key, style in (("bed_flux_centre/rhoUf", "-"), ("bed_flux_walls/rhoUf", "--")):
            values = [r[key] for r in rows]
            axes[0].step(edges, values + values[-1:], where="post", color=colour, ls=style,
                         label=label if style == "-" else None)  # fmt: skip
        values = [r["bubble_fraction"] for r in rows]
        axes[1].step(edges, values + values[-1:], where="post", color=colour, label=label)
    axes[0].axhline(0.0, color="k", lw=0.6)
    axes[0].set_ylabel(r"bed solid flux / $\rho U_f$" + "\ncentre (solid), outer 15 % (dashed)", fontsize=9)
    axes[0].legend(fontsize=8)
    axes[1].set_ylabel("bubble fraction", fontsize=9)
    axes[1].set_xlabel("t [s]")
    fig.suptitle(f"means over windows of {args.split:g} s", fontsize=9)
    fig.tight_layout()
    fig.savefig(args.output, dpi=110)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
