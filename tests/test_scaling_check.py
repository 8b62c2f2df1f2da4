"""benchmarks/scaling_projection.py: the cores' pace of a 2-rank window from its probes (`core_pace`), a busy
core's slow-down from the concurrent window (`load_factor`), the costs per unit of work (`unit_costs`: a check's
own window, the DEM's parallel code path, the coupling's filter per node) and the solver's counts."""

from __future__ import annotations

import importlib.util
import json
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


def concurrent(split, waits, steps=100):
    """A `--concurrent` window: every core's phase seconds (its start barrier included) and barrier waits."""
    rows = zip(split, waits, strict=True)
    return {"per_rank": [{"split": dict(sp), "waits": dict(w), "gas_steps": steps} for sp, w in rows]}


def test_busy_core_pays_the_wait_at_its_phase_end(projection):
    """A phase's time on a busy core: its work, less the barrier at its start, plus the one before the next phase."""
    serial = {"per_rank": [{"split": {"dem": 10.0, "coupling": 4.0, "gas": 8.0}, "gas_steps": 100}]}
    waits = {"dem": 0.5, "coupling": 0.3, "gas": 0.2, "untimed": 0.4}
    split = {"dem": 11.0, "coupling": 4.6, "gas": 8.2}
    f = projection.load_factor(serial, concurrent([split, split], [waits, waits]))
    assert f["dem"] == pytest.approx((11.0 - 0.5 + 0.3) / 10.0, rel=1e-12)  # the wait for the DEM's end
    assert f["coupling"] == pytest.approx((4.6 - 0.3 + 0.5 + 0.2) / 4.0, rel=1e-12)  # two coupling parts per step
    assert f["gas"] == pytest.approx((8.2 - 0.2 + 0.4) / 8.0, rel=1e-12)
    # every barrier counted once: the phases add up to the cores' timed seconds and the untimed barrier
    total = sum(f[k] * serial["per_rank"][0]["split"][k] for k in f)
    assert total == pytest.approx(sum(split.values()) + waits["untimed"], rel=1e-12)


def test_busy_core_factor_per_gas_step(projection):
    """A concurrent window of twice the serial window's gas steps at the same pace is not slower."""
    serial = {"per_rank": [{"split": {"dem": 10.0, "coupling": 4.0, "gas": 8.0}, "gas_steps": 100}]}
    zero = {"dem": 0.0, "coupling": 0.0, "gas": 0.0, "untimed": 0.0}
    doubled = {"dem": 20.0, "coupling": 8.0, "gas": 16.0}
    f = projection.load_factor(serial, concurrent([doubled, doubled], [zero, zero], steps=200))
    assert f == pytest.approx({"dem": 1.0, "coupling": 1.0, "gas": 1.0}, rel=1e-12)
    assert projection.load_factor(serial, None) == {"dem": 1.0, "coupling": 1.0, "gas": 1.0}


def serial_window(gas, steps, dem=6.0, coupling=2.0):
    sample = {"pairs": 1000, "owned": 100, "nodes_owned": 50}
    row = {"t0": 0.0, "t1": steps * 1e-4, "gas_steps": steps, "dem_steps": 8 * steps, "builds": steps // 2,
           "split": {"dem": dem, "coupling": coupling, "gas": gas}, "samples": [sample]}  # fmt: skip
    return {"per_rank": [row]}


def test_check_takes_the_parallel_solver_as_a_ratio_to_its_own_window(projection):
    """The CG + GAMG window was measured beside the base window: 0.9 of its gas time per step. A check's serial
    window, slower per step, keeps that ratio rather than the GAMG window's absolute seconds."""
    base, gamg = serial_window(10.0, 100), serial_window(9.0, 100)
    own = serial_window(16.0, 200)
    cost = projection.unit_costs(own, gamg, iter_of=base)
    assert cost["us_per_node_step_iter"] == pytest.approx(1e6 * 16.0 * 0.9 / (200 * 50), rel=1e-12)
    assert cost["us_per_node_step"] == pytest.approx(1e6 * 16.0 / (200 * 50), rel=1e-12)
    # without iter_of the GAMG window is the base's own companion: its seconds per step
    same = projection.unit_costs(base, gamg)
    assert same["us_per_node_step_iter"] == pytest.approx(1e6 * 9.0 / (100 * 50), rel=1e-12)


def test_dem_on_several_ranks_costs_its_parallel_code_path(projection):
    """The staged window (the DEM's parallel code path on one process) sets the DEM's cost per pair on several
    ranks, as a ratio to the window it was measured beside; its rebuilds key the history, so that is not added."""
    base = serial_window(10.0, 100, dem=6.0)
    staged = serial_window(10.0, 100, dem=7.2)
    row = {"rebuild": [0.010, 0.011], "rebuild_keyed": [0.018, 0.019], "rebuild_staged": [0.013, 0.014],
           "locate": [0.001, 0.001], "rebuild_loads": {"pairs": 1000, "owned": 100}}  # fmt: skip
    rebuild = {"per_rank": [row]}
    own = serial_window(16.0, 200, dem=15.0)
    cost = projection.unit_costs(own, None, rebuild, staged=staged, iter_of=base)
    assert cost["us_per_pair_step_staged"] == pytest.approx(cost["us_per_pair_step"] * 1.2, rel=1e-12)
    assert cost["us_per_pair_keyed_rebuild"] == 0.0
    assert cost["us_per_particle_locate"] == pytest.approx(1e6 * 0.001 / 100, rel=1e-12)
    # without the staged window: the parallel rebuild's own work from its code path on one process (medians)
    plain = projection.unit_costs(base, None, rebuild)
    assert plain["us_per_pair_step_staged"] == plain["us_per_pair_step"]
    assert plain["us_per_pair_keyed_rebuild"] == pytest.approx(1e6 * (0.014 - 0.011) / 1000, rel=1e-12)


def test_another_solvers_counts_take_the_default_solvers_scale(projection, tmp_path):
    """Counts of another solver on the same benchmark are scaled like the default's (not by their own 2-rank
    counts, which a bubbling-bed window of the default solver says nothing about); the busiest rank's flops
    come along unscaled."""
    ranks = [2, 4, 8, 16, 32, 64]
    row = {"messages": [10.0, 12.0], "bytes": [100.0, 80.0], "reductions": [4.0, 4.0], "flops": [5.0, 7.0]}
    data = {level: {str(P): row for P in ranks} for level in ("intermediate", "fine")}
    path = tmp_path / "counts.json"
    path.write_text(json.dumps(data))
    out = projection.solver_counts(path=path, scale={"messages": 2.0, "bytes": 0.5, "reductions": 1.0})
    assert out["C2"][16] == {"messages": 24.0, "bytes": 50.0, "reductions": 4.0, "flops": 7.0}
    assert out["C3"][64]["messages"] == 24.0


def test_the_couplings_work_over_the_nodes_is_counted_per_node(projection):
    """A rank filters over its owned and halo nodes: the measured nodal part of the coupling is taken out of the
    cost per particle and given per node, so that one process's total is unchanged."""
    base = serial_window(10.0, 100, coupling=10.0)  # 0.1 s of coupling per gas step, 100 particles, 50 nodes
    row = {"rebuild": [0.01, 0.01], "rebuild_keyed": [0.02, 0.02], "locate": [0.001, 0.001],
           "rebuild_loads": {"pairs": 1000, "owned": 100}, "coupling_nodes": [0.002, 0.0021]}  # fmt: skip
    cost = projection.unit_costs(base, None, {"per_rank": [row]})
    assert cost["us_per_node_coupling"] == pytest.approx(1e6 * 0.002 / 50, rel=1e-12)
    assert cost["us_per_particle_step"] == pytest.approx(1e6 * (0.1 - 0.002) / 100, rel=1e-12)
    total = cost["us_per_particle_step"] * 100 + cost["us_per_node_coupling"] * 50
    assert total == pytest.approx(1e6 * 0.1, rel=1e-12)
