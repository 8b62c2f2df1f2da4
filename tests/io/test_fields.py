"""Field output (`febed.io.fields`): an XDMF index over one HDF5 file per output time.

What is checked: the index lists the times written, every data item it names is a complete file holding the
values written (the nodal x coordinate, matched against the mesh file's geometry), the mesh's
cells name every node, and a process killed with SIGKILL while writing leaves an index whose every file opens
(and temporary files only, which the next run removes).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET

from mpi4py import MPI

import dolfinx.fem
import dolfinx.mesh
import h5py
import numpy as np
import pytest

from febed.io.fields import FieldWriter, remove_temporaries


def index_items(xdmf):
    """(time or None, data item text) of every HDF5 data item of the index, in document order."""
    root = ET.parse(xdmf).getroot()
    out = []
    for grid in root.iter("Grid"):
        if grid.get("GridType") != "Uniform":
            continue
        time = grid.find("Time")
        for item in grid.iter("DataItem"):
            out.append((None if time is None else float(time.get("Value")), item.text.strip()))
    return out


def dataset(folder, text):
    """The array that an index data item 'file.h5:/path' names (relative to the index's folder)."""
    name, _, path = text.partition(":")
    with h5py.File(folder / name, "r") as f:
        return f[path][...]


@pytest.mark.mpi
def test_a_folder_rank_0_cannot_make_stops_every_rank(mpi_tmp_path):
    """Rank 0 alone makes the series' folder: its error reaches every rank as one OutputFailure (no hang)."""
    from febed.runs.lifecycle import OutputFailure, guarded_write

    comm = MPI.COMM_WORLD
    mesh = dolfinx.mesh.create_unit_square(comm, 2, 2, dolfinx.mesh.CellType.quadrilateral)
    p = dolfinx.fem.Function(dolfinx.fem.FunctionSpace(mesh, ("Q", 1)))
    if comm.rank == 0:
        (mpi_tmp_path / "fields").write_text("a file where the folder should be\n")
    comm.barrier()
    path = mpi_tmp_path / "fields.xdmf"
    with pytest.raises(OutputFailure, match="fields"):
        guarded_write(comm, path, FieldWriter, path, mesh, {"p": p}, comm)


@pytest.mark.mpi
def test_each_time_is_a_file_of_its_own_and_the_index_names_its_values(mpi_tmp_path):
    comm = MPI.COMM_WORLD
    mesh = dolfinx.mesh.create_unit_square(comm, 6, 4, dolfinx.mesh.CellType.quadrilateral)
    V = dolfinx.fem.FunctionSpace(mesh, ("Q", 1))
    W = dolfinx.fem.VectorFunctionSpace(mesh, ("Q", 1))
    p, u = dolfinx.fem.Function(V), dolfinx.fem.Function(W)
    writer = FieldWriter(mpi_tmp_path / "fields.xdmf", mesh, {"p": p, "u": u}, comm)
    times = [0.0, 0.25, 0.5]
    for k, t in enumerate(times):
        p.interpolate(lambda x, k=k: x[0] + 10.0 * k)
        u.interpolate(lambda x: np.vstack([x[1], -x[0]]))
        writer.write(t)
    writer.close()
    comm.barrier()
    if comm.rank == 0:
        folder = mpi_tmp_path
        files = sorted(f.name for f in (folder / "fields").iterdir())
        assert files == ["000000.h5", "000001.h5", "000002.h5", "mesh.h5"]
        items = index_items(folder / "fields.xdmf")
        geometry = dataset(folder, next(text for t, text in items if text.endswith("/geometry")))
        assert geometry.shape == (7 * 5, 2)
        p_items = [(t, text) for t, text in items if "/Function/p/" in text]
        u_items = [(t, text) for t, text in items if "/Function/u/" in text]
        assert [t for t, _ in p_items] == times and [t for t, _ in u_items] == times
        for k, (_, text) in enumerate(p_items):
            assert text.startswith(f"fields/{k:06d}.h5:")
            assert np.allclose(dataset(folder, text)[:, 0], geometry[:, 0] + 10.0 * k, atol=1e-12)
        uu = dataset(folder, u_items[-1][1])
        assert np.allclose(uu[:, 0], geometry[:, 1], atol=1e-12) and np.allclose(uu[:, 1], -geometry[:, 0], atol=1e-12)
        topology = dataset(folder, next(text for t, text in items if text.endswith("/topology")))
        assert topology.shape == (24, 4) and set(np.unique(topology)) == set(range(35))


KILLED = """
import sys
from mpi4py import MPI
import dolfinx.fem, dolfinx.mesh
from febed.io.fields import FieldWriter, remove_temporaries
mesh = dolfinx.mesh.create_unit_square(MPI.COMM_SELF, 300, 300)
V = dolfinx.fem.FunctionSpace(mesh, ("P", 1))
f = dolfinx.fem.Function(V)
writer = FieldWriter(sys.argv[1], mesh, {"p": f}, MPI.COMM_SELF)
k = 0
while True:
    f.x.array[:] = k
    writer.write(float(k))
    print(k, flush=True)
    k += 1
"""


def test_a_run_killed_while_writing_leaves_every_indexed_file_readable(tmp_path):
    index = tmp_path / "fields.xdmf"
    proc = subprocess.Popen([sys.executable, "-c", KILLED, str(index)], stdout=subprocess.PIPE, text=True)
    try:
        seen = []
        for _ in range(3):  # three complete writes, then killed about halfway through the next one
            assert proc.stdout.readline().strip() != ""
            seen.append(time.perf_counter())
        time.sleep(0.5 * (seen[2] - seen[1]))
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    items = [(t, text) for t, text in index_items(index) if t is not None]
    assert len(items) >= 3
    for k, (t, text) in enumerate(items):
        assert t == float(k) and np.allclose(dataset(tmp_path, text), k, rtol=1e-14, atol=0.0)
    named = {text.partition(":")[0] for _, text in index_items(index)}
    complete = {f"fields/{f.name}" for f in (tmp_path / "fields").iterdir() if not f.name.startswith(".")}
    assert named <= complete
    left = {f for f in (tmp_path / "fields").iterdir() if f.name.startswith(".")}  # a write cut short, if any
    assert set(remove_temporaries(tmp_path)) == left
    assert {f"fields/{f.name}" for f in (tmp_path / "fields").iterdir()} == complete
