"""Field output: nodal gas fields (u, p, ε, ...) written as one XDMF time series that ParaView opens.

The mesh is written once; each call of `write(t)` appends every function at time t. P1/Q1 nodal
functions on a degree-1 mesh are written directly (no interpolation); works serially and with MPI (the
file is written collectively through HDF5).
"""

from __future__ import annotations

from pathlib import Path

from mpi4py import MPI

import dolfinx.io


class FieldWriter:
    """XDMF time series of a fixed set of DOLFINx Functions on one mesh."""

    def __init__(self, path: str | Path, mesh, functions: dict, comm=MPI.COMM_WORLD):
        """Open `path` (.xdmf, an .h5 beside it) and write the mesh; `functions` maps names to Functions."""
        path = Path(path)
        if path.suffix != ".xdmf":
            raise ValueError(f"path must end in .xdmf, got {str(path)!r}")
        if not functions:
            raise ValueError("functions: give at least one name -> Function to write")
        self.path = path
        self.functions = dict(functions)
        for name, f in self.functions.items():
            f.name = name
        if comm.rank == 0:
            path.parent.mkdir(parents=True, exist_ok=True)
        comm.barrier()
        self._file = dolfinx.io.XDMFFile(comm, str(path), "w")
        self._file.write_mesh(mesh)
        self.count = 0

    def write(self, t: float) -> None:
        """Append every function at time t [s] (collective)."""
        for f in self.functions.values():
            self._file.write_function(f, t)
        self.count += 1

    def close(self) -> None:
        """Close the file (collective)."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> FieldWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
