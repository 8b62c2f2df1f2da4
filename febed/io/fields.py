"""Field output: nodal gas fields (u, p, ε, ...) written as one XDMF time series that ParaView opens.

The mesh is written once; each call of `write(t)` appends every function at time t. P1/Q1 nodal
functions on a degree-1 mesh are written directly (no interpolation); works serially and with MPI (the
file is written collectively through HDF5).

A failed write (a full disk, an I/O error) raises OSError naming the file and the operating system's error,
as any other file write does: DOLFINx reports HDF5's failures as a bare RuntimeError ("Failed to close HDF5
dataset."), so while a `FieldWriter` writes, HDF5's own error report (normally printed to stderr as a long
stack) is read instead of printed (`hdf5_errors`), and its operating-system error is put into the OSError.
"""

from __future__ import annotations

import ctypes
import errno as errnos
import os
import re
from contextlib import contextmanager
from pathlib import Path

from mpi4py import MPI

import dolfinx.io


class FieldWriter:
    """XDMF time series of a fixed set of DOLFINx Functions on one mesh."""

    def __init__(self, path: str | Path, mesh, functions: dict, comm=MPI.COMM_WORLD):
        """Open `path` (.xdmf, an .h5 beside it) and write the mesh; `functions` maps names to Functions.

        Raises OSError (on the ranks where HDF5 failed) if the file cannot be written.
        """
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
        self._file = None
        self.count = 0
        with hdf5_errors(path):
            self._file = dolfinx.io.XDMFFile(comm, str(path), "w")
            self._file.write_mesh(mesh)

    def write(self, t: float) -> None:
        """Append every function at time t [s] (collective); OSError if the file cannot be written."""
        with hdf5_errors(self.path):
            for f in self.functions.values():
                self._file.write_function(f, t)
        self.count += 1

    def close(self) -> None:
        """Close the file (collective); a second call does nothing, even after a failed close (OSError)."""
        file, self._file = self._file, None
        if file is not None:
            with hdf5_errors(self.path):
                file.close()

    def __enter__(self) -> FieldWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ----------------------------------------------------------------------------------- HDF5's error reports
class _H5Error(ctypes.Structure):
    _fields_ = [
        ("cls_id", ctypes.c_int64), ("maj_num", ctypes.c_int64), ("min_num", ctypes.c_int64),
        ("line", ctypes.c_uint), ("func_name", ctypes.c_char_p), ("file_name", ctypes.c_char_p),
        ("desc", ctypes.c_char_p),
    ]  # fmt: skip


_WALK = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_uint, ctypes.POINTER(_H5Error), ctypes.c_void_p)
_AUTO = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_int64, ctypes.c_void_p)
_OS_ERROR = re.compile(r"errno = (\d+), error message = '([^']*)'")


class _Hdf5Reports:
    """HDF5's automatic error report, replaced (once per process) by one that keeps the report's lines.

    Outside a `hdf5_errors` block the report is printed as HDF5 would; inside, it is kept in `lines`.
    """

    def __init__(self):
        self.lib = None
        self.capturing = 0
        self.lines: list[str] = []
        self._walk = _WALK(self._line)
        self._auto = _AUTO(self._report)
        try:
            with open("/proc/self/maps") as maps:
                path = next(line.split()[-1] for line in maps if "libhdf5" in line.split()[-1])
            lib = ctypes.CDLL(path)
            lib.H5Ewalk2.argtypes = [ctypes.c_int64, ctypes.c_int, _WALK, ctypes.c_void_p]
            lib.H5Eprint2.argtypes = [ctypes.c_int64, ctypes.c_void_p]
            lib.H5Eset_auto2.argtypes = [ctypes.c_int64, _AUTO, ctypes.c_void_p]
            if lib.H5Eset_auto2(0, self._auto, None) >= 0:  # 0: H5E_DEFAULT, this thread's error stack
                self.lib = lib
        except (OSError, StopIteration, AttributeError):  # not Linux, or no HDF5 loaded: DOLFINx's message only
            self.lib = None

    def _line(self, n, err, data) -> int:
        desc = err.contents.desc
        self.lines.append(desc.decode(errors="replace") if desc else "")
        return 0

    def _report(self, stack, data) -> int:
        if not self.capturing:
            return self.lib.H5Eprint2(stack, None)
        self.lines = []
        self.lib.H5Ewalk2(stack, 0, self._walk, None)  # 0: H5E_WALK_UPWARD, the innermost failure first
        return 0

    def os_error(self) -> tuple[int, str] | None:
        """(errno, message) of the operating-system error in the last report kept, if it names one."""
        for line in self.lines:
            m = _OS_ERROR.search(line)
            if m:
                return int(m.group(1)), m.group(2)
        return None


_REPORTS: _Hdf5Reports | None = None


@contextmanager
def hdf5_errors(path: Path):
    """Turn the RuntimeError of a failed DOLFINx XDMF/HDF5 write inside the block into an OSError on `path`.

    The OSError carries the operating system's error found in HDF5's report (e.g. ENOSPC, "No space left on
    device"), or EIO with DOLFINx's message when the report names none. HDF5's report is not printed.
    """
    global _REPORTS
    if _REPORTS is None:
        _REPORTS = _Hdf5Reports()
    reports = _REPORTS
    reports.capturing += 1
    reports.lines = []
    try:
        yield
    except RuntimeError as e:
        if type(e) is not RuntimeError:  # one of febed's own errors, not DOLFINx's
            raise
        found = reports.os_error()
        h5 = Path(path).with_suffix(".h5")
        if found is not None:
            raise OSError(found[0], found[1], str(h5)) from None
        raise OSError(errnos.EIO, f"HDF5 write failed ({e}){_space_note(h5)}", str(h5)) from None
    finally:
        reports.capturing -= 1


def _space_note(path: Path) -> str:
    """', its file system is full' when the folder of `path` has no space left, else ''."""
    try:
        st = os.statvfs(Path(path).parent)
    except OSError:
        return ""
    return "; its file system is full" if st.f_bavail * st.f_frsize < 65536 else ""
