"""D4RL-style arrays: :func:`to_d4rl`, :func:`save_d4rl`, :func:`from_d4rl` (see :mod:`offline_adp.formats`)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.files import atomic_file
from offline_adp.data.info import ActionTable, DatasetInfo
from offline_adp.errors import IngestError
from offline_adp.formats.common import (
    _INT32_MAX,
    ACTION_VALUE,
    MAX_DECLARED_BYTES,
    META_KEY,
    _action_indices,
    _action_values,
    _columns,
    _default_info,
    _encode_actions,
    _finite_floats,
    _flags,
    _integers,
    _load_npz,
    _numeric,
    _provenance,
    _require_doctor,
    short_list,
)
from offline_adp.progress import get_logger

log = get_logger(__name__)


def to_d4rl(ds: TransitionDataset) -> dict[str, np.ndarray]:
    """D4RL-style arrays of a dataset (see module docstring)."""
    c = _columns(ds)
    out = {
        "observations": c["obs"],
        "next_observations": c["next_obs"],
        "actions": _action_values(ds),
        "rewards": -c["cost"],
        "terminals": c["terminated"],
        "timeouts": c["truncated"],
        "infos/action_index": c["action"],
        "infos/episode_id": c["episode_id"].astype(str),
        "infos/step": c["step"],
        "infos/source": c["source"].astype(str),
        META_KEY: np.array(ds.info.to_json()),
    }
    if c["behavior_prob"] is not None:
        out["infos/behavior_prob"] = c["behavior_prob"]
    if c["t_ns"] is not None:
        out["infos/t_ns"] = c["t_ns"]
    return out


def save_d4rl(ds: TransitionDataset, path: str | PathLike[str]) -> Path:
    """Write :func:`to_d4rl` arrays to an ``.npz`` file (atomically; loads without pickle)."""
    out = Path(path)
    with atomic_file(out, what="D4RL file") as tmp, open(tmp, "wb") as f:  # a handle: np.savez adds no suffix
        np.savez(f, **to_d4rl(ds))
    log.info("wrote %s: %d transitions (D4RL arrays)", out, len(ds))
    return out


def from_d4rl(data: Mapping[str, Any] | str | PathLike[str], info: DatasetInfo | None = None, *,
              feature_names: list[str] | None = None, action_table: ActionTable | None = None,
              name: str = "d4rl", max_bytes: int = MAX_DECLARED_BYTES) -> TransitionDataset:
    """A dataset from D4RL-style arrays (a mapping or an ``.npz`` file).

    Metadata comes from ``info``, else the arrays' ``metadata/offline_adp``, else
    ``feature_names`` (default ``x0, x1, ...``) and ``action_table`` (default: the
    distinct action rows when there are at most :data:`MAX_EXACT_ACTIONS`, else the
    continuous commands binned, with the exact commands kept in ``action_value.<dim>``
    columns). Actions are matched exactly to the action table unless
    ``infos/action_index`` is given.

    The file is untrusted: declared array sizes are checked against the file size and
    ``max_bytes`` before reading; flags must be booleans (0/1), steps and indices whole
    numbers in range, values finite; the result passes the ingestion doctor. Anything
    else is an :class:`IngestError` / :class:`ValidationError` naming the file, the
    array and the row.
    """
    where = str(data) if isinstance(data, str | PathLike) else name
    arrays = _load_npz(data, max_bytes) if isinstance(data, str | PathLike) else dict(data)
    missing = [k for k in ("observations", "actions", "rewards", "terminals") if k not in arrays]
    if missing:
        raise IngestError(f"{where}: missing D4RL arrays {missing}; found {short_list(sorted(arrays))}")
    obs_raw = _numeric(arrays["observations"], where, "observations")
    n = len(obs_raw)
    if n == 0:
        raise IngestError(f"{where}: observations: no transitions (shape {obs_raw.shape})")
    obs = _finite_floats(obs_raw, where, "observations").reshape(n, -1)
    if obs.shape[1] == 0:
        raise IngestError(f"{where}: observations: shape {obs_raw.shape} has no feature columns")
    act_vals = _finite_floats(_numeric(arrays["actions"], where, "actions", n=n), where, "actions").reshape(n, -1)
    rewards = _numeric(arrays["rewards"], where, "rewards", n=n)
    if rewards.size != n:
        raise IngestError(f"{where}: rewards: shape {rewards.shape} where ({n},) is required")
    rewards = _finite_floats(rewards.reshape(n), where, "rewards")
    term = _flags(arrays["terminals"], where, "terminals", n)
    tout = _flags(arrays["timeouts"], where, "timeouts", n) if "timeouts" in arrays else np.zeros(n, bool)
    if info is None and META_KEY in arrays:
        meta = np.asarray(arrays[META_KEY])
        if meta.dtype.kind != "U" or meta.size != 1:
            raise IngestError(f"{where}: {META_KEY}: a JSON string is required, found {meta.dtype} {meta.shape}")
        try:
            info = DatasetInfo.from_dict(json.loads(str(meta.reshape(()))), where=f"{where}:{META_KEY}")
        except (json.JSONDecodeError, RecursionError, TypeError, AttributeError) as exc:
            raise IngestError(f"{where}: {META_KEY}: not a dataset info.json ({type(exc).__name__}: "
                              f"{str(exc)[:200]})") from None
    extra: dict[str, np.ndarray] = {}
    idx0: np.ndarray | None = None
    if info is None:
        if action_table is not None:
            table = action_table
        else:
            idx0, table, extra = _encode_actions(act_vals, where)
        info = _default_info(obs.shape[1], table, feature_names, name)
    if len(info.features) != obs.shape[1]:
        raise IngestError(f"{where}: observations have {obs.shape[1]} columns, the metadata names "
                          f"{len(info.features)} features")
    if not extra and info.action_table.kind in ("binned",
                                                "continuous") and act_vals.shape[1] == len(info.action_table.dims):
        # binned commands: the logged values are the exact commands (what to_d4rl writes)
        extra = {
            ACTION_VALUE + dname: np.ascontiguousarray(act_vals[:, j]) for j, dname in enumerate(info.action_table.dims)
        }
    if "infos/action_index" in arrays:
        action = _integers(arrays["infos/action_index"], where, "infos/action_index", n, 0, info.n_actions - 1,
                           f"indices into the {info.n_actions}-action table")
    elif idx0 is not None:
        action = idx0
    else:
        action = _action_indices(act_vals, info.action_table, where)
    if "infos/episode_id" in arrays:
        ep_raw = np.asarray(arrays["infos/episode_id"])
        if ep_raw.dtype.kind not in "Uiu" or ep_raw.shape != (n,):
            raise IngestError(f"{where}: infos/episode_id: {ep_raw.dtype} {ep_raw.shape} where ({n},) strings or "
                              "integers are required")
        ep = ep_raw.astype(str)
        new_ep = np.r_[True, ep[1:] != ep[:-1]] if n else np.zeros(0, bool)
    else:
        new_ep = np.r_[True, (term | tout)[:-1]] if n else np.zeros(0, bool)
        ep = np.char.add(f"{name}-", np.char.zfill((np.cumsum(new_ep) - 1).astype(str), 6))
    if "infos/step" in arrays:
        step = _integers(arrays["infos/step"], where, "infos/step", n, 0, _INT32_MAX,
                         "steps are stored as int32 from 0")
    else:
        step = np.arange(n) - np.flatnonzero(new_ep)[np.cumsum(new_ep) - 1] if n else np.zeros(0, np.int64)
    last = np.r_[new_ep[1:], True] if n else np.zeros(0, bool)
    keep = np.ones(n, bool)
    if "next_observations" in arrays:
        nxt = _numeric(arrays["next_observations"], where, "next_observations", n=n)
        next_obs = _finite_floats(nxt, where, "next_observations").reshape(n, -1)
        if next_obs.shape != obs.shape:
            raise IngestError(f"{where}: next_observations: shape {nxt.shape}, observations {obs_raw.shape}")
    else:  # the next row of the same episode; an episode's last row has no successor
        next_obs = np.vstack([obs[1:], obs[-1:]]) if n else obs
        keep = ~last | term
        next_obs = np.where(last[:, None], obs, next_obs)  # terminal rows: next state unused (no bootstrap)
        if (~keep).any():
            log.info("%s: dropped %d last rows of episodes without a next observation", where, int((~keep).sum()))
    # an episode's last kept row ends it: terminated if logged so, else truncated (cut: a
    # time limit, the end of the file, or its successor-less last row dropped above)
    kept = np.flatnonzero(keep)
    ep_k = ep[kept]
    end = np.r_[ep_k[1:] != ep_k[:-1], True] if len(kept) else np.zeros(0, bool)
    tout = tout.copy()
    tout[kept[end & ~term[kept]]] = True
    src = "unknown"
    if "infos/source" in arrays:
        s_raw = np.asarray(arrays["infos/source"])
        if s_raw.dtype.kind not in "Uiu" or s_raw.shape != (n,):
            raise IngestError(f"{where}: infos/source: {s_raw.dtype} {s_raw.shape} where ({n},) strings are required")
        src = s_raw.astype(str)
    bp = _numeric(arrays["infos/behavior_prob"], where, "infos/behavior_prob", n=n).astype(np.float64) \
        if "infos/behavior_prob" in arrays else None
    if bp is not None and bp.shape != (n,):
        raise IngestError(f"{where}: infos/behavior_prob: shape {bp.shape} where ({n},) is required")
    t_ns = _integers(arrays["infos/t_ns"], where, "infos/t_ns", n, -(2**63) + 1, 2**63 - 1024, "int64 nanoseconds") \
        if "infos/t_ns" in arrays else None

    def sel(x: Any) -> Any:
        return x if x is None or isinstance(x, str) else x[keep]

    ds = TransitionDataset.from_arrays(
        info, episode_id=ep[keep], step=step[keep], obs=obs[keep], action=action[keep], cost=-rewards[keep],
        next_obs=next_obs[keep], terminated=term[keep], truncated=tout[keep], source=sel(src), behavior_prob=sel(bp),
        t_ns=sel(t_ns), extra={**{k: v[keep] for k, v in extra.items()},
                               **_provenance([where], np.zeros(len(kept), np.int64), kept)})
    return _require_doctor(ds, where)
