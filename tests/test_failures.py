"""Only failures of the simulation are reported as such; any other error in a run is reported as a bug in febed.

A failure of the simulation (a non-finite value, a lost particle, ...: `RunFailure`) says what went wrong; an
unexpected exception in a step with nothing wrong in the state is an internal error: logged with its traceback,
status.json "failed" with a message saying so, the last good state kept as a checkpoint, exit status 3. The
coupled runs are the seed-000 2D bed of demos/wang2d for a few gas steps.
"""

import json
import math
import signal
from pathlib import Path
from types import SimpleNamespace

from mpi4py import MPI

import pytest

from febed.cli import main
from febed.io.checkpoint import list_checkpoints, read_checkpoint

ROOT = Path(__file__).resolve().parents[1]
CASE = ROOT / "demos" / "wang2d" / "wang2d.toml"
END = 0.004


def febed(out, capsys):
    """`febed run` of the wang2d case to t = END in this process: (exit status, stderr, status.json, febed.log)."""
    sets = [f"output.directory={out}", f"run.end_time={END}", "output.checkpoint_interval=1.0"]
    code = main(["run", str(CASE), *[a for s in sets for a in ("--set", s)]])
    err = capsys.readouterr().err
    return code, err, json.loads((out / "status.json").read_text()), (out / "febed.log").read_text()


def at_call(real, call, fault):
    """`real`, except that its `call`-th call (counted from 1) runs `fault(*args)` instead."""
    calls = []

    def wrapped(*args, **kwargs):
        calls.append(1)
        return (fault if len(calls) == call else real)(*args, **kwargs)

    return wrapped


def test_an_error_in_a_kernel_is_reported_as_an_internal_error(tmp_path, capsys, monkeypatch):
    from febed.coupling import exchange

    def bug(*args):
        raise IndexError("index 7 is out of bounds for axis 0 with size 7")

    monkeypatch.setattr(exchange, "exchange_project_kernel", at_call(exchange.exchange_project_kernel, 3, bug))
    out = tmp_path / "run"
    code, err, info, log = febed(out, capsys)
    assert code == 3
    assert info["state"] == "failed"
    message = info["message"]
    assert message.startswith("internal error in the gas step from t = ") and "IndexError: index 7" in message
    assert "a bug in febed, not a failure of the simulation" in message and str(out / "febed.log") in message
    assert "numerical" not in message and "blew up" not in message
    said = [line for line in err.splitlines() if line.startswith("febed: ")]
    assert said == [f"febed: the run stopped on an {message}"], err
    # the traceback is in the log, down to the kernel call that raised
    assert "Traceback (most recent call last)" in log and "IndexError: index 7 is out of bounds" in log
    assert "in project_to_gas" in log
    # the last good state is kept as a checkpoint, as for a failure of the simulation
    ckpts = list_checkpoints(out / "checkpoints")
    assert ckpts and str(ckpts[-1]) in message
    assert read_checkpoint(ckpts[-1])[1]["time"] < END


def test_a_non_finite_gas_velocity_is_a_failure_of_the_simulation(tmp_path, capsys, monkeypatch):
    from febed.gas.vans import VANSSolver

    real = VANSSolver.step

    def nan_step(self, *args, **kwargs):
        info = real(self, *args, **kwargs)
        self.u[3, 1] = math.nan
        return info

    monkeypatch.setattr(VANSSolver, "step", at_call(real, 2, nan_step))
    out = tmp_path / "run"
    code, err, info, log = febed(out, capsys)
    assert code == 3 and info["state"] == "failed"
    assert info["message"].startswith("gas velocity u is not finite at the node at ")
    assert "internal error" not in info["message"] and "Traceback" not in log + err
    said = [line for line in err.splitlines() if line.startswith("febed: ")]
    assert len(said) == 1 and info["message"].startswith(said[0].removeprefix("febed: the run failed: ")), err
    assert "last good state" in info["message"] and list_checkpoints(out / "checkpoints")


def test_an_error_raised_by_a_blow_up_is_a_failure_of_the_simulation(tmp_path, capsys, monkeypatch):
    """An error that surfaces inside a kernel while the state holds non-finite values is the blow-up's."""
    from febed.coupling import exchange
    from febed.solver import CoupledSolver

    solvers = []
    real_init = CoupledSolver.__init__

    def init(self, *args, **kwargs):
        real_init(self, *args, **kwargs)
        solvers.append(self)

    def blow_up(*args):
        solvers[0].dem.particles.vel[5] = math.nan
        raise ValueError("negative dimensions are not allowed")

    monkeypatch.setattr(CoupledSolver, "__init__", init)
    monkeypatch.setattr(exchange, "exchange_project_kernel", at_call(exchange.exchange_project_kernel, 3, blow_up))
    out = tmp_path / "run"
    code, err, info, log = febed(out, capsys)
    assert code == 3 and info["state"] == "failed"
    message = info["message"]
    assert "has a non-finite position/velocity" in message and "ValueError: negative dimensions" in message
    assert "internal error" not in message
    said = [line for line in err.splitlines() if line.startswith("febed: ")]
    assert len(said) == 1 and message.startswith(said[0].removeprefix("febed: the run failed: ")), err


@pytest.mark.parametrize("kind", ["bug", "blow-up", "start-up"])
def test_a_fault_on_one_rank_ends_every_rank(tmp_path, kind):
    """Under `mpirun -n 2` rank 1 alone meets a bug, or a blow-up inside a kernel, while rank 0 goes on into the
    step's collective calls, or a bug while the solver is built (tests/_fault_on_one_rank.py).

    The job ends with status 3 (1 for the bug at start-up, as any bug outside a run's steps), neither rank left
    waiting for the other, not even in its exit, where PETSc frees its objects collectively; rank 1 writes
    status.json and its message into febed.log itself.
    """
    import shutil
    import subprocess
    import sys

    from _febed_process import MPIRUN, clean_env

    if shutil.which("mpirun") is None:
        pytest.skip("needs mpirun")
    out = tmp_path / "run"
    cmd = [*MPIRUN, sys.executable, str(ROOT / "tests" / "_fault_on_one_rank.py"), kind, "run", str(CASE),
           "--set", f"output.directory={out}", "--set", f"run.end_time={END}"]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=clean_env())
    assert r.returncode == (1 if kind == "start-up" else 3), r.stdout[-2000:] + r.stderr[-2000:]
    info = json.loads((out / "status.json").read_text())
    log = (out / "febed.log").read_text()
    assert info["state"] == "failed" and f"[rank 1] run failed: {info['message']}" in log
    if kind == "start-up":
        assert info["message"] == "injected on one rank while the solver is built" and info["step"] == 0
        assert "Traceback" in r.stderr
    elif kind == "bug":
        assert info["message"].startswith("internal error in the gas step from t = ")
        assert "IndexError: index 9 is out of bounds" in info["message"]
        assert "Traceback" in log and "injected on one rank" in log
    else:
        assert "has a non-finite position/velocity" in info["message"] and "internal error" not in info["message"]
        assert "ValueError: negative dimensions" in info["message"]


class _Run(SimpleNamespace):
    """The smallest run object `run_to_end` drives (see `febed.runs.lifecycle`)."""

    def __init__(self, fault, outdir):
        super().__init__(
            comm=MPI.COMM_SELF, outdir=outdir, good=None, statuses=[], closed=[], fault=fault,
            display=SimpleNamespace(end=lambda: None), log=SimpleNamespace(errors=[]),
        )  # fmt: skip
        self.log.error = lambda msg, exc_info=None: self.log.errors.append((msg, exc_info))

    def catch_signals(self):
        return lambda: None

    def advance_to(self, end):
        raise self.fault

    def status(self, state, message="", collective=True, alone=False):
        self.statuses.append((state, message))

    def close(self, last_output=True):
        self.closed.append(last_output)


def test_every_run_mode_reports_an_unexpected_exception_as_an_internal_error(tmp_path):
    from febed.runs.lifecycle import InternalError, run_to_end

    run = _Run(KeyError("gid"), tmp_path)
    with pytest.raises(InternalError, match=r"^internal error: KeyError: 'gid' \(a bug in febed") as info:
        run_to_end(run, 1.0)
    assert isinstance(info.value.__cause__, KeyError)
    assert run.statuses == [("failed", str(info.value))]
    assert run.log.errors == [(f"run failed: {info.value}", run.fault)]  # logged with its traceback
    assert run.closed == [False]  # files closed, no last output from a broken state


def test_a_second_signal_wrapped_by_an_extension_stops_the_run_at_once_not_as_an_internal_error(tmp_path):
    """A handler raising StopNow while Numba loads a cached kernel reaches the run as a SystemError caused by it."""
    from febed.runs.lifecycle import Interrupted, StopNow, run_to_end

    try:
        try:
            raise StopNow(signal.SIGINT)
        except StopNow as stop:
            raise SystemError("CPUDispatcher(<function pair_keys>) returned a result with an exception set") from stop
    except SystemError as wrapped:
        fault = wrapped
    run = _Run(fault, tmp_path)
    run.log.warning = lambda msg: None
    with pytest.raises(Interrupted, match="stopped at once by a second SIGINT") as info:
        run_to_end(run, 1.0)
    assert info.value.signum == signal.SIGINT
    assert [state for state, _ in run.statuses] == ["interrupted"] and run.log.errors == []
    assert run.closed == [False]


def test_an_error_met_while_handling_a_stop_is_still_an_internal_error(tmp_path):
    """Only an explicit cause makes a wrapped stop: a bug in an `except KeyboardInterrupt` block stays a bug."""
    from febed.runs.lifecycle import InternalError, StopNow, run_to_end

    try:
        try:
            raise StopNow(signal.SIGINT)
        except StopNow:
            raise KeyError("gid")  # noqa: B904 (its context, not its cause, is the stop)
    except KeyError as bug:
        fault = bug
    run = _Run(fault, tmp_path)
    with pytest.raises(InternalError, match="KeyError"):
        run_to_end(run, 1.0)
    assert [state for state, _ in run.statuses] == ["failed"]


@pytest.mark.parametrize("make", ["RunFailure", "DEMFailure"])
def test_failures_of_the_simulation_pass_through_unchanged(tmp_path, make):
    from febed.dem.solver import DEMFailure
    from febed.runs.lifecycle import run_to_end
    from febed.solver import RunFailure

    fault = {"RunFailure": RunFailure, "DEMFailure": DEMFailure}[make]("particle 3 has a non-finite velocity")
    run = _Run(fault, tmp_path)
    with pytest.raises(type(fault)) as info:
        run_to_end(run, 1.0)
    assert info.value is fault and run.statuses == [] and run.log.errors == []  # recorded by the mode itself
