"""Field output: nodal gas fields (u, p, ε, ...) written as one XDMF time series that ParaView opens.

Layout (for `fields.xdmf`): the index `fields.xdmf` and a folder `fields/` holding the mesh (`mesh.h5`) and
one HDF5 file per output time (`000000.h5`, `000001.h5`, ...). P1/Q1 nodal functions on a degree-1 mesh are
written directly (no interpolation); works serially and with MPI (each file is written collectively through
HDF5 by DOLFINx).

**Crash-safe.** An HDF5 file that is open for writing when its process dies is unreadable as a whole (its
superblock and object headers are written at close), so one file held open for a run would lose every field of
the run to a `kill -9`, an out-of-memory kill or a batch system's time limit. Each output time is therefore
its own file: written under a temporary name (`.<k>.tmp.h5`), closed, flushed to disk, renamed, and only then
added to the index, which is itself replaced atomically (`febed.io.atomic`). Every file the index names is
complete; a process killed during a write leaves at most that write's temporary files, which the folder's
next run removes (`remove_temporaries`).

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
import xml.etree.ElementTree as ET
from contextlib import contextmanager, suppress
from pathlib import Path

from mpi4py import MPI

import dolfinx.io
import dolfinx.log

from febed.io import atomic
from febed.io.atomic import atomic_write_text, publish

XINCLUDE = "http://www.w3.org/2001/XInclude"
ET.register_namespace("xi", XINCLUDE)


class FieldWriter:
    """XDMF time series of a fixed set of DOLFINx Functions on one mesh, one HDF5 file per output time."""

    def __init__(self, path: str | Path, mesh, functions: dict, comm=MPI.COMM_WORLD):
        """Write the mesh into the folder beside `path` (.xdmf) and an index without times.

        `functions` maps names to Functions. Raises OSError if a file cannot be written (its folder: on every rank).
        """
        path = Path(path)
        if path.suffix != ".xdmf":
            raise ValueError(f"path must end in .xdmf, got {str(path)!r}")
        if not functions:
            raise ValueError("functions: give at least one name -> Function to write")
        self.path = path
        self.folder = path.with_suffix("")
        self.comm = comm
        self.functions = dict(functions)
        for name, f in self.functions.items():
            f.name = name
        self.count = 0
        self._series: dict[str, ET.Element] = {}  # rank 0: each function's temporal collection
        self._mesh_grid = None
        problem = None
        if comm.rank == 0:
            try:
                self.folder.mkdir(parents=True, exist_ok=True)
                for old in self.folder.glob("[0-9]*.h5"):  # a series of this name that a restart replaces
                    old.unlink()
            except OSError as e:
                problem = e
        problem = comm.bcast(problem, root=0)  # every rank waits for the folder, and raises rank 0's error
        if problem is not None:
            raise problem
        root = self._write_file("mesh", lambda file: file.write_mesh(mesh))
        if root is not None:
            self._mesh_grid = root.find("Domain/Grid")
            self._write_index()

    def write(self, t: float) -> None:
        """Write every function at time t [s] into a file of its own, then add it to the index (collective).

        OSError if a file cannot be written.
        """

        def fill(file):
            with _quiet():  # DOLFINx warns that the file has no mesh: the index holds it
                for f in self.functions.values():
                    file.write_function(f, t)

        root = self._write_file(f"{self.count:06d}", fill)
        if root is not None:
            for grid in root.findall("Domain/Grid"):
                name = grid.get("Name")
                series = self._series.setdefault(name, ET.Element("Grid", grid.attrib))
                series.extend(grid.findall("Grid"))
            self._write_index()
        self.count += 1

    def close(self) -> None:
        """Nothing stays open between writes; kept so that a FieldWriter closes like every other writer."""

    def __enter__(self) -> FieldWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------ files
    def _write_file(self, stem: str, fill) -> ET.Element | None:
        """`fill(XDMFFile)` into `<folder>/<stem>.h5` through a temporary name (collective).

        Returns, on rank 0, the temporary XDMF document with its data items pointing at the final file (as
        seen from the index); None on the other ranks.
        """
        tmp = self.folder / f".{stem}.tmp.xdmf"  # (TMP_SUFFIXES: removed if a kill leaves it, and its .h5)
        final = self.folder / f"{stem}.h5"
        with hdf5_errors(final):
            file = dolfinx.io.XDMFFile(self.comm, str(tmp), "w")
            try:
                fill(file)
            except BaseException:
                with suppress(RuntimeError):
                    file.close()
                raise
            file.close()
        if self.comm.rank != 0:
            return None
        root = ET.parse(tmp).getroot()
        tmp_h5 = tmp.with_suffix(".h5")
        target = f"{self.folder.name}/{final.name}"
        for item in root.iter("DataItem"):
            file_name, sep, dataset = (item.text or "").strip().partition(":")
            if sep and file_name == tmp_h5.name:
                item.text = f"{target}:{dataset}"
        publish(tmp_h5, final)
        tmp.unlink()
        return root

    def _write_index(self) -> None:
        """Replace the index (rank 0): the mesh, then each function's series of times."""
        root = ET.Element("Xdmf", {"Version": "3.0"})
        domain = ET.SubElement(root, "Domain")
        domain.append(self._mesh_grid)
        for name in self.functions:
            if name in self._series:
                domain.append(self._series[name])
        ET.indent(root, space="  ")
        body = ET.tostring(root, encoding="unicode")
        if f'xmlns:xi="{XINCLUDE}"' not in body:  # (only serialised once an xi:include is in the tree)
            body = body.replace("<Xdmf ", f'<Xdmf xmlns:xi="{XINCLUDE}" ', 1)
        atomic_write_text(self.path, '<?xml version="1.0"?>\n<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>\n' + body + "\n")


TMP_SUFFIXES = ("tmp.h5", "tmp.xdmf")  # the temporary files of a write, .<stem>.tmp.h5 and .xdmf (glob ".*.*<suffix>")


def remove_temporaries(outdir: str | Path) -> list[Path]:
    """Remove the temporary files of field writes that never finished (a run killed while writing).

    Looks in every field series folder of the run folder `outdir` (`fields/`, `fields.restart<k>/`). Call it
    only while holding the run folder's lock (`febed.io.rundir.lock_output`). Returns the files removed.
    """
    return [
        f
        for folder in sorted(Path(outdir).glob("fields*/"))
        for suffix in TMP_SUFFIXES
        for f in atomic.remove_temporaries(folder, "*", suffix)
    ]


@contextmanager
def _quiet():
    """DOLFINx's log below errors silenced inside the block."""
    level = dolfinx.log.get_log_level()
    dolfinx.log.set_log_level(dolfinx.log.LogLevel.ERROR)
    try:
        yield
    finally:
        dolfinx.log.set_log_level(level)


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
