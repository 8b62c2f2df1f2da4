"""The gas solver's set-up from an empty DOLFINx form cache: what the first run of a case on a fresh machine pays.

Builds a case's mesh, then its gas solver (`VANSSolver.from_case`: the nodal operators, boundary weights,
pressure solvers) in a fresh process whose DOLFINx JIT cache (`$XDG_CACHE_HOME/fenics`) is a new empty
folder, and prints the set-up time and how many forms and elements DOLFINx compiled for it:

    .venv/bin/python benchmarks/form_compile.py [--case demos/pseudo2d/C1.toml]

prints `gas set-up from an empty form cache: X s, N compiled modules`. The Numba kernel cache is left as it is
(`benchmarks/kernel_compile.py` measures that one), so only the form compilation is cold.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = """
import sys, time
from mpi4py import MPI
from febed.case import load_case
from febed.meshing import load_case_mesh
from febed.gas.vans import VANSSolver
case = load_case(sys.argv[1], [])
md = load_case_mesh(case, MPI.COMM_WORLD)
t = time.perf_counter()
VANSSolver.from_case(case, md)
print(f"{time.perf_counter() - t:.3f}")
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default=str(ROOT / "demos" / "pseudo2d" / "C1.toml"))
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="febed-forms-") as tmp:
        env = dict(os.environ, XDG_CACHE_HOME=tmp)
        home = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
        if "NUMBA_CACHE_DIR" not in env:  # keep febed's compiled kernels: only the forms start cold
            env["NUMBA_CACHE_DIR"] = str(home / "febed" / "numba")
        run = subprocess.run([sys.executable, "-c", CHILD, args.case], env=env, cwd=tmp, capture_output=True, text=True)
        if run.returncode != 0:
            raise SystemExit(run.stderr[-2000:])
        seconds = float(run.stdout.strip().splitlines()[-1])
        modules = len(list((Path(tmp) / "fenics").glob("*.so")))
    print(f"case {Path(args.case).name}: forms of the mesh and the gas solver compiled by DOLFINx (FFCx, C compiler)")
    print(f"gas set-up from an empty form cache: {seconds:.2f} s, {modules} compiled modules")


if __name__ == "__main__":
    main()
