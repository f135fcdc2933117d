"""Offline-RL dataset formats: D4RL-style arrays, Minari datasets, LeRobot layout.

Our datasets are transitions with named features, a declared action table and costs;
these formats are flat arrays (D4RL), episodes of ``T + 1`` observations (Minari) or
frames (LeRobot). The conversions keep every transition exactly (float64 throughout,
``reward = -cost`` and back, which is exact in floating point) and carry our metadata
(feature names and units, the action table, episode ids, steps, sources, logged
propensities) in the places each format has for it, so an export followed by an
import gives the same dataset.

D4RL arrays (:func:`to_d4rl`, :func:`save_d4rl`, :func:`from_d4rl`)
    ``observations``, ``next_observations``, ``actions`` (the action *values*, (n, k)),
    ``rewards``, ``terminals``, ``timeouts`` (= our ``truncated``) and ``infos/...``
    (``action_index``, ``episode_id``, ``step``, ``source``, ``behavior_prob``,
    ``t_ns``), plus ``metadata/offline_adp`` (the dataset's ``info.json``) in an
    ``.npz`` file (no pickle). Episode boundaries come from ``infos/episode_id``, else
    from ``terminals | timeouts``; without ``next_observations`` the next row of the
    same episode is the next state and an episode's last row (no successor) is dropped,
    as in D4RL's ``qlearning_dataset``.
Minari (:func:`to_minari`, :func:`from_minari`)
    One Minari episode per episode: ``observations`` ``(T + 1, d)`` (the last is the
    final next state; episodes must be contiguous, ``next_obs[t] == obs[t + 1]``),
    ``actions`` (``Discrete`` indices), ``rewards``, ``terminations``, ``truncations``,
    ``infos`` (``episode_id``, ``step``, ``source``, ``behavior_prob``). Written with
    Minari's arrow storage under ``MINARI_DATASETS_PATH`` (or ``datasets_path``); our
    ``info.json`` is in the dataset metadata under ``offline_adp``. Nothing is
    downloaded: reading takes a local dataset (id, path or ``MinariDataset``).
LeRobot layout (:func:`to_lerobot`)
    ``meta/info.json`` (codebase v2.1 layout: features with names and shapes, fps,
    path templates), ``meta/episodes.jsonl``, ``meta/episodes_stats.jsonl`` (per episode
    and feature: min, max, mean, std, count), ``meta/tasks.jsonl`` and
    ``data/chunk-000/episode_000000.parquet`` with one frame per transition:
    ``observation.state``, ``action`` (values), ``action_index``, ``next.reward``,
    ``next.done`` (terminated), ``next.truncated``, ``next.observation.state``,
    ``timestamp``, ``frame_index``, ``episode_index``, ``index``, ``task_index``.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Mapping
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.data.io import atomic_file
from offline_adp.errors import IngestError, OfflineADPError
from offline_adp.progress import get_logger

log = get_logger(__name__)

META_KEY = "metadata/offline_adp"


# ----------------------------------------------------------------------------- helpers
#: Bound on the bytes an imported file's arrays may declare, per byte of file (after
#: decompression, every element counted as at least 8 bytes: the float64 we convert to).
MAX_EXPANSION = 64
#: Absolute bound on the declared bytes of an imported file's arrays.
MAX_DECLARED_BYTES = 16 << 30
#: Actions with at most this many distinct value rows become an exact (discrete) action
#: table; more distinct rows are continuous commands and are binned (see :func:`_encode_actions`).
MAX_EXACT_ACTIONS = 256
#: Quantile bins per action component for continuous commands (product table capped at
#: :data:`MAX_BINNED_ACTIONS` cells).
ACTION_BINS = 16
MAX_BINNED_ACTIONS = 4096
#: Prefix of the extra columns that keep continuous commands exactly (``action_value.<dim>``).
ACTION_VALUE = "action_value."
_INT32_MAX = int(np.iinfo(np.int32).max)


def _short(items: Any, k: int = 8) -> str:
    """At most ``k`` items of a list for a message (never thousands)."""
    items = list(items)
    return repr(items) if len(items) <= k else f"[{', '.join(repr(x) for x in items[:k])}, ... ({len(items)} in all)]"


def _columns(ds: TransitionDataset) -> dict[str, Any]:
    a = ds.arrays()
    out = {"obs": a.obs, "next_obs": a.next_obs, "action": a.action.astype(np.int64), "cost": a.cost,
           "terminated": a.terminated.astype(bool), "truncated": a.truncated.astype(bool), "step": a.step.astype(np.int64),
           "episode_id": ds.column("episode_id").astype(str), "source": ds.column("source").astype(str),
           "behavior_prob": a.behavior_prob}
    out["t_ns"] = ds.column("t_ns").astype(np.int64) if "t_ns" in ds.table.column_names else None
    return out


def _action_values(ds: TransitionDataset) -> np.ndarray:
    """The logged command of each row: the exact ``action_value.*`` columns of continuous
    commands when present, else the action table's values."""
    dims = ds.info.action_table.dims
    cols = [ACTION_VALUE + d for d in dims]
    if all(c in ds.table.column_names for c in cols):
        return np.column_stack([ds.column(c).astype(np.float64) for c in cols])
    return ds.info.action_table.values[ds.arrays().action]


def _numeric(x: Any, where: str, field: str, *, n: int | None = None) -> np.ndarray:
    """A numeric (int/float/bool) array with ``n`` rows, else IngestError naming the field."""
    a = np.asarray(x)
    if a.dtype.kind not in "biuf":
        raise IngestError(f"{where}: {field}: dtype {a.dtype} where numbers are required")
    if a.ndim == 0 or (n is not None and len(a) != n):
        raise IngestError(f"{where}: {field}: shape {a.shape} where {n} rows are required")
    return a


def _finite(a: np.ndarray, where: str, field: str) -> np.ndarray:
    """Float64 copy of ``a``; NaN or infinity is an IngestError naming the field and row."""
    v = np.asarray(a, dtype=np.float64)
    bad = ~np.isfinite(v)
    if bad.any():
        i = int(np.argmax(bad.reshape(len(v), -1).any(axis=1)))
        raise IngestError(f"{where}: {field}: row {i}: value {v[i].tolist() if v.ndim > 1 else float(v[i])!r} is NaN or "
                          f"infinite ({int(bad.reshape(len(v), -1).any(axis=1).sum())} rows); the format stores finite values")
    return v


def _flags(x: Any, where: str, field: str, n: int) -> np.ndarray:
    """Boolean flags: bool, or numbers that are exactly 0 or 1 (anything else, NaN or 0.5,
    is an IngestError naming the field and row: it is not a flag)."""
    a = _numeric(x, where, field, n=n)
    if a.ndim != 1:
        if a.ndim == 2 and a.shape[1] == 1:
            a = a[:, 0]
        else:
            raise IngestError(f"{where}: {field}: shape {a.shape} where ({n},) flags are required")
    if a.dtype.kind == "b":
        return a.astype(bool)
    bad = ~((a == 0) | (a == 1))
    if bad.any():
        i = int(np.argmax(bad))
        raise IngestError(f"{where}: {field}: row {i}: value {a[i].item()!r} is not a boolean flag (0/1, true/false); "
                          f"{int(bad.sum())} such rows")
    return a == 1


def _integers(x: Any, where: str, field: str, n: int, lo: int, hi: int, what: str) -> np.ndarray:
    """Whole numbers in [lo, hi] as int64 (a float must be integral; nothing wraps)."""
    a = _numeric(x, where, field, n=n)
    if a.ndim != 1:
        raise IngestError(f"{where}: {field}: shape {a.shape} where ({n},) is required")
    if a.dtype.kind == "f":
        bad = ~np.isfinite(a) | (a != np.round(a)) | (a < lo) | (a > hi)
    elif a.dtype.kind == "u":
        bad = a > np.uint64(hi)
    else:
        bad = (a.astype(np.int64) < lo) | (a.astype(np.int64) > hi) if a.dtype.kind != "b" else np.zeros(n, bool)
    if bad.any():
        i = int(np.argmax(bad))
        raise IngestError(f"{where}: {field}: row {i}: value {a[i].item()!r} is not a whole number in [{lo}, {hi}] "
                          f"({what}); {int(bad.sum())} such rows")
    return a.astype(np.int64)


def _unique_rows(vals: np.ndarray, limit: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(distinct rows, inverse) if there are at most ``limit`` distinct rows, else None."""
    uniq, inv = np.unique(vals, axis=0, return_inverse=True)
    return (uniq, inv.reshape(-1)) if len(uniq) <= limit else None


def _action_indices(values: np.ndarray, table: ActionTable, where: str) -> np.ndarray:
    """Index of each action value row in the table (exact match), else IngestError.
    Memory: one comparison of the distinct rows against the table, in blocks."""
    vals = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
    tv = table.values
    if vals.shape[1] != tv.shape[1]:
        raise IngestError(f"{where}: actions have {vals.shape[1]} components, the action table {tv.shape[1]} {list(table.dims)}")
    uniq, inv = np.unique(vals, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    pos = np.full(len(uniq), -1, np.int64)
    block = max(1, (1 << 24) // max(1, len(tv) * tv.shape[1]))
    for s in range(0, len(uniq), block):
        eq = (uniq[s:s + block, None, :] == tv[None, :, :]).all(axis=2)
        pos[s:s + block] = np.where(eq.any(axis=1), eq.argmax(axis=1), -1)
    idx = pos[inv] if len(vals) else np.zeros(0, np.int64)
    if (idx < 0).any():
        i = int(np.argmax(idx < 0))
        raise IngestError(f"{where}: actions: row {i}: action {vals[i].tolist()} is not in the action table "
                          f"{_short(tv.tolist())} ({int((idx < 0).sum())} rows); pass action_table=, or bin continuous "
                          "actions with an ingestion spec")
    return idx


def _default_info(d: int, table: ActionTable, feature_names: list[str] | None, name: str) -> DatasetInfo:
    names = feature_names or [f"x{j}" for j in range(d)]
    if len(names) != d:
        raise IngestError(f"{name}: {len(names)} feature names for {d} observation columns")
    return DatasetInfo(features=tuple(Feature(n) for n in names), action_table=table, name=name)


def _dims(k: int) -> tuple[str, ...]:
    return ("a",) if k == 1 else tuple(f"a{j}" for j in range(k))


def _table_from_values(values: np.ndarray) -> ActionTable:
    """An exact action table of the distinct value rows (names unique: shortest repr)."""
    vals = np.unique(np.asarray(values, np.float64).reshape(len(values), -1), axis=0)
    dims = _dims(vals.shape[1])
    names = [",".join(f"{d}={float(x)!r}" for d, x in zip(dims, row, strict=True)) for row in vals]
    return ActionTable.from_values(vals, dims=dims, names=names)


def _binned(vals: np.ndarray, where: str) -> tuple[np.ndarray, ActionTable]:
    """Continuous commands -> (indices, binned action table): each component in quantile
    bins (at most :data:`ACTION_BINS`, the product at most :data:`MAX_BINNED_ACTIONS`
    cells), index row-major over the components, each cell's value the mean command in
    it (its centre when empty), as the ingestion spec bins continuous actions."""
    n, k = vals.shape
    nb = max(2, min(ACTION_BINS, int(np.floor(MAX_BINNED_ACTIONS ** (1.0 / k) + 1e-9))))
    if nb ** k > MAX_BINNED_ACTIONS:
        raise IngestError(f"{where}: actions: {k} continuous components cannot be binned into at most "
                          f"{MAX_BINNED_ACTIONS} actions; pass action_table=")
    per = []
    for j in range(k):
        col = vals[:, j]
        edges = np.unique(np.quantile(col, np.linspace(0, 1, nb + 1)))
        if len(edges) < 2:
            edges = np.array([col.min() - 0.5, col.max() + 0.5])
        m = len(edges) - 1
        per.append((np.clip(np.searchsorted(edges, col, side="right") - 1, 0, m - 1), (edges[:-1] + edges[1:]) / 2, edges))
    shape = tuple(len(c) for _, c, _ in per)
    idx = np.ravel_multi_index(tuple(i for i, _, _ in per), shape) if n else np.zeros(0, np.int64)
    cells = np.array(np.unravel_index(np.arange(int(np.prod(shape))), shape)).T
    centre = np.column_stack([per[j][1][cells[:, j]] for j in range(k)])
    counts = np.bincount(idx, minlength=len(cells))
    value = centre.copy()
    for j in range(k):
        sums = np.bincount(idx, weights=vals[:, j], minlength=len(cells))
        value[:, j] = np.where(counts > 0, sums / np.maximum(counts, 1), centre[:, j])
    dims = _dims(k)
    names = [",".join(f"{d}#{i}" for d, i in zip(dims, c, strict=True)) for c in cells]
    from offline_adp.data.info import Action

    table = ActionTable(actions=tuple(Action(nm, tuple(float(x) for x in v)) for nm, v in zip(names, value, strict=True)),
                        dims=dims, kind="binned", bin_edges=tuple(float(e) for e in per[0][2]) if k == 1 else None)
    return idx.astype(np.int64), table


def _encode_actions(vals: np.ndarray, where: str, continuous: bool | None = None
                    ) -> tuple[np.ndarray, ActionTable, dict[str, np.ndarray]]:
    """Action values (n, k) without a given table -> (indices, table, extra columns).

    At most :data:`MAX_EXACT_ACTIONS` distinct rows (and not ``continuous=True``): an
    exact discrete table of those rows. Otherwise continuous commands: binned
    (:func:`_binned`) and kept exactly in ``action_value.<dim>`` float64 columns."""
    vals = np.asarray(vals, np.float64).reshape(len(vals), -1)
    few = None if continuous else _unique_rows(vals, MAX_EXACT_ACTIONS)
    if few is not None and len(few[0]):
        uniq, inv = few
        table = _table_from_values(uniq)
        return inv.astype(np.int64), table, {}
    if not len(vals):
        raise IngestError(f"{where}: no transitions")
    idx, table = _binned(vals, where)
    extra = {ACTION_VALUE + d: np.ascontiguousarray(vals[:, j]) for j, d in enumerate(table.dims)}
    log.info("%s: continuous actions: %d distinct commands binned into %d actions; exact commands kept in %s",
             where, len(np.unique(vals, axis=0)), len(table), list(extra))
    return idx, table, extra


def _require_doctor(ds: TransitionDataset, where: str) -> TransitionDataset:
    """The ingestion doctor on a converted dataset built with ``src_file``/``src_row``
    columns (the source file, or file and episode, and the row in it); any finding is a
    ValidationError naming them, the column and why. Returns ``ds`` without those columns."""
    from offline_adp.data.validate import validate
    from offline_adp.errors import ValidationError

    if len(ds) == 0:
        raise IngestError(f"{where}: no transitions to convert")
    report = validate(ds)  # names src_file/src_row of each finding
    if not report.ok:
        f = report.findings.iloc[0]
        counts = ", ".join(f"{k} {v}" for k, v in report.counts().items())
        raise ValidationError(f"{where}: the converted dataset fails the doctor ({counts}); first: {f['file']}: row "
                              f"{f['row']} (episode {f['episode_id']}, step {f['step']}) column {f['column']!r}: "
                              f"{f['message']}", report)
    return TransitionDataset(ds.table.drop_columns(["src_file", "src_row"]), ds.info)


def _provenance(files: list[str], file_index: np.ndarray, rows: np.ndarray) -> dict[str, Any]:
    import pyarrow as pa

    return {"src_file": pa.DictionaryArray.from_arrays(pa.array(np.asarray(file_index, np.int32)), pa.array(files)),
            "src_row": pa.array(np.asarray(rows, np.int64))}


def _load_npz(path: str | PathLike[str], max_bytes: int) -> dict[str, np.ndarray]:
    """The arrays of an untrusted ``.npz``: member names, dtypes and declared sizes checked
    against the file size and ``max_bytes`` before anything is read (no pickle)."""
    import re

    from offline_adp import artifact_checks as C

    p = Path(path)
    try:
        size = p.stat().st_size
        # per member: deflate's own limit (~1032x; long runs of false flags compress that
        # well); the total is bounded below against the file size
        members = C.check_npz(p, max_expansion=1100, name_pattern=re.compile(r"^[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*\.npy$"))
    except FileNotFoundError:
        raise IngestError(f"{p}: no such file") from None
    except OfflineADPError as exc:
        raise IngestError(f"{exc} (not a D4RL .npz we can read safely)") from None
    total = 0
    for key, (dtype, shape) in members.items():
        count = int(np.prod(shape, dtype=object))
        total += count * max(8, dtype.itemsize)
        if total > min(max_bytes, MAX_EXPANSION * max(size, 1) + (1 << 20)):
            raise IngestError(f"{p}: {key}: arrays declare {total} bytes (as float64) in a {size}-byte file "
                              f"(at most {MAX_EXPANSION}x the file size and {max_bytes} bytes); refusing to read")
    try:
        with np.load(p, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except C.ZIP_ERRORS as exc:
        raise IngestError(f"{p}: not a readable .npz of D4RL arrays ({type(exc).__name__}: {str(exc)[:200]})") from None

# ----------------------------------------------------------------------------- D4RL
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
        raise IngestError(f"{where}: missing D4RL arrays {missing}; found {_short(sorted(arrays))}")
    obs_raw = _numeric(arrays["observations"], where, "observations")
    n = len(obs_raw)
    if n == 0:
        raise IngestError(f"{where}: observations: no transitions (shape {obs_raw.shape})")
    obs = _finite(obs_raw, where, "observations").reshape(n, -1)
    if obs.shape[1] == 0:
        raise IngestError(f"{where}: observations: shape {obs_raw.shape} has no feature columns")
    act_vals = _finite(_numeric(arrays["actions"], where, "actions", n=n), where, "actions").reshape(n, -1)
    rewards = _numeric(arrays["rewards"], where, "rewards", n=n)
    if rewards.size != n:
        raise IngestError(f"{where}: rewards: shape {rewards.shape} where ({n},) is required")
    rewards = _finite(rewards.reshape(n), where, "rewards")
    term = _flags(arrays["terminals"], where, "terminals", n)
    tout = _flags(arrays["timeouts"], where, "timeouts", n) if "timeouts" in arrays else np.zeros(n, bool)
    if info is None and META_KEY in arrays:
        meta = np.asarray(arrays[META_KEY])
        if meta.dtype.kind != "U" or meta.size != 1:
            raise IngestError(f"{where}: {META_KEY}: a JSON string is required, found {meta.dtype} {meta.shape}")
        try:
            info = DatasetInfo.from_dict(json.loads(str(meta.reshape(()))), where=f"{where}:{META_KEY}")
        except (json.JSONDecodeError, RecursionError, TypeError, AttributeError) as exc:
            raise IngestError(f"{where}: {META_KEY}: not a dataset info.json ({type(exc).__name__}: {str(exc)[:200]})") from None
    extra: dict[str, np.ndarray] = {}
    idx0: np.ndarray | None = None
    if info is None:
        if action_table is not None:
            table = action_table
        else:
            idx0, table, extra = _encode_actions(act_vals, where)
        info = _default_info(obs.shape[1], table, feature_names, name)
    if len(info.features) != obs.shape[1]:
        raise IngestError(f"{where}: observations have {obs.shape[1]} columns, the metadata names {len(info.features)} features")
    if not extra and info.action_table.kind == "binned" and act_vals.shape[1] == len(info.action_table.dims):
        # binned commands: the logged values are the exact commands (what to_d4rl writes)
        extra = {ACTION_VALUE + dname: np.ascontiguousarray(act_vals[:, j]) for j, dname in enumerate(info.action_table.dims)}
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
            raise IngestError(f"{where}: infos/episode_id: {ep_raw.dtype} {ep_raw.shape} where ({n},) strings or integers are required")
        ep = ep_raw.astype(str)
        new_ep = np.r_[True, ep[1:] != ep[:-1]] if n else np.zeros(0, bool)
    else:
        new_ep = np.r_[True, (term | tout)[:-1]] if n else np.zeros(0, bool)
        ep = np.char.add(f"{name}-", np.char.zfill((np.cumsum(new_ep) - 1).astype(str), 6))
    if "infos/step" in arrays:
        step = _integers(arrays["infos/step"], where, "infos/step", n, 0, _INT32_MAX, "steps are stored as int32 from 0")
    else:
        step = np.arange(n) - np.flatnonzero(new_ep)[np.cumsum(new_ep) - 1] if n else np.zeros(0, np.int64)
    last = np.r_[new_ep[1:], True] if n else np.zeros(0, bool)
    keep = np.ones(n, bool)
    if "next_observations" in arrays:
        nxt = _numeric(arrays["next_observations"], where, "next_observations", n=n)
        next_obs = _finite(nxt, where, "next_observations").reshape(n, -1)
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


# ----------------------------------------------------------------------------- Minari
def _minari() -> Any:
    try:
        import minari
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise OfflineADPError("Minari support needs the minari package: pip install 'offline-adp[minari]'") from exc
    return minari


def _episode_bounds(ep_codes: np.ndarray) -> np.ndarray:
    return np.r_[np.flatnonzero(np.r_[True, ep_codes[1:] != ep_codes[:-1]]), len(ep_codes)] if len(ep_codes) else np.zeros(1, int)


def to_minari(ds: TransitionDataset, dataset_id: str, *, datasets_path: str | PathLike[str] | None = None,
              author: str | None = None, description: str | None = None) -> Path:
    """Write ``ds`` as a local Minari dataset ``dataset_id`` (see module docstring);
    returns its directory. ``datasets_path`` overrides ``MINARI_DATASETS_PATH``."""
    minari = _minari()
    import gymnasium as gym
    from minari.data_collector import EpisodeBuffer

    c = _columns(ds)
    bounds = _episode_bounds(ds.episode_index)
    first, last = bounds[:-1], bounds[1:] - 1
    inner = np.ones(len(ds), bool)
    inner[last] = False
    gap = np.flatnonzero(inner[:-1] & (c["next_obs"][:-1] != c["obs"][1:]).any(axis=1)) if len(ds) > 1 else []
    if len(gap):
        i = int(gap[0])
        raise OfflineADPError(f"episode {c['episode_id'][i]!r} step {c['step'][i]}: next_obs differs from the next step's obs; "
                              "Minari episodes are observation sequences and need contiguous episodes")
    buffers = []
    nan = np.full(1, np.nan)
    for k, (lo, hi) in enumerate(zip(first, last + 1, strict=True)):
        obs = np.vstack([c["obs"][lo:hi], c["next_obs"][hi - 1:hi]])
        bp = c["behavior_prob"][lo:hi] if c["behavior_prob"] is not None else np.full(hi - lo, np.nan)
        infos = {"episode_id": np.append(c["episode_id"][lo:hi], c["episode_id"][hi - 1]).astype(str).tolist(),
                 "step": np.r_[c["step"][lo:hi], c["step"][hi - 1] + 1].astype(np.int64).tolist(),
                 "source": np.append(c["source"][lo:hi], c["source"][hi - 1]).astype(str).tolist(),
                 "behavior_prob": np.r_[bp, nan].astype(np.float64).tolist()}
        if c["t_ns"] is not None:
            infos["t_ns"] = np.r_[c["t_ns"][lo:hi], c["t_ns"][hi - 1]].astype(np.int64).tolist()
        # infos as lists: minari's arrow storage cannot decode 1-D numpy info arrays (empty shape)
        buffers.append(EpisodeBuffer(id=k, observations=obs, actions=c["action"][lo:hi],
                                     rewards=-c["cost"][lo:hi], terminations=c["terminated"][lo:hi],
                                     truncations=c["truncated"][lo:hi], infos=infos))
    d = len(ds.feature_names)
    obs_space = gym.spaces.Box(-np.inf, np.inf, shape=(d,), dtype=np.float64)
    act_space = gym.spaces.Discrete(ds.n_actions)
    old = os.environ.get("MINARI_DATASETS_PATH")
    if datasets_path is not None:
        os.environ["MINARI_DATASETS_PATH"] = str(datasets_path)
    try:
        with warnings.catch_warnings():  # minari's reminders about optional metadata fields
            warnings.filterwarnings("ignore", message=r".*(is set to None|env_spec is None)", category=UserWarning)
            out = minari.create_dataset_from_buffers(
                dataset_id, buffers, observation_space=obs_space, action_space=act_space, algorithm_name="offline_adp",
                author=author, description=description or f"exported by offline_adp from {ds.info.name or 'a dataset'}",
                code_permalink="https://github.com/offline-adp", data_format="arrow")
        out.storage.update_metadata({"offline_adp": json.loads(ds.info.to_json())})
        path = Path(out.storage.data_path).parent
    except ValueError as exc:  # e.g. the id exists already
        raise OfflineADPError(f"minari dataset {dataset_id!r}: {exc}") from exc
    finally:
        if datasets_path is not None:
            if old is None:
                os.environ.pop("MINARI_DATASETS_PATH", None)
            else:
                os.environ["MINARI_DATASETS_PATH"] = old
    log.info("wrote Minari dataset %s at %s: %d episodes, %d steps", dataset_id, path, len(first), len(ds))
    return path


def _minari_dir(source: Any) -> Path:
    """The ``data/`` directory of a local Minari dataset (a path or an id; never downloaded)."""
    p = Path(source)
    cands = [p / "data", p] if p.exists() else []
    if not cands:
        try:
            from minari.storage.datasets_root_dir import get_dataset_path

            q = get_dataset_path(str(source))
        except Exception as exc:  # minari's own id parsing: a malformed id
            raise IngestError(f"{source}: not a Minari dataset id or path ({type(exc).__name__}: {str(exc)[:200]})") from None
        cands = [q / "data"] if q.exists() else []
    data_dir = next((c for c in cands if (c / "metadata.json").is_file()), None)
    if data_dir is None:
        raise IngestError(f"{source}: no local Minari dataset there (looked for metadata.json; datasets path "
                          f"{os.environ.get('MINARI_DATASETS_PATH', '~/.minari/datasets')}); nothing is downloaded")
    meta = data_dir / "metadata.json"
    if meta.stat().st_size > 64 << 20:
        raise IngestError(f"{meta}: {meta.stat().st_size} bytes is too large for Minari metadata")
    try:
        m = json.loads(meta.read_bytes().decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise IngestError(f"{meta}: not valid JSON ({type(exc).__name__}: {str(exc)[:200]})") from None
    if not isinstance(m, dict):
        raise IngestError(f"{meta}: a JSON object is required, found {type(m).__name__}")
    return data_dir


def _space_kind(space: Any, where: str, what: str) -> str:
    name = type(space).__name__
    if name not in ("Box", "Discrete"):
        raise IngestError(f"{where}: {what} space {name} is not supported (Box or Discrete)")
    return name


def from_minari(source: Any, info: DatasetInfo | None = None, *, feature_names: list[str] | None = None,
                action_table: ActionTable | None = None) -> TransitionDataset:
    """A dataset from a local Minari dataset: a ``MinariDataset``, a dataset directory
    (or its ``data/``), or an id under ``MINARI_DATASETS_PATH`` (never downloaded).

    Metadata: ``info``, else the ``offline_adp`` entry of the dataset's metadata, else
    ``feature_names`` and ``action_table`` (default: ``Discrete(n)`` actions are indices
    with values ``0..n-1``; ``Box`` actions are continuous commands: the distinct rows
    when there are at most :data:`MAX_EXACT_ACTIONS`, else binned, with the exact
    commands in ``action_value.<dim>`` columns).

    The directory is untrusted: missing or unreadable files, spaces we cannot store,
    episodes of the wrong shapes, non-boolean flags and out-of-range steps are an
    :class:`IngestError` naming the dataset and episode; the result passes the ingestion
    doctor (findings name the episode and step).
    """
    minari = _minari()
    if isinstance(source, minari.MinariDataset):
        mds, where = source, "minari dataset"
    else:
        data_dir = _minari_dir(source)
        where = str(source)
        try:
            mds = minari.MinariDataset(data_dir)
        except Exception as exc:  # minari raises whatever its parsers raise on a damaged directory
            raise IngestError(f"{where}: not a readable Minari dataset ({type(exc).__name__}: {str(exc)[:300]})") from None
    try:
        return _read_minari(mds, where, info, feature_names, action_table)
    except OfflineADPError:
        raise
    except Exception as exc:  # a damaged episode file, a wrong type deep inside minari / pyarrow
        raise IngestError(f"{where}: not a readable Minari dataset ({type(exc).__name__}: {str(exc)[:300]})") from None


def _read_minari(mds: Any, where: str, info: DatasetInfo | None, feature_names: list[str] | None,
                 action_table: ActionTable | None) -> TransitionDataset:
    meta = mds.storage.metadata
    if not isinstance(meta, dict):
        raise IngestError(f"{where}: metadata is not a JSON object")
    if info is None and "offline_adp" in meta:
        if not isinstance(meta["offline_adp"], dict):
            raise IngestError(f"{where}: metadata offline_adp: a JSON object is required")
        info = DatasetInfo.from_dict(meta["offline_adp"], where=f"{where}: metadata offline_adp")
    akind = _space_kind(mds.action_space, where, "action")
    _space_kind(mds.observation_space, where, "observation")
    discrete = akind == "Discrete"
    d = int(np.prod(mds.observation_space.shape))
    k = 1 if discrete else int(np.prod(mds.action_space.shape))
    cols: dict[str, list[Any]] = {c: [] for c in ("ep", "step", "obs", "next", "act", "rew", "term", "trunc", "src", "bp", "t",
                                                   "e", "row")}
    names: list[str] = []
    n_ep = 0
    for e in mds.iterate_episodes():
        ew = f"{where} episode {e.id}"
        rew = _numeric(e.rewards, ew, "rewards")
        T = len(rew)
        if rew.shape != (T,):
            raise IngestError(f"{ew}: rewards: shape {rew.shape} where (T,) is required")
        o = _numeric(e.observations, ew, "observations")
        if o.shape[0] != T + 1 or o.size != (T + 1) * d:
            raise IngestError(f"{ew}: observations: shape {o.shape} where ({T + 1}, {d}) is required (T + 1 for {T} steps)")
        o = _finite(o.reshape(T + 1, d), ew, "observations")
        a = _numeric(e.actions, ew, "actions")
        if a.shape[0] != T or a.size != T * k:
            raise IngestError(f"{ew}: actions: shape {a.shape} where ({T}{'' if discrete else f', {k}'}) is required")
        inf = e.infos if isinstance(e.infos, dict) else {}
        cols["ep"].append(np.asarray(inf["episode_id"][:T]).astype(str) if "episode_id" in inf else np.full(T, f"minari-{e.id:06d}"))
        cols["step"].append(_integers(np.asarray(inf["step"])[:T], ew, "infos/step", T, 0, _INT32_MAX,
                                      "steps are stored as int32 from 0") if "step" in inf else np.arange(T))
        cols["obs"].append(o[:-1])
        cols["next"].append(o[1:])
        cols["act"].append(a.reshape(T, k))
        cols["rew"].append(_finite(rew, ew, "rewards"))
        cols["term"].append(_flags(e.terminations, ew, "terminations", T))
        cols["trunc"].append(_flags(e.truncations, ew, "truncations", T))
        cols["src"].append(np.asarray(inf["source"][:T]).astype(str) if "source" in inf else np.full(T, "unknown"))
        cols["bp"].append(np.asarray(inf["behavior_prob"][:T], np.float64) if "behavior_prob" in inf else np.full(T, np.nan))
        if "t_ns" in inf:
            cols["t"].append(_integers(np.asarray(inf["t_ns"])[:T], ew, "infos/t_ns", T, -(2**63) + 1, 2**63 - 1024,
                                       "int64 nanoseconds"))
        cols["e"].append(np.full(T, n_ep, np.int64))
        cols["row"].append(np.arange(T))
        names.append(ew)
        n_ep += 1
    if not n_ep:
        raise IngestError(f"{where}: no episodes")
    n_steps = sum(len(r) for r in cols["rew"])
    for key, found in (("total_episodes", n_ep), ("total_steps", n_steps)):
        declared = meta.get(key)
        if declared is not None and declared != found:
            raise IngestError(f"{where}: metadata {key} = {declared!r} but {found} were read (a missing or damaged episode file)")
    cat = {c: np.concatenate(v) if v else np.zeros(0) for c, v in cols.items()}
    acts = cat["act"]
    extra: dict[str, Any] = {}
    if discrete:
        n_act = int(mds.action_space.n)
        action = _integers(acts.reshape(-1), where, "actions", len(acts), 0, n_act - 1, f"Discrete({n_act}) indices")
        if info is None:
            table = action_table or ActionTable.from_values(np.arange(n_act, dtype=float))
    elif info is not None or action_table is not None:
        vals = _finite(acts, where, "actions")
        action = _action_indices(vals, (info.action_table if info is not None else action_table), where)  # type: ignore[union-attr]
        table = action_table  # type: ignore[assignment]
    else:
        action, table, extra = _encode_actions(_finite(acts, where, "actions"), where)
    if info is None:
        info = _default_info(d, table, feature_names, str(meta.get("dataset_id", "minari")))
    if len(info.features) != d:
        raise IngestError(f"{where}: observations have {d} components, the metadata names {len(info.features)} features")
    if discrete and info.n_actions < int(mds.action_space.n):
        bad = action >= info.n_actions
        if bad.any():
            raise IngestError(f"{where}: actions: index {int(action[bad][0])} outside the {info.n_actions}-action table")
    bp = cat["bp"] if len(cat["bp"]) and not np.isnan(cat["bp"]).all() else None
    ds = TransitionDataset.from_arrays(
        info, episode_id=cat["ep"], step=cat["step"], obs=cat["obs"], action=action, cost=-cat["rew"],
        next_obs=cat["next"], terminated=cat["term"], truncated=cat["trunc"], source=cat["src"], behavior_prob=bp,
        t_ns=cat["t"] if len(cols["t"]) == n_ep else None, extra={**extra, **_provenance(names, cat["e"], cat["row"])})
    return _require_doctor(ds, where)


# ----------------------------------------------------------------------------- LeRobot
def to_lerobot(ds: TransitionDataset, root: str | PathLike[str], *, fps: float | None = None, task: str | None = None,
               robot_type: str = "unknown", overwrite: bool = False) -> Path:
    """Write ``ds`` in the LeRobot dataset layout (v2.1, no videos) under ``root``.

    ``fps`` defaults to the median step period of ``t_ns`` (else 1); ``task`` to the
    dataset's name. One frame per transition (see module docstring).
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    from offline_adp.data.io import atomic_directory

    c = _columns(ds)
    bounds = _episode_bounds(ds.episode_index)
    n, d = len(ds), len(ds.feature_names)
    ep_index = np.repeat(np.arange(len(bounds) - 1), np.diff(bounds))
    frame = np.arange(n) - bounds[:-1][ep_index]
    if fps is None:
        dt = np.diff(c["t_ns"])[(np.diff(ep_index) == 0)] if c["t_ns"] is not None and n > 1 else np.zeros(0)
        fps = float(1e9 / np.median(dt)) if len(dt) and np.median(dt) > 0 else 1.0
    if c["t_ns"] is not None:
        timestamp = (c["t_ns"] - c["t_ns"][bounds[:-1][ep_index]]) / 1e9
    else:
        timestamp = frame / fps
    at = ds.info.action_table
    values = at.values[c["action"]]
    task = task or ds.info.name or ds.info.problem or "offline_adp dataset"

    def lst(x: np.ndarray) -> pa.Array:
        return pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(x).reshape(-1)), x.shape[1])

    feats = {
        "observation.state": {"dtype": "float64", "shape": [d], "names": list(ds.feature_names),
                              "units": [f.unit for f in ds.info.features]},
        "action": {"dtype": "float64", "shape": [values.shape[1]], "names": list(at.dims), "units": list(at.units)},
        "action_index": {"dtype": "int64", "shape": [1], "names": None},
        "next.observation.state": {"dtype": "float64", "shape": [d], "names": list(ds.feature_names)},
        "next.reward": {"dtype": "float64", "shape": [1], "names": None},
        "next.done": {"dtype": "bool", "shape": [1], "names": None},
        "next.truncated": {"dtype": "bool", "shape": [1], "names": None},
        "timestamp": {"dtype": "float32", "shape": [1], "names": None},
        "frame_index": {"dtype": "int64", "shape": [1], "names": None},
        "episode_index": {"dtype": "int64", "shape": [1], "names": None},
        "index": {"dtype": "int64", "shape": [1], "names": None},
        "task_index": {"dtype": "int64", "shape": [1], "names": None},
    }
    chunks = 1000
    with atomic_directory(root, overwrite=overwrite) as tmp:
        meta = tmp / "meta"
        meta.mkdir()
        lines = []
        for k, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
            sl = slice(lo, hi)
            table = pa.table({
                "observation.state": lst(c["obs"][sl]), "action": lst(values[sl]),
                "action_index": pa.array(c["action"][sl]), "next.observation.state": lst(c["next_obs"][sl]),
                "next.reward": pa.array(-c["cost"][sl]), "next.done": pa.array(c["terminated"][sl]),
                "next.truncated": pa.array(c["truncated"][sl]), "timestamp": pa.array(timestamp[sl].astype(np.float32)),
                "frame_index": pa.array(frame[sl]), "episode_index": pa.array(ep_index[sl]),
                "index": pa.array(np.arange(lo, hi)), "task_index": pa.array(np.zeros(hi - lo, np.int64))})
            f = tmp / "data" / f"chunk-{k // chunks:03d}" / f"episode_{k:06d}.parquet"
            f.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(table, f)
            lines.append(json.dumps({"episode_index": k, "tasks": [task], "length": int(hi - lo),
                                     "episode_id": str(c["episode_id"][lo]), "source": str(c["source"][lo])}))
        (meta / "episodes.jsonl").write_text("\n".join(lines) + ("\n" if lines else ""))
        frames = {"observation.state": c["obs"], "action": values, "action_index": c["action"],
                  "next.observation.state": c["next_obs"], "next.reward": -c["cost"], "next.done": c["terminated"],
                  "next.truncated": c["truncated"], "timestamp": timestamp.astype(np.float32), "frame_index": frame,
                  "episode_index": ep_index, "index": np.arange(n), "task_index": np.zeros(n, np.int64)}
        (meta / "episodes_stats.jsonl").write_text(_episodes_stats(frames, bounds))
        (meta / "tasks.jsonl").write_text(json.dumps({"task_index": 0, "task": task}) + "\n")
        n_ep = len(bounds) - 1
        info = {"codebase_version": "v2.1", "robot_type": robot_type, "total_episodes": n_ep, "total_frames": n,
                "total_tasks": 1, "total_videos": 0, "total_chunks": (n_ep + chunks - 1) // chunks, "chunks_size": chunks,
                "fps": fps, "splits": {"train": f"0:{n_ep}"},
                "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet", "video_path": None,
                "features": feats, "offline_adp": json.loads(ds.info.to_json())}
        (meta / "info.json").write_text(json.dumps(info, indent=1))
    log.info("wrote LeRobot-layout dataset %s: %d episodes, %d frames", root, n_ep, n)
    return Path(root)


def _episodes_stats(frames: dict[str, np.ndarray], bounds: np.ndarray) -> str:
    """``meta/episodes_stats.jsonl`` of LeRobot v2.1: per episode, per feature, ``min``,
    ``max``, ``mean``, ``std`` (population) per component and ``count`` (frames), from
    the frames as written (a scalar feature has one component), all episodes at once."""
    starts = bounds[:-1]
    n_ep = len(starts)
    if n_ep == 0:
        return ""
    lengths = np.diff(bounds).astype(np.int64)
    ep = np.repeat(np.arange(n_ep), lengths)
    stats: dict[str, dict[str, np.ndarray]] = {}
    for name, x in frames.items():
        a = np.asarray(x, dtype=np.float64).reshape(len(x), -1)
        mean = np.add.reduceat(a, starts, axis=0) / lengths[:, None]
        var = np.add.reduceat((a - mean[ep]) ** 2, starts, axis=0) / lengths[:, None]
        stats[name] = {"min": np.minimum.reduceat(a, starts, axis=0), "max": np.maximum.reduceat(a, starts, axis=0),
                       "mean": mean, "std": np.sqrt(var)}
    lines = []
    for k in range(n_ep):  # one line per episode (the output's size)
        per = {name: {**{s: v[k].tolist() for s, v in st.items()}, "count": [int(lengths[k])]}
               for name, st in stats.items()}
        lines.append(json.dumps({"episode_index": k, "stats": per}))
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- CLI entry
FORMATS = ("dataset", "d4rl", "minari", "lerobot")


def convert(source: str, out: str, *, from_format: str = "dataset", to_format: str = "dataset",
            overwrite: bool = False) -> Path:
    """``offline-adp convert``: read ``source`` in ``from_format`` (a dataset directory,
    a D4RL ``.npz``, a local Minari dataset id or path) and write ``out`` in ``to_format``
    (a dataset directory, a ``.npz`` file, a Minari dataset id under
    ``MINARI_DATASETS_PATH``, a LeRobot-layout directory)."""
    from offline_adp.data.io import read_dataset
    from offline_adp.errors import UnknownNameError

    for f in (from_format, to_format):
        if f not in FORMATS:
            raise UnknownNameError(f"unknown dataset format {f!r}; known: {list(FORMATS)}")
    if from_format == "lerobot":
        raise OfflineADPError("reading the LeRobot layout is not supported (export only)")
    readers = {"dataset": read_dataset, "d4rl": from_d4rl, "minari": from_minari}
    ds = readers[from_format](source)
    if from_format == "dataset":  # d4rl / minari readers run the doctor themselves
        from offline_adp.data.validate import require_usable

        require_usable(ds, source)
    if to_format == "dataset":
        ds.save(out, overwrite=overwrite)
        return Path(out)
    if to_format == "d4rl":
        if Path(out).exists() and not overwrite:
            raise OfflineADPError(f"{out} already exists; pass --overwrite to replace it")
        return save_d4rl(ds, out)
    if to_format == "minari":
        return to_minari(ds, out)
    return to_lerobot(ds, out, overwrite=overwrite)
