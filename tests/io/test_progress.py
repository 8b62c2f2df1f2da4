"""Progress lines: the rate over the recent past, and no live line into a file behind an MPI launcher."""

import io
import logging
import math
import os
import subprocess

import pytest

from febed.io.progress import Progress, RateMeter, launcher_is_terminal, peak_memory


def test_rate_is_measured_over_the_recent_window_not_since_the_start():
    # 100 s of start-up (compilation) for 0.001 simulated s, then a steady 1,000 wall s per simulated s
    meter = RateMeter(2.0, window=300.0, now=0.0)
    assert math.isnan(meter.rate(2.0, now=1.0))  # no progress yet
    t, now = 2.001, 100.0
    meter.rate(t, now)
    while now < 1000.0:
        t, now = t + 0.002, now + 2.0
        rate = meter.rate(t, now)
    assert rate == pytest.approx(1000.0, rel=1e-9)  # the start-up has left the window
    assert (now - 0.0) / (t - 2.0) > 1.1 * rate  # ... while the mean since the start still holds it
    assert len(meter.samples) <= 152  # bounded: the window's samples only
    assert meter.text(t, t + 1.0, now) == "16.67 min wall per simulated s  ETA 0h16m40s"


def test_a_short_run_rates_from_its_start():
    meter = RateMeter(0.0, window=300.0, now=0.0)
    assert meter.rate(0.5, now=30.0) == pytest.approx(60.0)
    assert meter.rate(1.0, now=40.0) == pytest.approx(40.0)  # both samples within the window: since the start


@pytest.fixture
def launcher_writing_to():
    """A stand-in launcher process whose standard output goes to a file or to a pseudo-terminal."""
    procs, fds = [], []

    def start(kind, tmp_path):
        if kind == "file":
            out = open(tmp_path / "run.out", "w")
        else:
            master, slave = os.openpty()
            fds.extend([master, slave])
            out = slave
        p = subprocess.Popen(["sleep", "30"], stdout=out)
        procs.append(p)
        return p.pid

    yield start
    for p in procs:
        p.kill()
        p.wait()
    for fd in fds:
        os.close(fd)


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="reads the launcher's stdout from /proc")
def test_live_line_only_when_the_launchers_output_is_a_terminal(tmp_path, launcher_writing_to):
    class Tty(io.StringIO):
        def isatty(self):
            return True

    mpi = {"OMPI_COMM_WORLD_SIZE": "2"}
    to_file, to_pty = launcher_writing_to("file", tmp_path), launcher_writing_to("pty", tmp_path)
    assert launcher_is_terminal({}, to_file)  # not under a launcher: the stream's own isatty decides
    assert not launcher_is_terminal(mpi, to_file)  # `mpirun ... > run.out`
    assert launcher_is_terminal(mpi, to_pty)  # `mpirun ...` in a terminal
    assert launcher_is_terminal(mpi, 2**22 + 7)  # no such process: keep the stream's answer

    log = logging.getLogger("febed.test.launcher")
    log.handlers.clear()
    log.addHandler(logging.FileHandler(tmp_path / "febed.log"))
    batch = Tty()
    p = Progress(log, 0, batch, env=mpi, launcher_pid=to_file)
    p.show("t = 0.1 / 1 s")
    p.end()
    assert not p.live and batch.getvalue() == ""
    assert "t = 0.1 / 1 s" in (tmp_path / "febed.log").read_text()
    assert Progress(log, 0, Tty(), env=mpi, launcher_pid=to_pty).live


@pytest.mark.mpi
def test_peak_memory_is_the_processes_resident_memory_in_gigabytes():
    # ru_maxrss is in kB on Linux: this process (Python, NumPy, MPI) holds between 20 MB and the machine's memory,
    # and the sum over the ranks is at least the largest rank's
    import re

    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    text = peak_memory(comm)
    numbers = [float(x) for x in re.findall(r"([0-9.]+) GB", text)]
    physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1e9
    assert len(numbers) == (1 if comm.size == 1 else 2), text
    assert 0.02 * comm.size <= numbers[0] <= physical, text
    if comm.size > 1:
        assert numbers[1] <= numbers[0] and f"of {comm.size} ranks" in text
