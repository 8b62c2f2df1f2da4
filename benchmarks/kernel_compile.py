"""Numba compile time per kernel from an empty cache: what a fresh clone's first run (and `make test`) pays.

Runs small cases through `febed run` in this process with the Numba cache pointed at a new temporary folder
and prints `tools/compile_times.py`'s table (which does the same over a pytest run): per kernel, its
signatures and its compile seconds with and without the kernels it compiled on the way, then the total.
Cases (each a fraction of a second of simulated time):

* `wang2d`: the seed-000 bed (DEM with the `linear-history` law and RK2, gas, coupling, Gidaspow blend);
* `verlet`: the same with velocity Verlet and the `linear` law;
* `pcpm`: the seed-000 study's PCPM bed from l = 2 (`demos/wang2d/coarse/pcpm2.toml`), past its first events.

    .venv/bin/python benchmarks/kernel_compile.py [--cases wang2d verlet pcpm] [--top 30]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def case_args(name: str, work: Path) -> list[str]:
    """`febed run` arguments of the named case, writing into `work`."""
    wang2d = str(ROOT / "demos" / "wang2d" / "wang2d.toml")
    out = f"output.directory={work / name}"
    if name == "wang2d":
        return ["run", wang2d, "--set", out, "--set", "run.end_time=0.002"]
    if name == "verlet":
        return ["run", wang2d, "--set", out, "--set", "run.end_time=0.002", "--set", "contact.integrator=verlet",
                "--set", "contact.model=linear"]  # fmt: skip
    if name == "pcpm":  # past the first evaluation of the crush and merge criteria
        pcpm2 = str(ROOT / "demos" / "wang2d" / "coarse" / "pcpm2.toml")
        return ["run", pcpm2, "--set", out, "--set", "run.end_time=0.012"]
    raise SystemExit(f"--cases: unknown case {name!r} (wang2d, verlet, pcpm)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["wang2d", "verlet", "pcpm"], help="cases to run, in order")
    ap.add_argument("--top", type=int, default=30, help="kernels listed")
    a = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="febed-compile-"))
    os.environ["NUMBA_CACHE_DIR"] = str(work / "numba")  # an empty cache, set before febed configures Numba
    sys.path.insert(0, str(ROOT / "tools"))
    from compile_times import CompileRecorder, listener_for  # the recorder of the pytest-run tool
    from numba.core import event

    from febed.cli import main as febed_main

    recorder = CompileRecorder()
    wall = {}
    with event.install_listener("numba:compile", listener_for(recorder)):
        for name in a.cases:
            t0 = time.perf_counter()
            code = febed_main(case_args(name, work))
            wall[name] = time.perf_counter() - t0
            if code != 0:
                sys.exit(f"case {name}: febed run exited with {code}")
    print(recorder.report(a.top))
    print("wall per case (compilation included): " + ", ".join(f"{k} {v:.1f} s" for k, v in wall.items()))
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
