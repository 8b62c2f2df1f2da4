"""The keyed typeof of kernel records (`febed.kernel_records`) gives Numba's own type for every kind of field."""

from collections import namedtuple
from typing import NamedTuple

import numpy as np
import pytest
from numba import njit
from numba.core.typing.typeof import Purpose, _typeof_tuple

from febed.kernel_records import _key, fast_typeof

Params = namedtuple("Params", "k e")


@fast_typeof
class Rec(NamedTuple):
    a: np.ndarray
    b: np.ndarray
    n: int
    x: float
    flag: bool
    p: tuple


class _Argument:
    """A typeof context for arguments (what a kernel call uses)."""

    purpose = Purpose.argument


def numba_default(rec):
    """What Numba gives without the registration: its rule for tuples, field by field."""
    return _typeof_tuple(rec, _Argument())


def variants():
    base = np.arange(12.0).reshape(3, 4)
    ro = np.ones(3)
    ro.flags.writeable = False
    return [
        Rec(np.zeros(3), base, 3, 1.0, True, Params(1.0, 0.5)),
        Rec(np.zeros(3, np.int32), base, 3, 1.0, True, Params(1.0, 0.5)),  # another dtype
        Rec(np.zeros(3), np.asfortranarray(base), 3, 1.0, True, Params(1.0, 0.5)),  # F layout
        Rec(np.zeros(3), base[:, ::2], 3, 1.0, True, Params(1.0, 0.5)),  # A layout
        Rec(ro, base, 3, 1.0, True, Params(1.0, 0.5)),  # read-only
        Rec(np.zeros((3, 1)), base, 3, 1.0, True, Params(1.0, 0.5)),  # another ndim
        Rec(np.zeros(3), base, 2**63, 1.0, True, Params(1.0, 0.5)),  # an int beyond int64 (uint64)
        Rec(np.zeros(3), base, 3, 1.0, True, Params(1, 0.5)),  # a nested int instead of float
        Rec(np.zeros(3), base, np.int64(3), 1.0, True, Params(1.0, 0.5)),  # a NumPy scalar: not keyed
    ]


def test_every_variant_gets_numbas_own_type_and_the_cache_never_mixes_them():
    from numba import typeof

    seen = {}
    for _ in range(2):  # the second pass is served from the cache
        for i, rec in enumerate(variants()):
            got = typeof(rec)
            assert got == numba_default(rec), i
            seen.setdefault(i, got)
            assert seen[i] == got
    assert len({str(t) for t in seen.values()}) == len(seen) - 1  # the NumPy-scalar variant types as the first


def test_numpy_scalars_are_not_keyed():
    assert _key(np.float64(1.0)) is None
    assert _key(Rec(np.zeros(3), np.zeros(3), np.int64(1), 1.0, True, Params(1.0, 0.5))) is None
    assert _key(Rec(np.zeros(3), np.zeros(3), 1, 1.0, True, Params(1.0, 0.5))) is not None


@njit(cache=False)
def _total(rec):
    return rec.a.sum() + rec.b.sum() + rec.n + rec.x + rec.p.k


def test_a_kernel_called_with_changing_layouts_compiles_one_signature_per_type():
    recs = variants()[:4]
    for rec in recs:
        assert _total(rec) == pytest.approx(rec.a.sum() + rec.b.sum() + rec.n + rec.x + rec.p.k)
    assert len(_total.signatures) == 4
