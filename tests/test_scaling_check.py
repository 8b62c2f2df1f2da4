"""benchmarks/scaling_projection.py: the cores' pace of a 2-rank window from its probes (`core_pace`)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def projection():
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location("scaling_projection", BENCH / "scaling_projection.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        yield mod
    finally:
        sys.path.remove(str(BENCH))


def window(rank0, rank1, serial=None, message=None, memory=None):
    m1 = {"per_rank": [{"core_probe": serial or [1e-4] * len(rank0)}]}
    rows = [{"core_probe": list(rank0)}, {"core_probe": list(rank1)}]
    if message is not None:
        rows[0]["message_probe"] = message
    if memory is not None:
        for r, m in zip(rows, memory, strict=True):
            r["memory_probe"] = m
    return m1, {"per_rank": rows}


def test_equal_cores_keep_the_model(projection):
    m1, m2 = window([1e-4] * 40, [1e-4] * 40)
    pace = projection.core_pace(m1, m2)
    assert pace["uneven"] == pytest.approx(1.0, abs=1e-12) and pace["busy"] == pytest.approx(1.0, abs=1e-12)
    assert pace["samples"] == 40 and "latency" not in pace


def test_cores_slow_in_turn_set_the_pace_of_the_slower(projection):
    """Each core 20 % slower half of the time, in turn: every step goes at 1.2, the mean is 1.1."""
    slow, fast = [1.2e-4] * 20, [1e-4] * 20
    m1, m2 = window(slow + fast, fast + slow)
    pace = projection.core_pace(m1, m2)
    assert pace["uneven"] == pytest.approx(1.2 / 1.1, rel=1e-9)
    assert pace["busy"] == pytest.approx(1.1, rel=1e-9)


def test_one_interrupted_probe_is_not_the_pace(projection):
    spiked = [1e-4] * 40
    spiked[17] = 1e-3  # a timer interrupt inside one loop
    m1, m2 = window(spiked, [1e-4] * 40, message=[1e-6, 3e-6], memory=[[1e-3], [2e-3]])
    pace = projection.core_pace(m1, m2)
    assert pace["uneven"] == pytest.approx(1.0, abs=1e-12)
    assert pace["latency"] == pytest.approx(2e-6) and pace["latency_median"] == pytest.approx(2e-6)
    assert pace["memory_gbs"] == pytest.approx([16 * 2**20 / 1e-3 / 1e9, 16 * 2**20 / 2e-3 / 1e9])


def test_windows_without_probes_give_none(projection):
    m1, m2 = window([1e-4] * 5, [1e-4] * 5)
    m2["per_rank"][1]["core_probe"] = None
    assert projection.core_pace(m1, m2) is None
