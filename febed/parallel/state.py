"""Checkpoints of a distributed DEM: one rank-count-independent state from every rank's `DEM.get_state()`.

Write: `state = gather_state(dem)` (collective; the merged state on rank 0, None elsewhere) and save it.
Restart on any number of ranks: every rank reads it, `dem.set_state(state)`, then
`dem.attach_exchange(exchange, distribute=True)`: each rank keeps its cells' particles, and the contact history,
keyed by gid pairs, is restored at the first pair-list build.
"""

from __future__ import annotations

import numpy as np

_ROWS = "p_"
_KEYED = (("saved_keys", "saved_vals"), ("saved_wkeys", "saved_wvals"))


def merge_states(states: list[dict]) -> dict:
    """One state (rows ordered by gid, history keys sorted and unique) from the per-rank `DEM.get_state()` dicts."""
    if not states:
        raise ValueError("states: need at least one state")
    rows = [k for k in states[0] if k.startswith(_ROWS) and k != "p_next_gid"]
    rows += [k for k in states[0] if k.startswith("aux_")]
    out = {k: np.concatenate([np.asarray(s[k]) for s in states]) for k in rows}
    order = np.argsort(out["p_gid"], kind="stable")
    out = {k: v[order] for k, v in out.items()}
    if np.unique(out["p_gid"]).size != out["p_gid"].size:
        raise ValueError("states: a gid appears on several ranks")
    first = states[0]
    for k in ("dt", "time", "steps", "pl_skin", "since_sort"):
        out[k] = first[k]
    if "walls_count" in first:
        out["walls_count"] = first["walls_count"]
    out["pl_builds"] = max(int(s.get("pl_builds", 0)) for s in states)
    out["max_overlap"] = max(float(s.get("max_overlap", 0.0)) for s in states)
    out["p_next_gid"] = int(out["p_gid"].max()) + 1 if out["p_gid"].size else 0  # per-rank gid blocks start over
    out["pos_ref"] = out["p_pos"].copy()
    out["lists_valid"] = 0
    out["dirty"] = 1
    out["forces_valid"] = 0
    out["has_saved"] = 1
    for kk, vk in _KEYED:
        keys = np.concatenate([np.asarray(s.get(kk, np.zeros(0, np.int64)), dtype=np.int64) for s in states])
        vals = np.concatenate([np.asarray(s.get(vk, np.zeros((0, 3)))).reshape(-1, 3) for s in states])
        keys, first_idx = np.unique(keys, return_index=True)  # a pair across the partition is held twice
        out[kk], out[vk] = keys, vals[first_idx]
    return out


def gather_state(dem, root: int = 0) -> dict | None:
    """The merged state of a distributed DEM on `root` (None on the other ranks; collective). Serial: get_state."""
    if dem.exchange is None:
        return dem.get_state()
    states = dem.exchange.comm.gather(dem.get_state(), root=root)
    return merge_states(states) if dem.exchange.rank == root else None
