"""Probe CSV files: rows as written, restart keeps rows up to the restart time and appends after them."""

import math

from mpi4py import MPI

import pytest

from febed.io.probes import ProbeFile, read_probes

pytestmark = pytest.mark.mpi


def test_write_read_and_restart(mpi_tmp_path):
    path = mpi_tmp_path / "probes.csv"
    p = ProbeFile(path, ["dp", "bed_height"])
    for k in range(10):
        p.write(0.1 * k, {"dp": 100.0 + k, "bed_height": 0.2 if k % 2 else None})
    p.close()
    MPI.COMM_WORLD.barrier()
    data = read_probes(path)
    assert data["time"] == [0.1 * k for k in range(10)]
    assert data["dp"][3] == 103.0 and math.isnan(data["bed_height"][0])
    MPI.COMM_WORLD.barrier()
    p = ProbeFile(path, ["dp", "bed_height"], restart_time=0.1 * 4)  # keep rows 0..4, append
    for k in range(5, 12):
        p.write(0.1 * k, {"dp": 100.0 + k})
    p.close()
    MPI.COMM_WORLD.barrier()
    data = read_probes(path)
    assert data["time"] == [0.1 * k for k in range(12)]
    assert data["dp"] == [100.0 + k for k in range(12)]
    MPI.COMM_WORLD.barrier()
    with pytest.raises(ValueError, match="columns"):
        if MPI.COMM_WORLD.rank == 0:
            ProbeFile(path, ["other"], restart_time=0.3)
        else:
            raise ValueError("columns (rank 0 checks)")
