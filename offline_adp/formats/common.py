"""What the format converters share: bounds on imported files, column and action encodings,
checks of imported arrays, provenance and the doctor's verdict."""

from __future__ import annotations

from dataclasses import replace
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import ACTION_VALUE_PREFIX, ActionTable, DatasetInfo, Feature
from offline_adp.errors import IngestError, OfflineADPError, short_list
from offline_adp.progress import get_logger

log = get_logger(__name__)

META_KEY = "metadata/offline_adp"


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
ACTION_VALUE = ACTION_VALUE_PREFIX
_INT32_MAX = int(np.iinfo(np.int32).max)


def _columns(ds: TransitionDataset) -> dict[str, Any]:
    a = ds.arrays()
    out = {"obs": a.obs, "next_obs": a.next_obs, "action": a.action.astype(np.int64), "cost": a.cost,
           "terminated": a.terminated.astype(bool), "truncated": a.truncated.astype(bool),
           "step": a.step.astype(np.int64),
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


def _finite_floats(a: np.ndarray, where: str, field: str) -> np.ndarray:
    """Float64 copy of ``a``; NaN or infinity is an IngestError naming the field and row."""
    v = np.asarray(a, dtype=np.float64)
    bad = ~np.isfinite(v)
    if bad.any():
        i = int(np.argmax(bad.reshape(len(v), -1).any(axis=1)))
        raise IngestError(f"{where}: {field}: row {i}: value "
                          f"{v[i].tolist() if v.ndim > 1 else float(v[i])!r} is NaN or "
                          f"infinite ({int(bad.reshape(len(v), -1).any(axis=1).sum())} rows); the format stores "
                          "finite values")
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
        raise IngestError(f"{where}: actions have {vals.shape[1]} components, the action table {tv.shape[1]} "
                          f"{list(table.dims)}")
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
                          f"{short_list(tv.tolist())} ({int((idx < 0).sum())} rows); pass action_table=, or "
                          "bin continuous actions with an ingestion spec")
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
        per.append((np.clip(np.searchsorted(edges, col, side="right") - 1, 0, m - 1), (edges[:-1] + edges[1:]) / 2,
                    edges))
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

    table = ActionTable(actions=tuple(Action(nm,
                                             tuple(float(x) for x in v)) for nm, v in zip(names, value, strict=True)),
                        dims=dims, kind="binned", bin_edges=tuple(float(e) for e in per[0][2]) if k == 1 else None)
    return idx.astype(np.int64), table


def _encode_actions(vals: np.ndarray, where: str, continuous: bool | None = None, *, low: Any = None,
                    high: Any = None) -> tuple[np.ndarray, ActionTable, dict[str, np.ndarray]]:
    """Action values (n, k) without a given table -> (indices, table, extra columns).

    At most :data:`MAX_EXACT_ACTIONS` distinct rows (and not ``continuous=True``): an
    exact discrete table of those rows. Otherwise continuous commands: kept exactly in
    ``action_value.<dim>`` float64 columns, a table of kind ``continuous`` whose entries
    are quantile bins (:func:`_binned`, the ``action`` column's coarse view) and whose
    bounds are ``low``/``high`` (a format's declared box, widened to the logged range),
    else the logged range."""
    vals = np.asarray(vals, np.float64).reshape(len(vals), -1)
    few = None if continuous else _unique_rows(vals, MAX_EXACT_ACTIONS)
    if few is not None and len(few[0]):
        uniq, inv = few
        table = _table_from_values(uniq)
        return inv.astype(np.int64), table, {}
    if not len(vals):
        raise IngestError(f"{where}: no transitions")
    idx, table = _binned(vals, where)
    # the exact commands are the actions (kind "continuous", bounds: the logged range, or the
    # declared ones a format gives); the bins stay as the coarse view
    lo = tuple(float(x) for x in (vals.min(axis=0) if low is None else np.minimum(low, vals.min(axis=0))))
    hi = tuple(float(x) for x in (vals.max(axis=0) if high is None else np.maximum(high, vals.max(axis=0))))
    table = replace(table, kind="continuous", low=lo, high=hi)
    extra = {ACTION_VALUE + d: np.ascontiguousarray(vals[:, j]) for j, d in enumerate(table.dims)}
    log.info("%s: continuous actions: %d distinct commands kept exactly in %s (coarse view: %d bins)",
             where, len(np.unique(vals, axis=0)), list(extra), len(table))
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
    import stat

    import offline_adp.artifacts.checks as C

    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise IngestError(f"{p}: no such file") from None
    if not stat.S_ISREG(st.st_mode):  # /dev/zero, a FIFO, a directory: refused before any read
        raise IngestError(f"{p}: not a regular file (a directory, device, pipe or socket); expected a D4RL .npz file")
    try:
        size = st.st_size
        # per member: deflate's own limit (~1032x; long runs of false flags compress that
        # well); the total is bounded below against the file size
        members = C.check_npz(p, max_expansion=1100,
                              name_pattern=re.compile(r"^[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*\.npy$"))
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


def _episode_bounds(ep_codes: np.ndarray) -> np.ndarray:
    return np.r_[np.flatnonzero(np.r_[True, ep_codes[1:] != ep_codes[:-1]]),
                 len(ep_codes)] if len(ep_codes) else np.zeros(1, int)
