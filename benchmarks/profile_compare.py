"""Where a parallel run loses its efficiency: a P-rank profile set against the serial one, function by function.

Reads the cProfile files of `scaling_measure.py --profile` for the same window serially and on P ranks and
prints, for the functions with the largest excess, the serial seconds, each rank's seconds and the excess
max_r(t_r) - t_serial / P: the part of a function's time that does not divide by the ranks (work done on
every rank whole, communication, waiting for the other rank). Own time (`tottime`) by default, inclusive time
(`cumtime`) with `--cumulative`:

    python benchmarks/profile_compare.py benchmarks/out/profile_C2_P1_r0.pstats \\
        benchmarks/out/profile_C2_P2_r0.pstats benchmarks/out/profile_C2_P2_r1.pstats [--top 30]
"""

from __future__ import annotations

import argparse
import pstats
from pathlib import Path


def seconds(path: Path, cumulative: bool) -> dict[str, float]:
    """Seconds per function (file:line(name)) of one profile file."""
    stats = pstats.Stats(str(path)).stats
    k = 3 if cumulative else 2  # (calls, primitive calls, tottime, cumtime, callers)
    return {f"{Path(f).name}:{line}({name})": v[k] for (f, line, name), v in stats.items()}


def excess(serial: dict[str, float], ranks: list[dict[str, float]]) -> list[tuple[str, float, list[float], float]]:
    """(function, serial seconds, seconds per rank, max over ranks - serial / P), largest excess first."""
    P = len(ranks)
    names = set(serial).union(*ranks)
    rows = []
    for name in names:
        t1 = serial.get(name, 0.0)
        tr = [r.get(name, 0.0) for r in ranks]
        rows.append((name, t1, tr, max(tr) - t1 / P))
    return sorted(rows, key=lambda r: -r[3])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("serial", type=Path, help="profile of the serial window")
    parser.add_argument("ranks", type=Path, nargs="+", help="profiles of the same window, one per rank")
    parser.add_argument("--top", type=int, default=25, help="functions to print")
    parser.add_argument("--cumulative", action="store_true", help="inclusive time instead of own time")
    args = parser.parse_args()
    for p in [args.serial, *args.ranks]:
        if not p.is_file():
            raise SystemExit(f"{p}: no such profile (write it with scaling_measure.py --profile)")
    serial = seconds(args.serial, args.cumulative)
    ranks = [seconds(p, args.cumulative) for p in args.ranks]
    rows = excess(serial, ranks)
    P = len(ranks)
    total1 = sum(serial.values()) if not args.cumulative else max(serial.values())
    totals = [sum(r.values()) if not args.cumulative else max(r.values()) for r in ranks]
    print(f"total: serial {total1:.2f} s, ranks {' '.join(f'{t:.2f}' for t in totals)} s, "
          f"efficiency {total1 / (P * max(totals)):.1%}")  # fmt: skip
    print(f"{'excess s':>9} {'serial s':>9} {'per rank s':>20}  function")
    for name, t1, tr, ex in rows[: args.top]:
        print(f"{ex:9.3f} {t1:9.3f} {' '.join(f'{t:9.3f}' for t in tr):>20}  {name}")


if __name__ == "__main__":
    main()
