"""Where Numba caches febed's compiled kernels: a folder keyed on the kernels' sources, so it cannot go stale.

Numba invalidates a cached kernel when the file that defines it changes, but not when a function it
inlines from another file does: a force loop in `febed/dem/forces.py` compiled with a contact law of
`febed/dem/contact.py` would keep the old law after the law is edited. febed therefore caches every kernel
under a folder named after a hash of the sources of all its Numba modules (every febed module that imports
Numba) and of the febed modules they import from. Editing any of them moves the cache to a new folder: the
kernels compile once again, and no stale machine code is ever loaded.

The base folder is `NUMBA_CACHE_DIR` if set, otherwise `$XDG_CACHE_HOME/febed/numba` (`~/.cache/febed/numba`),
so `make test`, plain `pytest`, the demos and `febed run` share one cache. Folders of older sources are left
in place (delete the base folder to reclaim the space). `configure()` runs when `febed` is imported, before
any kernel is defined; it does not import Numba.
"""

from __future__ import annotations

import hashlib
import os
import re
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent
KEYED = re.compile(r"^febed-kernels-[0-9a-f]{16}$")  # the folder name configure() appends to the base
_IMPORT = re.compile(r"^\s*(?:from\s+febed\.([\w.]+)\s+import|import\s+febed\.([\w.]+))", re.MULTILINE)


def _module_file(name: str) -> Path | None:
    """The source file of febed module `febed.<name>` (a package's __init__.py), if it exists."""
    base = PACKAGE.joinpath(*name.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def kernel_sources() -> list[Path]:
    """Every febed module that uses Numba, and every febed module one of them imports, sorted by path."""
    files = set()
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        if "numba" not in text:
            continue
        files.add(path)
        for match in _IMPORT.finditer(text):
            dep = _module_file(match.group(1) or match.group(2))
            if dep is not None:
                files.add(dep)
    return sorted(files)


def source_key() -> str:
    """16 hex digits of a hash of `kernel_sources()` (their paths relative to the package and contents)."""
    h = hashlib.sha256()
    for path in kernel_sources():
        h.update(str(path.relative_to(PACKAGE)).encode())
        h.update(b"\0")
        h.update(path.read_bytes())
        h.update(b"\0")
    return h.hexdigest()[:16]


def base_dir() -> Path:
    """The folder holding the keyed caches: NUMBA_CACHE_DIR (without a keyed folder already appended) or XDG."""
    env = os.environ.get("NUMBA_CACHE_DIR", "")
    if env:
        path = Path(env)
        return path.parent if KEYED.match(path.name) else path
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg) / "febed" / "numba"


def configure() -> Path:
    """Point Numba's cache at `base_dir()/febed-kernels-<source_key()>` (environment and, if loaded, Numba's config).

    The environment variable carries the folder to child processes (MPI ranks, test subprocesses), which
    recompute their own key from their own sources. Returns the folder.
    """
    folder = base_dir() / f"febed-kernels-{source_key()}"
    os.environ["NUMBA_CACHE_DIR"] = str(folder)
    config = sys.modules.get("numba.core.config")
    if config is not None:  # Numba was imported first: its config has read the environment already
        config.CACHE_DIR = str(folder)
    return folder
