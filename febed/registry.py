"""Name -> function registries for physics closures (drag laws, contact laws, coarse-grain models).

One registry per kind of closure. A closure module registers each law with a decorator; the case
schema asks the registry for the valid names, so a new law is one function and one decorator line and
the case validation learns its name by itself.

Example:
    >>> DRAG = Registry("drag law", "febed.coupling.drag")
    >>> @DRAG.register("stokes")
    ... def stokes(...): ...
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any


class Registry:
    """A named collection of closures, filled lazily by importing the module(s) that define them."""

    def __init__(self, kind: str, *modules: str):
        """Create an empty registry of `kind` (e.g. "drag law") whose entries live in `modules`."""
        self.kind = kind
        self._modules = modules
        self._entries: dict[str, Any] = {}
        self._loaded = False

    def register(self, name: str) -> Callable[[Any], Any]:
        """Decorator registering `obj` under `name`; a duplicate name is a programming error."""

        def deco(obj: Any) -> Any:
            if name in self._entries and self._entries[name] is not obj:
                raise ValueError(f"{self.kind} {name!r} is registered twice")
            self._entries[name] = obj
            return obj

        return deco

    def _load(self) -> None:
        if not self._loaded:
            self._loaded = True
            for mod in self._modules:
                importlib.import_module(mod)

    def names(self) -> list[str]:
        """Sorted names of every registered entry."""
        self._load()
        return sorted(self._entries)

    def get(self, name: str) -> Any:
        """The entry registered under `name`; a clear KeyError listing the valid names otherwise."""
        self._load()
        try:
            return self._entries[name]
        except KeyError:
            raise KeyError(f"unknown {self.kind} {name!r}; choose one of {', '.join(self.names())}") from None

    def __contains__(self, name: str) -> bool:
        self._load()
        return name in self._entries
