"""The gas and DEM states as checkpoint arrays: what a checkpoint holds and how a run takes it back.

Arrays are named `gas/<key>` (`VANSSolver.get_state` at the owned nodes, with their coordinates `gas/x`, so that
a restart on another number of ranks finds its nodes by position) and `dem/<key>` (`DEM.get_state`: every
particle array by row, `p_*`, the contact history keyed by global-id pairs and, on one rank, the neighbour
lists themselves so that a serial restart continues bit for bit). `gather` makes them independent of the
rank count on rank 0; `restore_gas` and `load_dem` put them back on any number of ranks.
"""

from __future__ import annotations

from mpi4py import MPI

import numpy as np

from febed.io.checkpoint import CheckpointError, gather_rows, match_nodes

_ROWS = "p_"  # DEM state keys holding one row per particle
_HISTORY = ("saved_keys", "saved_vals", "saved_wkeys", "saved_wvals")


def gas_arrays(gas) -> dict[str, np.ndarray]:
    """This rank's gas state as checkpoint arrays `gas/<key>` (copies), with the owned nodes' coordinates."""
    arrays = {f"gas/{k}": v for k, v in gas.get_state().items()}
    arrays["gas/x"] = gas.x[: gas.n_owned].copy()
    return arrays


def restore_gas(gas, arrays: dict[str, np.ndarray], t: float, comm=MPI.COMM_WORLD) -> None:
    """Put a checkpoint's `gas/` arrays into `gas` at time t, finding this rank's nodes by position (collective)."""
    n = gas.n_owned
    width = float(np.min(gas.ops.width[:n], initial=np.inf))
    h = comm.allreduce(width, op=MPI.MIN)
    try:
        idx, problem = match_nodes(arrays["gas/x"], gas.x[:n], h), None
    except CheckpointError as e:  # maybe on this rank only: every rank raises it (the others would go on)
        idx, problem = None, str(e)
    if comm.size > 1:
        problem = next((p for p in comm.allgather(problem) if p), None)
    if problem:
        raise CheckpointError(problem)
    gas.set_state({k[4:]: v[idx] for k, v in arrays.items() if k.startswith("gas/") and k != "gas/x"}, t)


def dem_arrays(dem) -> dict[str, np.ndarray]:
    """This rank's DEM state as checkpoint arrays `dem/<key>` (copies), the contact history keyed by gids too."""
    state = dem.get_state()
    if "saved_keys" not in state and int(state.get("lists_valid", 0)):  # one rank: the lists hold the history;
        (k, v), (wk, wv) = dem._history_keys()  # keyed by gids too, for a restart on other rank counts
        state.update(keyed_keys=k, keyed_vals=v, keyed_wkeys=wk, keyed_wvals=wv)
    return {f"dem/{k}": np.array(v, copy=True) for k, v in state.items()}


def gather(arrays: dict[str, np.ndarray], meta: dict, comm=MPI.COMM_WORLD) -> dict[str, np.ndarray]:
    """The rank-count-independent checkpoint arrays on rank 0 (one rank: the state unchanged)."""
    if comm.size == 1:
        return arrays
    rows = {k: v for k, v in arrays.items() if k.startswith("gas/") or k.startswith(f"dem/{_ROWS}")}
    rows.update({f"dem/{k}": arrays[f"dem/{k}"] for k in _HISTORY if f"dem/{k}" in arrays})
    out = gather_rows(rows, comm)
    if "dem/p_gid" not in arrays:  # a gas-only run
        return out
    scalars = ("time", "steps", "dt", "pl_skin", "pl_builds", "max_overlap", "walls_count")
    top = comm.allreduce(int(arrays["dem/p_gid"].max(initial=-1)), op=MPI.MAX)
    if comm.rank == 0:
        for k in _HISTORY[::2]:  # cross-partition pairs are held by both ranks: keep each key once
            key, val = f"dem/{k}", f"dem/{k.replace('keys', 'vals')}"
            if key in out:
                out[key], first = np.unique(out[key], return_index=True)
                out[val] = out[val][first]
        out.update({f"dem/{k}": arrays[f"dem/{k}"] for k in scalars if f"dem/{k}" in arrays})
        out["dem/p_next_gid"] = np.array(top + 1)  # each rank gets its own block above it on restart
        out["dem/has_saved"] = np.array(int("dem/saved_keys" in out))
        out["dem/lists_valid"] = np.array(0)
        out["dem/dirty"] = np.array(1)
    return out


def load_dem(dem, arrays: dict[str, np.ndarray], meta: dict, ranks: int) -> None:
    """Put a checkpoint's `dem/` arrays into `dem` (every rank holds the whole checkpoint; collective).

    A one-rank checkpoint read by one process continues bit for bit; otherwise see `reload_particles`.
    """
    state = {k[4:]: v for k, v in arrays.items() if k.startswith("dem/")}
    same_layout = meta["ranks"] == ranks == 1
    if not same_layout:
        state = portable(state)
    dem.set_state(state)
    if not same_layout:  # cell indices are rank-local: search the restored particles afresh
        dem.particles.cell[: dem.particles.n_owned] = -1
    if dem.exchange is not None:  # every rank holds every particle: keep this rank's share
        dem.exchange.distribute(dem.particles)


def portable(dem: dict) -> dict:
    """A DEM state in global-id order without the rank-local neighbour lists (rebuilt from the keyed history)."""
    out = {k: v for k, v in dem.items() if not k.startswith(("pl_start", "pl_nbr", "pl_hist", "w_", "keyed_"))}
    if "keyed_keys" in dem and "saved_keys" not in dem:  # a one-rank checkpoint: its history keyed by gids
        out.update({f"saved_{k[6:]}": dem[k] for k in dem if k.startswith("keyed_")})
        out["has_saved"] = 1
    order = np.argsort(out["p_gid"], kind="stable")  # the auxiliary arrays' rows (aux_*) follow their particles
    out.update({k: np.asarray(v)[order] for k, v in out.items() if k.startswith((_ROWS, "aux_")) and k != "p_next_gid"})
    out["lists_valid"], out["dirty"], out["forces_valid"] = 0, 1, 0
    out["pos_ref"] = np.array(out["p_pos"], copy=True)  # lists are rebuilt at the first step
    return out
