"""Numba compile time per kernel over a pytest run from an empty cache (what a fresh clone pays).

    python tools/compile_times.py [--top 30] [--keep-cache] [pytest arguments ...]

Runs pytest in this process (default arguments: `-q -m "not slow"`) with Numba's cache pointed at an empty
temporary folder, records every compilation (Numba's "numba:compile" events), and prints, per kernel,
the number of signatures compiled, the time including the kernels it compiled on the way (inclusive)
and without them (exclusive), the largest first, then the total and the wall time of the run.
A kernel compiled for several signatures is a candidate for one signature (fewer compilations).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from collections import defaultdict


class CompileRecorder:
    """A Numba event listener: inclusive and exclusive compile seconds per kernel, and its signatures."""

    def __init__(self):
        self.stack: list[list] = []  # [name, start, seconds spent in nested compilations]
        self.inclusive: dict[str, float] = defaultdict(float)
        self.exclusive: dict[str, float] = defaultdict(float)
        self.signatures: dict[str, set] = defaultdict(set)

    @staticmethod
    def _name(event) -> str:
        func = event.data["dispatcher"].py_func
        module = getattr(func, "__module__", None) or "numba"  # overload implementations have none
        return f"{module}.{getattr(func, '__qualname__', func)}"

    def on_start(self, event) -> None:
        """A compilation starts (nested inside the one on top of the stack, if any)."""
        self.stack.append([self._name(event), time.perf_counter(), 0.0])
        self.signatures[self._name(event)].add(str(event.data["args"]))

    def on_end(self, event) -> None:
        """A compilation ends: its time goes to its kernel, and to its parent's nested time."""
        name = self._name(event)
        while self.stack and self.stack[-1][0] != name:  # a nested typing attempt that failed and ended early
            self.stack.pop()
        if not self.stack:
            return
        name, start, nested = self.stack.pop()
        spent = time.perf_counter() - start
        self.inclusive[name] += spent
        self.exclusive[name] += spent - nested
        if self.stack:
            self.stack[-1][2] += spent

    def report(self, top: int) -> str:
        """The `top` kernels by exclusive compile time, and the totals, as text."""
        rows = sorted(self.exclusive, key=self.exclusive.get, reverse=True)
        lines = [f"{'kernel':72s} {'sigs':>4s} {'incl s':>7s} {'excl s':>7s}"]
        for name in rows[:top]:
            n = len(self.signatures[name])
            lines.append(f"{name[-72:]:72s} {n:4d} {self.inclusive[name]:7.1f} {self.exclusive[name]:7.1f}")
        total = sum(self.exclusive.values())
        multi = sum(1 for s in self.signatures.values() if len(s) > 1)
        lines.append(
            f"{len(rows)} kernels, {sum(len(s) for s in self.signatures.values())} signatures "
            f"({multi} kernels with more than one): {total:.1f} s of compilation"
        )
        return "\n".join(lines)


def listener_for(recorder: CompileRecorder):
    """A Numba event listener feeding `recorder` (register it for "numba:compile")."""
    from numba.core import event

    return type("Listener", (event.Listener,), {"on_start": lambda s, e: recorder.on_start(e),
                                                "on_end": lambda s, e: recorder.on_end(e)})()  # fmt: skip


def main() -> int:
    """Run pytest from an empty cache and print the compile times; returns pytest's exit code."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--top", type=int, default=30, help="kernels listed (default 30)")
    ap.add_argument("--keep-cache", action="store_true", help="keep the temporary cache folder")
    args, pytest_args = ap.parse_known_args()
    cache = tempfile.mkdtemp(prefix="febed-numba-cold-")
    os.environ["NUMBA_CACHE_DIR"] = cache  # before Numba or febed is imported
    import pytest
    from numba.core import event

    recorder = CompileRecorder()
    listener = listener_for(recorder)
    start = time.perf_counter()
    with event.install_listener("numba:compile", listener):
        code = pytest.main(pytest_args or ["-q", "-m", "not slow"])
    wall = time.perf_counter() - start
    print(recorder.report(args.top))
    print(f"pytest exit code {int(code)}, wall time {wall:.0f} s, cache {cache}")
    if not args.keep_cache:
        shutil.rmtree(cache, ignore_errors=True)
    return int(code)


if __name__ == "__main__":
    sys.exit(main())
