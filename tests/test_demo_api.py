"""The Python API demo (demos/api/run_api.py) runs and passes its own check, serially and on 2 ranks.

It is run in this process (`runpy`), so that under `mpirun -n 2 pytest -m mpi` the script itself runs on
the two ranks of the job, as a user's `mpirun -n 2 python run_api.py` would.
"""

import runpy
from pathlib import Path

from mpi4py import MPI

import pytest

import febed
from febed.io.rundir import release_output

DEMO = Path(__file__).resolve().parents[1] / "demos" / "api"


def _files_outside_out() -> set[Path]:
    return {p for p in DEMO.rglob("*") if "out" not in p.relative_to(DEMO).parts and "__pycache__" not in p.parts}


@pytest.mark.mpi
def test_api_demo_runs_and_writes_its_output():
    comm = MPI.COMM_WORLD
    before = _files_outside_out()
    error = None
    try:
        runpy.run_path(str(DEMO / "run_api.py"), run_name="__main__")
    except Exception as e:  # reported on every rank below, so that no rank waits for another
        error = f"rank {comm.rank}: {type(e).__name__}: {e}"
    finally:
        release_output(DEMO / "out")
    errors = [e for e in comm.allgather(error) if e]
    assert not errors, errors
    out = DEMO / "out"
    if comm.rank == 0:
        probes = febed.read_probes(out / "probes.csv")
        assert probes["time"][0] == 0.0 and probes["time"][-1] == pytest.approx(0.02, abs=1e-3)
        assert all(n == 300 for n in probes["particles"])  # none lost
        assert (out / "fields.xdmf").exists() and list((out / "particles").glob("*.vtp"))
        assert (out / "case.resolved.toml").exists()
    assert _files_outside_out() == before  # the demo writes only under its out/
