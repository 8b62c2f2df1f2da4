"""Particle output that ParaView opens: one VTK XML PolyData file (.vtp) per output + a .pvd collection.

Each .vtp holds the particle centres as vertices with point data velocity (m/s), angular velocity (rad/s),
diameter (m), n_orig and gid, base64-encoded binary. Files are written atomically (`febed.io.atomic`) and the
.pvd is rewritten after every output, so a run stopped at any moment leaves a readable series; a write that
fails (OSError naming the file) adds nothing to it. With MPI, rank 0 gathers the particles and writes (fine
up to millions of particles).
"""

from __future__ import annotations

import base64
import os
from pathlib import Path

from mpi4py import MPI

import numpy as np

from febed.io.atomic import atomic_write_bytes

_VTK_TYPES = {np.dtype(np.float64): "Float64", np.dtype(np.int64): "Int64", np.dtype(np.int32): "Int32"}


def _data_array(name: str, a: np.ndarray, ncomp: int = 1) -> str:
    a = np.ascontiguousarray(a)
    raw = a.tobytes()
    payload = base64.b64encode(np.uint64(len(raw)).tobytes() + raw).decode("ascii")
    return (
        f'<DataArray type="{_VTK_TYPES[a.dtype]}" Name="{name}" NumberOfComponents="{ncomp}" format="binary">'
        f"{payload}</DataArray>\n"
    )


def vtp_bytes(pos: np.ndarray, fields: dict[str, np.ndarray]) -> bytes:
    """The .vtp document (bytes) of points pos (n, 3) with point-data arrays `fields` ((n,) or (n, 3))."""
    n = pos.shape[0]
    out = [
        '<?xml version="1.0"?>\n',
        '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" header_type="UInt64">\n',
        "<PolyData>\n",
        f'<Piece NumberOfPoints="{n}" NumberOfVerts="{n}" NumberOfLines="0" NumberOfStrips="0" NumberOfPolys="0">\n',
        "<PointData>\n",
    ]
    for name, a in fields.items():
        a = np.asarray(a)
        if a.dtype not in _VTK_TYPES:
            a = a.astype(np.float64)
        out.append(_data_array(name, a, a.shape[1] if a.ndim == 2 else 1))
    out += ["</PointData>\n", "<Points>\n", _data_array("Points", np.asarray(pos, dtype=np.float64), 3)]
    out += ["</Points>\n", "<Verts>\n"]
    out.append(_data_array("connectivity", np.arange(n, dtype=np.int64)))
    out.append(_data_array("offsets", np.arange(1, n + 1, dtype=np.int64)))
    out += ["</Verts>\n", "</Piece>\n", "</PolyData>\n", "</VTKFile>\n"]
    return "".join(out).encode("ascii")


class ParticleWriter:
    """Writes `<outdir>/<name>_NNNNNN.vtp` per output and the collection `<outdir>/<name>.pvd`."""

    def __init__(self, outdir: str | os.PathLike, name: str = "particles", comm=MPI.COMM_WORLD, entries=None):
        """Prepare the writer; files go to `outdir` (created if needed).

        `entries` [(time, file name), ...] continues a series after a restart (from the checkpoint).
        """
        self.outdir = Path(outdir)
        self.name = name
        self.comm = comm
        self.entries: list[tuple[float, str]] = [(float(t), str(f)) for t, f in (entries or [])]
        if comm.rank == 0:
            self.outdir.mkdir(parents=True, exist_ok=True)

    def write(self, t: float, particles) -> Path:
        """Write the owned particles of every rank at simulated time t (s); returns the .vtp path."""
        n = particles.n_owned
        local = {
            "pos": particles.pos[:n],
            "velocity": particles.vel[:n],
            "omega": particles.omega[:n],
            "diameter": particles.diameter[:n],
            "n_orig": particles.n_orig[:n],
            "gid": particles.gid[:n],
        }
        if self.comm.size > 1:
            parts = self.comm.gather(local, root=0)
            if self.comm.rank == 0:
                local = {k: np.concatenate([p[k] for p in parts]) for k in local}
        fname = f"{self.name}_{len(self.entries):06d}.vtp"
        entry = (float(t), fname)
        path = self.outdir / fname
        if self.comm.rank == 0:  # the entry is added once its files are written (a failed write leaves none)
            pos = local.pop("pos")
            atomic_write_bytes(path, vtp_bytes(pos, local))
            entries = [*self.entries, entry]
            rows = "".join(f'<DataSet timestep="{tt:.9g}" part="0" file="{f}"/>\n' for tt, f in entries)
            pvd = (
                '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
                f"<Collection>\n{rows}</Collection>\n</VTKFile>\n"
            )
            atomic_write_bytes(self.outdir / f"{self.name}.pvd", pvd.encode("ascii"))
        self.entries.append(entry)
        return path


def read_vtp(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Arrays of a .vtp written by `ParticleWriter` (for tests and post-processing): name -> array."""
    import xml.etree.ElementTree as ET

    root = ET.parse(path).getroot()
    out = {}
    for da in root.iter("DataArray"):
        raw = base64.b64decode(da.text.strip())
        size = int(np.frombuffer(raw[:8], dtype=np.uint64)[0])
        dtype = {"Float64": np.float64, "Int64": np.int64, "Int32": np.int32}[da.get("type")]
        a = np.frombuffer(raw[8 : 8 + size], dtype=dtype)
        ncomp = int(da.get("NumberOfComponents", "1"))
        out[da.get("Name")] = a.reshape(-1, ncomp) if ncomp > 1 else a
    return out
