"""Fast Numba typing of the NamedTuple records febed's kernels take (`fast_typeof`).

Numba types a plain numpy argument in C, from a cache, but a tuple argument in Python, field by field:
`numba.typeof` builds a `types.Array` for every array of the record, which costs about 20 µs each (type
interning, hashing). A record of 10-20 arrays passed to a kernel thousands of times a simulated second then
costs more than a small bed's kernels themselves (the seed-000 study's TM l = 2 bed spent about a fifth of
its run typing records). `fast_typeof` registers, for one record class, a typeof that keys each record on
what its Numba type depends on (per array: dtype, ndim, contiguity, writeable; per scalar: its Python type,
and for integers whether they fit in int64; nested records recursively) and returns the type computed once
for that key by Numba's own rule for tuples (`numba.core.typing.typeof._typeof_tuple`, a Numba internal:
`tests/test_kernel_records.py` checks the keyed types against it for every kind of field).
"""

from __future__ import annotations

import numpy as np
from numba.core.typing.typeof import _typeof_tuple, typeof_impl

_INT64 = (-(2**63), 2**63 - 1)


def _key(value):
    """What the Numba type of `value` depends on; None if it is of a kind this module does not key."""
    if isinstance(value, np.ndarray):
        flags = value.flags
        return (value.dtype, value.ndim, flags.c_contiguous, flags.f_contiguous, flags.writeable)
    kind = type(value)
    if kind is float or kind is bool:
        return kind
    if kind is int:
        return (int, _INT64[0] <= value <= _INT64[1])
    if isinstance(value, tuple) and hasattr(kind, "_fields"):
        keys = tuple(_key(v) for v in value)
        return None if any(k is None for k in keys) else (kind, keys)
    return None  # numpy scalars, strings, ...: typed by Numba each time


def fast_typeof(cls: type) -> type:
    """Class decorator: register the keyed typeof of the NamedTuple class `cls` with Numba; returns `cls`."""
    cache: dict = {}

    @typeof_impl.register(cls)
    def _typeof_record(value, c):
        key = _key(value)
        if key is None:
            return _typeof_tuple(value, c)
        key = (key, c.purpose)
        ty = cache.get(key)
        if ty is None:
            ty = cache[key] = _typeof_tuple(value, c)
        return ty

    return cls


__all__ = ["fast_typeof"]
