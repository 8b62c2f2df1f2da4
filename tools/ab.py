"""A benchmark at two commits, back to back on one core: the ratio a speed claim needs.

    python tools/ab.py OLD [--new REV] [--rounds 3] [--cpu 1] [--metric REGEX] -- COMMAND ...

Checks OLD (and NEW, by default the working tree as it is) out into temporary git worktrees, then runs
COMMAND in each tree in turn, `--rounds` times, pinned to one core (`taskset`), each tree with its own Numba
cache, after one uncounted warm-up run per tree (it compiles the kernels). COMMAND runs from the tree's root
with that tree's `febed` first on the Python path, so `benchmarks/dem_settle.py` is each commit's own script
(a relative interpreter such as `.venv/bin/python` is the repository's, in every tree).
From each run's output the first group of `--metric` (default: the number in `DEM: X us per particle-step`)
is taken; the tool prints every round, the medians and new/old per round and of the medians. A benchmark's
data cache (`benchmarks/out`) is shared with the worktrees, so a packed bed is made once.

Run it from the repository (the git work tree whose commits are compared). Example, the DEM benchmark:

    python tools/ab.py HEAD~1 -- .venv/bin/python benchmarks/dem_settle.py --steps 2000
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

DEFAULT_METRIC = r"DEM: ([0-9.eE+-]+) us per particle-step"


def git(*args: str, cwd: Path | None = None) -> str:
    """The output of a git command (exit with its message if it fails)."""
    done = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"ab: git {' '.join(args)}: {done.stderr.strip()}")
    return done.stdout.strip()


def add_tree(root: Path, rev: str, where: Path) -> Path:
    """A detached worktree of `rev` at `where`, sharing `root`'s benchmark data cache."""
    git("worktree", "add", "--detach", "--force", str(where), rev, cwd=root)
    out = root / "benchmarks" / "out"
    if out.is_dir() and (where / "benchmarks").is_dir() and not (where / "benchmarks" / "out").exists():
        (where / "benchmarks" / "out").symlink_to(out)
    return where


def run(tree: Path, command: list[str], cache: Path, cpu: int | None, metric: re.Pattern) -> float:
    """One run of `command` in `tree`; the metric it printed."""
    path = os.pathsep.join([str(tree), os.environ.get("PYTHONPATH", "")])
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=path)
    pin = ["taskset", "-c", str(cpu)] if cpu is not None and shutil.which("taskset") else []
    done = subprocess.run([*pin, *command], cwd=tree, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"ab: {' '.join(command)} failed in {tree} (exit {done.returncode}):\n{done.stderr[-2000:]}")
    found = metric.search(done.stdout)
    if found is None:
        raise SystemExit(f"ab: no match of --metric {metric.pattern!r} in the output of {tree}:\n{done.stdout[-2000:]}")
    return float(found.group(1))


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, run the rounds, print the ratio; the worktrees are removed whatever happens."""
    argv = sys.argv[1:] if argv is None else argv
    if "--" not in argv:
        raise SystemExit("ab: give the command after --, e.g. tools/ab.py HEAD~1 -- python benchmarks/dem_settle.py")
    cut = argv.index("--")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old", help="the commit to compare against")
    ap.add_argument("--new", default=None, help="the other commit (default: this working tree as it is)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--cpu", type=int, default=1, help="core to pin every run to (taskset); -1: no pinning")
    ap.add_argument("--metric", default=DEFAULT_METRIC, help="regular expression; its first group is the figure")
    args = ap.parse_args(argv[:cut])
    command = argv[cut + 1 :]
    if not command or args.rounds < 1:
        raise SystemExit("ab: need a command after -- and --rounds >= 1")
    metric = re.compile(args.metric)
    root = Path(git("rev-parse", "--show-toplevel"))
    if "/" in command[0] and (root / command[0]).exists():  # e.g. .venv/bin/python: the repository's own, in every tree
        command[0] = str((root / command[0]).resolve())
    cpu = None if args.cpu < 0 else args.cpu
    tmp = Path(tempfile.mkdtemp(prefix="febed-ab-"))
    trees: list[Path] = []
    try:
        old = add_tree(root, args.old, tmp / "old")
        trees.append(old)
        new = root if args.new is None else add_tree(root, args.new, tmp / "new")
        if args.new is not None:
            trees.append(new)
        sides = {"old": (old, tmp / "cache-old"), "new": (new, tmp / "cache-new")}
        short = {rev: git("rev-parse", "--short", rev, cwd=root) for rev in (args.old, args.new) if rev is not None}
        names = {"old": f"{args.old} ({short[args.old]})",
                 "new": "working tree" if args.new is None else f"{args.new} ({short[args.new]})"}  # fmt: skip
        for side, (tree, cache) in sides.items():
            print(f"warm-up {side}: {names[side]} -> {run(tree, command, cache, cpu, metric):g}", flush=True)
        values: dict[str, list[float]] = {"old": [], "new": []}
        for r in range(args.rounds):
            for side in ("old", "new") if r % 2 == 0 else ("new", "old"):  # alternate who goes first
                tree, cache = sides[side]
                values[side].append(run(tree, command, cache, cpu, metric))
            print(f"round {r + 1}: old {values['old'][-1]:g}  new {values['new'][-1]:g}  "
                  f"new/old {values['new'][-1] / values['old'][-1]:.3f}", flush=True)  # fmt: skip
        mo, mn = statistics.median(values["old"]), statistics.median(values["new"])
        print(f"old {names['old']}: median {mo:g}; new {names['new']}: median {mn:g}")
        rounds = ", ".join(f"{n / o:.3f}" for o, n in zip(values["old"], values["new"], strict=True))
        print(f"new/old: {mn / mo:.3f} (per round {rounds})")
    finally:
        for tree in trees:
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=root, capture_output=True)
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
