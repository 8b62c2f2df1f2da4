"""Command-line parts of `febed post`, `febed study` and `febed compare`, wired into `febed` by febed/cli.py.

    febed post RUN_DIR [--window T0 T1] [--bins NX NZ] [--kernel ngp|cic] [--agitation cell|window]
                       [--heights H ...] [--split DT] [--no-figures] [-o OUT]
    febed study STUDY.toml [--list | --jobs FILE] [--collect-only] [--retry-failed] [--no-fields]
    febed compare RUN_DIR RUN_DIR ... [--labels A B ...] [--window T0 T1 [--window T0 T1 ...]] [-o OUT]

The same commands without the `febed` front end: `python -m febed.post RUN_DIR ...`,
`python -m febed.post study STUDY.toml ...` and `python -m febed.post compare RUN_DIR ...`.
Bad input raises ValueError (printed by febed/cli.py).
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from febed.post.collect import compare_runs
from febed.post.grid import BUBBLE_ALPHA
from febed.post.report import post_run
from febed.post.windows import check_width, split_window, spread, standard_errors, window_edges, write_windows
from febed.study import collect, job_lines, load_study, member_states, resume_flags, run_study


def add_post_parser(subparsers) -> argparse.ArgumentParser:
    """Add the `post` sub-command to an argparse subparsers object; returns its parser."""
    p = subparsers.add_parser(
        "post",
        help="time-averaged particle fields, profiles and probe series of a run (CSV + PNG in RUN_DIR/post)",
    )
    p.add_argument("run_dir", help="a run's output folder (finished or still running)")
    p.add_argument(
        "--window", type=float, nargs=2, metavar=("T0", "T1"), help="averaging window [s]; default the last half"
    )
    p.add_argument(
        "--bins", type=int, nargs=2, metavar=("NX", "NZ"), help="plane bins; default the built-in mesh's cells"
    )
    p.add_argument("--kernel", choices=("ngp", "cic"), default="ngp", help="particle -> bin kernel (default ngp)")
    p.add_argument(
        "--agitation",
        choices=("cell", "window"),
        default="cell",
        help="q_p^2 about the bin's instantaneous mean velocity (cell, seed 001) or its time mean (window)",
    )
    p.add_argument(
        "--heights", type=float, nargs="+", default=[0.092], metavar="Z/H", help="profile heights z/H (0.092)"
    )
    p.add_argument(
        "--bubble-alpha",
        type=float,
        default=BUBBLE_ALPHA,
        metavar="A",
        help=f"a bin whose instantaneous solid fraction is below A is bubble (default {BUBBLE_ALPHA})",
    )
    p.add_argument(
        "--depth-height",
        type=float,
        default=0.16,
        metavar="Z/H",
        help="height of the particle velocity profile across the depth (3D runs; 0.16, seed 001 Fig 11)",
    )
    p.add_argument(
        "--depth-bins", type=int, metavar="N", help="bins across the depth (default the built-in mesh's cells)"
    )
    p.add_argument(
        "--split",
        type=float,
        metavar="DT",
        help="also the means over consecutive windows of DT s inside the averaging window (windows.csv, "
        "windows.png): whether the bed is steady and how much the means of windows that long vary",
    )
    p.add_argument("--no-figures", action="store_true", help="CSV tables only")
    p.add_argument("-o", "--output", help="output folder (default RUN_DIR/post)")
    return p


def cmd_post(args) -> int:
    """Run `febed post` with parsed arguments; prints what it wrote and the main numbers."""
    from mpi4py import MPI

    if MPI.COMM_WORLD.rank != 0:  # started under mpirun: one process does the work
        return 0
    run_dir = Path(args.run_dir)
    if not run_dir.is_dir():
        raise ValueError(f"RUN_DIR {run_dir} is not a folder")
    if args.split is not None and args.window:  # a bad --split fails before the averaging, not after it
        window_edges(*args.window, args.split)
    elif args.split is not None:
        check_width(args.split)
    res = post_run(
        run_dir,
        window=tuple(args.window) if args.window else None,
        bins=tuple(args.bins) if args.bins else None,
        kernel=args.kernel,
        agitation=args.agitation,
        heights=tuple(args.heights),
        figures=not args.no_figures,
        out=args.output,
        bubble_alpha=args.bubble_alpha,
        depth_height=args.depth_height,
        depth_bins=args.depth_bins,
    )
    v = res.values
    print(
        f"{run_dir}: window {v['window_t0']:g}..{v['window_t1']:g} s, {v['snapshots']} particle snapshots, "
        f"{v['probe_rows']} probe rows; mean dp_bed = {v['dp_bed_mean']:.1f} Pa "
        f"({v['dp_bed_over_weight']:.3f} x bed weight/area), bed height {1e3 * v['bed_height_mean']:.1f} mm"
    )
    if "bed_flux_centre/rhoUf" in v:
        print(
            f"  bed-averaged vertical solid flux / rho U_f: centre {v['bed_flux_centre/rhoUf']:+.1f}, "
            f"walls {v['bed_flux_walls/rhoUf']:+.1f}; bubble fraction {v['bubble_fraction']:.3f}; "
            f"q_p^2/U_f^2 in the bed {v['q2_bed/Uf2']:.4f}"
        )
        print(f"  the bottom wall carries {v['bottom_support/W']:.3f} of the bed weight by contact")
    key = f"depth_zH{args.depth_height:g}_spread_all/Uf"
    if key in v:
        print(
            f"  across the depth at z/H = {args.depth_height:g}, U_p,z varies by {v[key]:.3f} U_f over the whole "
            f"width and {v[key.replace('_all', '_walls')]:.3f} U_f at the side walls (max - min; ~0: two-dimensional); "
            f"solid (front - back)/(front + back) {v[key.replace('spread_all/Uf', 'front_back_asymmetry')]:+.3f}"
        )
    files = list(res.files)
    if args.split is not None:
        files += _post_windows(run_dir, args, (v["window_t0"], v["window_t1"]))
    for f in files:
        print(f"  wrote {f}")
    return 0


def _post_windows(run_dir: Path, args, window: tuple[float, float]) -> list[Path]:
    """`febed post --split DT`: the means of consecutive windows, their spread printed; the files written."""
    rows = split_window(
        run_dir, window, args.split, bins=tuple(args.bins) if args.bins else None, kernel=args.kernel,
        agitation=args.agitation, bubble_alpha=args.bubble_alpha,
    )  # fmt: skip
    print(
        f"  {len(rows)} windows of {args.split:g} s from {window[0]:g} s (mean +- standard deviation, range;"
        " standard error of the whole window's mean, lag-1 correlation of the windows):"
    )
    for key, name, fmt in (
        ("bed_flux_centre/rhoUf", "bed solid flux / rho U_f, central third", "+.1f"),
        ("bed_flux_walls/rhoUf", "bed solid flux / rho U_f, outer 15 %", "+.1f"),
        ("dp_bed_over_weight", "dp_bed / W", ".3f"),
        ("bubble_fraction", "bubble fraction", ".3f"),
    ):
        s = spread(rows, key)
        print(
            f"    {name}: {s['mean']:{fmt}} +- {s['std']:.3g} ({s['min']:{fmt}} to {s['max']:{fmt}});"
            f" standard error {s['sem']:.2g}, r1 {s['r1']:+.2f}"
        )
    out = Path(args.output) if args.output else run_dir / "post"
    title = f"{run_dir.name}: means over windows of {args.split:g} s"
    return write_windows(rows, out, figures=not args.no_figures, title=title)


def add_study_parser(subparsers) -> argparse.ArgumentParser:
    """Add the `study` sub-command to an argparse subparsers object; returns its parser."""
    p = subparsers.add_parser(
        "study", help="run a family of cases varying named parameters, resume it, compare the results"
    )
    p.add_argument("study", help="study TOML file ([study] base = CASE.toml, [parameters] key = [values])")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--list", action="store_true", help="print each member's state and command line, run nothing")
    g.add_argument(
        "--jobs",
        metavar="FILE",
        help="write the (mpirun) command lines of the unfinished members to FILE (one per line), run nothing",
    )
    g.add_argument("--collect-only", action="store_true", help="only compare the existing results")
    p.add_argument("--retry-failed", action="store_true", help="re-run failed members from scratch")
    p.add_argument("--no-fields", action="store_true", help="compare probe series only (no particle averages)")
    return p


def cmd_study(args) -> int:
    """Run `febed study` with parsed arguments; 0 if every member finished, 1 otherwise."""
    study = load_study(args.study)
    if args.list:
        for m, state in member_states(study):
            restart, overwrite = resume_flags(m, state)
            cmd = shlex.join(m.command(study, restart=restart, overwrite=overwrite))
            print(f"{m.name:30s} {state:12s} {cmd}")  # copy-pasteable
        return 0
    if args.jobs:
        lines = job_lines(study, retry_failed=args.retry_failed)
        Path(args.jobs).write_text("".join(line + "\n" for line in lines))
        print(f"wrote {len(lines)} command line(s) to {args.jobs}")
        return 0
    ok = True
    if not args.collect_only:
        ok = run_study(study, retry_failed=args.retry_failed)
    table = collect(study, fields=not args.no_fields)
    print(f"comparison of {len(table.rows)} member(s): {table.csv}")
    for f in table.figures:
        print(f"  wrote {f}")
    return 0 if ok else 1


def add_compare_parser(subparsers) -> argparse.ArgumentParser:
    """Add the `compare` sub-command to an argparse subparsers object; returns its parser."""
    p = subparsers.add_parser(
        "compare",
        help="one table and figures comparing run folders made separately (a mesh or parameter sweep by hand)",
    )
    p.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="output folders of febed runs")
    p.add_argument("--labels", nargs="+", metavar="NAME", help="a name per run (default the folder names)")
    p.add_argument(
        "--window",
        type=float,
        nargs=2,
        action="append",
        metavar=("T0", "T1"),
        help="averaging window [s]: once for every run, or once per run in order; default the last half of each",
    )
    p.add_argument("--height", type=float, default=0.092, metavar="Z/H", help="profile height z/H (0.092)")
    p.add_argument("--no-fields", action="store_true", help="probe series only (no particle averages)")
    p.add_argument(
        "--split",
        type=float,
        metavar="DT",
        help="also the standard error of each run's means, from its consecutive windows of DT s (columns KEY_se)",
    )
    p.add_argument("-o", "--output", default="comparison", help="output folder (default ./comparison)")
    return p


def cmd_compare(args) -> int:
    """Run `febed compare` with parsed arguments; prints the table's main columns and the files written."""
    from mpi4py import MPI

    if MPI.COMM_WORLD.rank != 0:
        return 0
    extra = None
    if args.split is not None:  # each run's standard errors from its windows of DT s
        check_width(args.split)
        if args.no_fields:
            raise ValueError("split: the standard errors need the particle averages; leave out --no-fields")

        def extra(run_dir, window):
            return standard_errors(run_dir, window, args.split)

    table = compare_runs(
        args.run_dirs,
        labels=args.labels,
        windows=[tuple(w) for w in args.window] if args.window else None,
        fields=not args.no_fields,
        height=args.height,
        out=args.output,
        extra=extra,
    )
    print(f"{'run':24s} {'window [s]':>13s} {'dp/W':>6s} {'bed [mm]':>8s} {'centre':>7s} {'walls':>7s} {'bubbles':>7s}")
    for r in table.rows:
        print(
            f"{r['run']:24s} {r['window_t0']:6.3g}-{r['window_t1']:<6.3g} {r['dp_bed_over_weight']:6.3f} "
            f"{1e3 * r['bed_height_mean']:8.1f} {r['bed_flux_centre/rhoUf']:+7.1f} {r['bed_flux_walls/rhoUf']:+7.1f} "
            f"{r['bubble_fraction']:7.3f}"
        )
        if args.split is not None:
            print(
                f"{'  standard error':24s} {'':13s} {r['dp_bed_over_weight_se']:6.3f} "
                f"{1e3 * r['bed_height_mean_se']:8.1f} {r['bed_flux_centre/rhoUf_se']:7.1f} "
                f"{r['bed_flux_walls/rhoUf_se']:7.1f} {r['bubble_fraction_se']:7.3f}"
            )
    print(f"wrote {table.csv}")
    for f in table.figures:
        print(f"  wrote {f}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """`python -m febed.post`: `RUN_DIR [options]`, `study STUDY.toml [options]` or `compare RUN_DIR ...`."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="python -m febed.post")
    sub = parser.add_subparsers(dest="command", required=True)
    add_post_parser(sub)
    add_study_parser(sub)
    add_compare_parser(sub)
    if not argv or argv[0] not in ("post", "study", "compare", "-h", "--help"):
        argv = ["post", *argv]
    args = parser.parse_args(argv)
    try:
        return {"post": cmd_post, "study": cmd_study, "compare": cmd_compare}[args.command](args)
    except ValueError as e:
        print(f"febed {args.command}: error: {e}", file=sys.stderr)
        return 2
