"""Every demo runs (briefly), passes its own checks and writes only under its own `out/` folder.

Each demo is run as a user runs it, a separate `python demos/<name>/<script>.py` process with its shortest
options; the demo's folder (all but `out/`) must be unchanged afterwards. The demos that run on several
ranks are also run under `mpirun -n 2 pytest -m mpi` (`make test-mpi`): those tests (marked `mpi`) run the
script in this process, on the two ranks of the job, as `mpirun -n 2 python <script>.py` would; on one
process they are skipped, the serial run being the test beside them. The coarse-graining demo starts its
own `mpirun -n 2` for its 2-rank run. The Python API demo is run by tests/test_demo_api.py.
"""

import os
import runpy
import shutil
import subprocess
import sys
from pathlib import Path

from mpi4py import MPI

import pytest
from _febed_process import clean_env

from febed.io.rundir import release_output

DEMOS = Path(__file__).parents[1] / "demos"
TWO_RANKS = pytest.mark.skipif(MPI.COMM_WORLD.size < 2, reason="the run on the ranks of mpirun -n N pytest -m mpi")


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    """(size, mtime) of every file under `folder` except in `out/` and `__pycache__/` folders."""
    files = {}
    for root, dirs, names in os.walk(folder):
        dirs[:] = [d for d in dirs if d not in ("out", "__pycache__")]
        for n in names:
            st = os.stat(os.path.join(root, n))
            files[os.path.relpath(os.path.join(root, n), folder)] = (st.st_size, st.st_mtime_ns)
    return files


def assert_unchanged(folder: Path, before: dict, script: Path) -> None:
    after = snapshot(folder)
    changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
    assert not changed, f"{script.name} wrote outside {folder / 'out'}: {changed}"


def run_demo(script: Path, *args: str, timeout: int = 1800) -> str:
    """Run a demo script; assert it succeeds and leaves its folder (but `out/`) as it was; return its stdout."""
    before = snapshot(script.parent)
    res = subprocess.run(
        [sys.executable, str(script), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=script.parent,
        env=clean_env(),
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert_unchanged(script.parent, before, script)
    return res.stdout


def run_demo_here(script: Path, args: list[str], monkeypatch, capsys) -> str:
    """Run a demo script in this process on every rank of the job; assert that it succeeds on every rank and
    leaves its folder (but `out/`) as it was; return rank 0's stdout (the demos print on rank 0)."""
    comm = MPI.COMM_WORLD
    before = snapshot(script.parent) if comm.rank == 0 else None
    comm.barrier()  # no rank writes before rank 0 has looked
    monkeypatch.setattr(sys, "argv", [str(script), *args])
    error = None
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as e:  # the ranks but 0 leave after the run (`sys.exit()`): success unless a status
        if e.code not in (None, 0):
            error = f"rank {comm.rank}: exit {e.code}"
    except Exception as e:  # reported on every rank below, so that no rank waits for another
        error = f"rank {comm.rank}: {type(e).__name__}: {e}"
    finally:
        release_output(script.parent / "out")
    errors = [e for e in comm.allgather(error) if e]
    assert not errors, errors
    if comm.rank == 0:
        assert_unchanged(script.parent, before, script)
    return capsys.readouterr().out


def test_meshes_demo():
    assert "figures written" in run_demo(DEMOS / "meshes" / "demo_meshes.py")


@pytest.mark.mpi
@TWO_RANKS
def test_meshes_demo_two_ranks(monkeypatch, capsys):
    out = run_demo_here(DEMOS / "meshes" / "demo_meshes.py", [], monkeypatch, capsys)
    if MPI.COMM_WORLD.rank == 0:
        assert "figures written" in out and "184800 cells" in out


def test_wang2d_demo_short():
    out = run_demo(DEMOS / "wang2d" / "demo_wang2d.py", "--end-time", "0.03")
    assert "figures:" in out


@pytest.mark.mpi
@TWO_RANKS
def test_wang2d_demo_short_two_ranks(monkeypatch, capsys):
    out = run_demo_here(DEMOS / "wang2d" / "demo_wang2d.py", ["--end-time", "0.03"], monkeypatch, capsys)
    if MPI.COMM_WORLD.rank == 0:
        assert "figures:" in out
        assert (DEMOS / "wang2d" / "out" / "snapshots.png").exists()


# The pseudo-2D bed (57,296 particles) is packed on first use, which takes minutes: slow until it exists.
PSEUDO2D_BED = DEMOS / "pseudo2d" / "pseudo2d-75g.npz"
NEEDS_BED = [] if PSEUDO2D_BED.exists() else [pytest.mark.slow]
PSEUDO2D_DEFAULT = "C1-partial-slip-edges"  # the demo's default case


@pytest.mark.parametrize("end_time", [pytest.param("0.004", marks=NEEDS_BED)])
def test_pseudo2d_demo_short(end_time):
    figures = DEMOS / "pseudo2d" / "out" / "figures"
    shutil.rmtree(figures, ignore_errors=True)
    out = run_demo(DEMOS / "pseudo2d" / "demo_pseudo2d.py", "--end-time", end_time)
    assert "checks passed: solid volume conserved" in out
    assert list(figures.glob(f"{PSEUDO2D_DEFAULT}_*.png"))


@pytest.mark.mpi
@TWO_RANKS
@pytest.mark.parametrize("end_time", [pytest.param("0.004", marks=NEEDS_BED)])
def test_pseudo2d_demo_short_two_ranks(end_time, monkeypatch, capsys):
    out = run_demo_here(DEMOS / "pseudo2d" / "demo_pseudo2d.py", ["--end-time", end_time], monkeypatch, capsys)
    if MPI.COMM_WORLD.rank == 0:
        assert "checks passed: solid volume conserved" in out
        log = (DEMOS / "pseudo2d" / "out" / PSEUDO2D_DEFAULT / "febed.log").read_text()
        assert f"{MPI.COMM_WORLD.size} rank(s)" in log


def test_scg_demo():
    out_dir = DEMOS / "scg" / "out"
    shutil.rmtree(out_dir, ignore_errors=True)
    run_demo(DEMOS / "scg" / "scg_demo.py")  # its default folder is out/
    assert (out_dir / "results.json").exists() and (out_dir / "fig3_uniform_speed.png").exists()


@pytest.mark.skipif(shutil.which("mpirun") is None, reason="needs mpirun")
def test_coarse_demo_quick():
    """Two of the study's runs for 0.01 s: TM l = 1 serially and PCPM from l = 2 on 2 ranks (the demo's mpirun)."""
    runs = DEMOS / "wang2d" / "coarse" / "out" / "quick"
    shutil.rmtree(runs, ignore_errors=True)  # no finished run to reuse
    out = run_demo(DEMOS / "wang2d" / "coarse" / "demo_coarse.py", "--quick", "--only", "tm1", "pcpm2-np2",
                   "--end-time", "0.01", timeout=600)  # fmt: skip
    assert "checks passed: 2 run(s) reached their end time" in out
    assert "2 rank(s)" in (runs / "pcpm2-np2" / "febed.log").read_text()
    assert {p.name for p in (runs / "figures").iterdir()} >= {"table.md", "snapshots_4080.png", "groups.png"}


@pytest.mark.slow
def test_wang2d_bed_fluidizes():
    """Seed-000 bed at 0.9 m/s: time-averaged pressure drop over 1 s after start-up within 5 % of W/A."""
    out = run_demo(DEMOS / "wang2d" / "demo_wang2d.py", "--end-time", "1.3")
    assert "time-averaged bed pressure drop / weight" in out
