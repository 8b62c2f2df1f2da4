"""A distributed PETSc matrix filled from coordinate (COO) entries through PETSc's own COO assembly.

PETSc ≥ 3.18 can take a matrix's entries as (row, column) pairs once (`MatSetPreallocationCOO`) and then,
at every refill, only their values (`MatSetValuesCOO`): it sums repeated entries and sends the rows owned by
other ranks with a communication plan made once. petsc4py 3.18 does not wrap the two calls, so they are
reached through the PETSc library that petsc4py loaded. The drag-weighted pressure operator is refilled at
every gas step on several ranks (`febed.gas.weighted`); inserting it row by row (`MatSetValues`, a search
for every entry's column) cost more than the rest of its assembly.

`coo_matrix` returns None where the library or the calls cannot be found; the caller then inserts by rows.
"""

from __future__ import annotations

import ctypes

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np

_LIB = None  # the PETSc library petsc4py uses, once found (False when it cannot be)


def _library():
    """A ctypes handle on the PETSc shared library in this process, or None."""
    global _LIB
    if _LIB is None:
        _LIB = False
        paths = []
        try:
            with open("/proc/self/maps") as f:  # the libraries loaded (Linux)
                paths = sorted({line.split()[-1] for line in f if "libpetsc" in line and ".so" in line})
        except OSError:
            pass
        paths.append(PETSc.__file__)  # a petsc4py linked statically against PETSc
        for path in paths:
            try:
                lib = ctypes.CDLL(path)
            except OSError:
                continue
            if hasattr(lib, "MatSetPreallocationCOO") and hasattr(lib, "MatSetValuesCOO"):
                lib.MatSetPreallocationCOO.argtypes = [ctypes.c_void_p, ctypes.c_ssize_t]
                lib.MatSetPreallocationCOO.argtypes += [ctypes.c_void_p, ctypes.c_void_p]
                lib.MatSetValuesCOO.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]
                _LIB = lib
                break
    return _LIB or None


class COOMatrix:
    """An MPI AIJ matrix with a fixed list of (global row, global column) entries, refilled by `fill`."""

    def __init__(self, comm, n_owned: int, rows: np.ndarray, cols: np.ndarray, lib):
        self.lib = lib
        self.n = rows.size
        self.M = PETSc.Mat().create(comm=comm)
        self.M.setSizes(((n_owned, PETSc.DECIDE), (n_owned, PETSc.DECIDE)))
        self.M.setType(PETSc.Mat.Type.AIJ)
        # PETSc may overwrite the index arrays it is given: pass copies in its integer type
        i = np.array(rows, dtype=PETSc.IntType)
        j = np.array(cols, dtype=PETSc.IntType)
        self._check(lib.MatSetPreallocationCOO(self.M.handle, self.n, i.ctypes.data, j.ctypes.data), "preallocation")

    def fill(self, vals: np.ndarray) -> None:
        """The matrix becomes the sum of the entries' values (collective; no separate assembly)."""
        v = np.ascontiguousarray(vals, dtype=PETSc.ScalarType)
        if v.size != self.n:
            raise ValueError(f"COO fill: {v.size} values for {self.n} entries")
        self._check(self.lib.MatSetValuesCOO(self.M.handle, v.ctypes.data, int(PETSc.InsertMode.INSERT)), "fill")

    @staticmethod
    def _check(code: int, what: str) -> None:
        if code != 0:
            raise RuntimeError(f"PETSc COO {what} failed with error code {code}")


def coo_matrix(comm, n_owned: int, rows: np.ndarray, cols: np.ndarray) -> COOMatrix | None:
    """A `COOMatrix` over the given global entries, or None if this PETSc offers no COO assembly (collective)."""
    lib = _library() if PETSc.Sys.getVersion() >= (3, 18, 0) else None  # the signatures used here
    ok = comm.allreduce(lib is not None, op=MPI.LAND)
    return COOMatrix(comm, n_owned, rows, cols, lib) if ok else None
