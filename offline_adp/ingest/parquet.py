"""Parquet/CSV transition or step tables -> validated dataset directory.

The user's files are read as they are (only the spec's columns), mapped through the
spec, sorted by (episode, order), checked by the doctor, and written atomically. Every
row keeps ``src_file``/``src_row`` so a finding or a quarantined row names its origin.

Step tables (``kind = "steps"``) get ``next_obs`` by shifting within each episode. The
last row of an episode has no following row:

- if it is ``terminated``, ``next_obs`` is set to its own ``obs`` (a placeholder: no
  algorithm bootstraps through termination);
- otherwise, if the spec gives ``next_columns``, they supply its next state;
- otherwise the row cannot form a transition: it is dropped, the previous row becomes
  the episode's (truncated) end, and the count is reported in the summary and in
  ``info.json`` (``ingest.dropped_last_rows``) - never silently.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from offline_adp._version import __version__
from offline_adp.data import schema as S
from offline_adp.data.columns import encode_strings, sorted_encoding
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.files import locked_directory, sha256_file
from offline_adp.data.info import DatasetInfo, Feature
from offline_adp.data.io import write_dataset
from offline_adp.data.validate import ValidationReport, split_quarantine, validate
from offline_adp.errors import IngestError, ValidationError
from offline_adp.ingest.actions import (
    bin_continuous,
    command_actions,
    command_columns,
    map_discrete,
)
from offline_adp.ingest.spec import TIME_UNITS, ActionSpec, ParquetSpec, load_parquet_spec


@dataclass
class IngestResult:
    """What an ingestion produced and found."""

    dataset: TransitionDataset
    report: ValidationReport
    quarantined_rows: int = 0
    quarantined_episodes: int = 0
    dropped_last_rows: int = 0
    inputs: list[dict[str, Any]] = field(default_factory=list)
    path: Path | None = None
    quarantine: pa.Table | None = None

    def summary(self) -> dict[str, Any]:
        return {
            "episodes": self.dataset.n_episodes,
            "transitions": len(self.dataset),
            "per_source": self.dataset.source_counts(),
            "quarantined_episodes": self.quarantined_episodes,
            "quarantined_rows": self.quarantined_rows,
            "dropped_last_rows": self.dropped_last_rows,
            "terminated_and_truncated": self.report.n_terminated_and_truncated,
            "inputs": len(self.inputs),
        }


def _read(path: Path, spec: ParquetSpec) -> pa.Table:
    fmt = spec.format
    if fmt == "auto":
        suffix = "".join(path.suffixes[-2:]).lower()
        fmt = "csv" if ".csv" in suffix or ".tsv" in suffix else "parquet"
    cols = spec.needed_columns()
    try:
        if fmt == "csv":
            opts = pacsv.ReadOptions()
            table = pacsv.read_csv(path, read_options=opts, parse_options=pacsv.ParseOptions(delimiter=spec.csv_delimiter))
            available = table.column_names
        else:
            schema = pq.read_schema(path)
            available = schema.names
            table = None
    except FileNotFoundError:
        raise IngestError(f"{path}: no such file") from None
    except (OSError, pa.ArrowInvalid) as exc:
        raise IngestError(f"{path}: cannot read as {fmt} ({exc})") from exc
    missing = [c for c in cols if c not in available]
    if missing:
        raise IngestError(f"{path}: spec needs columns {missing} that the file does not have; it has {available}")
    if table is None:
        try:
            # column by column, without pre-buffering: only one column's compressed pages
            # are in memory besides the decoded table (read_table holds them all)
            # string columns of few distinct values arrive dictionary-encoded: the source
            # labels stay so (their strings are never materialised); the episode ids are
            # cast to strings once, at their exact size (decoding them as strings directly
            # grows buffers that peak at about 3x the column)
            as_dict = [c for c in dict.fromkeys((spec.episode.id, spec.source_column))
                       if c and c in available and pa.types.is_string(schema.field(c).type)] or None
            pf = pq.ParquetFile(path, pre_buffer=False, buffer_size=1 << 20, read_dictionary=as_dict)
            table = pa.table({c: pf.read(columns=[c], use_threads=False).column(0) for c in dict.fromkeys(cols)})
        except (OSError, pa.ArrowInvalid) as exc:
            raise IngestError(f"{path}: unreadable Parquet ({exc})") from exc
    table = table.select(cols)
    for name in cols:  # CSV cells that are not UTF-8 arrive as binary
        col = table.column(name)
        if pa.types.is_binary(col.type) or pa.types.is_large_binary(col.type):
            for i, v in enumerate(col.to_pylist()):  # error path only: stops at the first bad cell
                try:
                    if v is not None:
                        v.decode("utf-8")
                except UnicodeDecodeError:
                    raise IngestError(f"{path}: row {i} column {name!r}: not UTF-8 text; save the file as UTF-8") from None
            raise IngestError(f"{path}: column {name!r} holds binary data, not text or numbers")
    return table


def _where(file_of: Callable[[np.ndarray], str], i: int) -> str:
    """``"FILE: row R"`` of sorted row ``i`` (``file_of`` carries the row-in-file map)."""
    return f"{file_of(np.array([i]))}: row {getattr(file_of, 'rows', np.arange(i + 1))[i]}"


def _first_unparsable(c: pa.ChunkedArray, target: pa.DataType) -> int | None:
    """Index of the first non-null value of ``c`` that does not convert to ``target``."""
    if pa.types.is_string(c.type) or pa.types.is_large_string(c.type):
        import pandas as pd

        vals = pd.Series(c.to_numpy(zero_copy_only=False))
        bad = np.flatnonzero(pd.to_numeric(vals, errors="coerce").isna().to_numpy() & vals.notna().to_numpy())
        return int(bad[0]) if len(bad) else None
    return None


def _np(table: pa.Table, col: str, dtype: Any, file_of: Callable[[np.ndarray], str]) -> np.ndarray:
    c = table.column(col)
    if dtype is object:
        return c.to_numpy(zero_copy_only=False)
    numeric = pa.types.is_boolean(c.type) or pa.types.is_integer(c.type) or pa.types.is_floating(c.type) or pa.types.is_decimal(c.type)
    if not numeric and dtype is not bool:
        i = _first_unparsable(c, pa.float64())
        if i is not None:
            raise IngestError(f"{_where(file_of, i)}: column {col!r}: {c[i].as_py()!r} is not a number")
        try:
            c = c.cast(pa.float64())
        except (ValueError, TypeError, pa.ArrowInvalid, pa.ArrowNotImplementedError) as exc:
            raise IngestError(f"{file_of(np.array([0]))}: column {col!r} of type {c.type} cannot be read as "
                              f"{np.dtype(dtype).name} ({exc})") from None
    if c.null_count:
        bad = np.flatnonzero(np.asarray(pc.is_null(c)))
        if dtype is bool:
            return np.asarray(c.fill_null(False).to_numpy(zero_copy_only=False), dtype=bool)
        if np.dtype(dtype).kind == "f":
            return c.cast(pa.float64()).to_numpy(zero_copy_only=False).astype(dtype)  # nulls -> NaN, reported by the doctor
        raise IngestError(f"{_where(file_of, int(bad[0]))}: column {col!r} is missing ({len(bad)} missing values in the column)")
    return c.to_numpy(zero_copy_only=False).astype(dtype, copy=False)


def _f64(table: pa.Table, col: str, file_of: Callable[[np.ndarray], str], *, keep_nulls: bool = False) -> pa.ChunkedArray:
    """A numeric column as float64 in Arrow, without a copy when it already is float64:
    what :func:`_np` gives for ``np.float64`` (nulls -> NaN, reported by the doctor; with
    ``keep_nulls`` they stay null), without the conversion to numpy."""
    c = table.column(col)
    numeric = pa.types.is_integer(c.type) or pa.types.is_floating(c.type) or pa.types.is_decimal(c.type) or pa.types.is_boolean(c.type)
    if not numeric:
        return pa.chunked_array([pa.array(_np(table, col, np.float64, file_of), mask=np.asarray(pc.is_null(c)) if keep_nulls and c.null_count else None)])
    if c.type != pa.float64():
        c = c.cast(pa.float64(), safe=False)  # as numpy's astype: large integers round
    if c.null_count and not keep_nulls:
        c = c.fill_null(np.nan)
    return c


def _flag(table: pa.Table, col: str | None, n: int, file_of: Callable[[np.ndarray], str]) -> tuple[np.ndarray, np.ndarray]:
    """A bool flag column and its null mask (a null flag is kept null: the doctor reports
    it, it never silently becomes False)."""
    if not col:
        return np.zeros(n, bool), np.zeros(n, bool)
    c = table.column(col)
    if not pa.types.is_boolean(c.type):
        if pa.types.is_integer(c.type) or pa.types.is_floating(c.type):
            v = c.to_numpy(zero_copy_only=False)
            bad = np.flatnonzero(~np.isin(v, [0, 1]) & ~np.isnan(v.astype(np.float64)))
            if len(bad):
                raise IngestError(f"{_where(file_of, int(bad[0]))}: column {col!r}: {v[bad[0]]!r} is not a flag (true/false or 0/1)")
            c = pc.not_equal(c, 0)
        else:
            raise IngestError(f"{file_of(np.array([0]))}: column {col!r} of type {c.type} is not a flag column (bool or 0/1)")
    null = np.asarray(pc.is_null(c)) if c.null_count else np.zeros(n, bool)
    return np.asarray(c.fill_null(False).to_numpy(zero_copy_only=False), dtype=bool), null


def _steps(table: pa.Table, col: str, base: int, file_of: Callable[[np.ndarray], str]) -> np.ndarray | pa.ChunkedArray:
    """The step column minus ``base``: integral, within int32 (what the format stores); an
    int32 Arrow column (no copy when it already is one from 0) or an int64 array."""
    c = table.column(col)
    if pa.types.is_integer(c.type) and not c.null_count and len(c):
        mm = pc.min_max(c).as_py()
        if mm["min"] - base >= 0 and mm["max"] - base <= np.iinfo(np.int32).max:  # else: the error below
            if base:
                c = pc.subtract(c.cast(pa.int64()), base)
            return c.cast(pa.int32())
    v = _np(table, col, np.float64 if not pa.types.is_integer(c.type) else np.int64, file_of)
    if v.dtype.kind == "f":
        bad = np.flatnonzero(~np.isfinite(v) | (v != np.round(v)))
        if len(bad):
            raise IngestError(f"{_where(file_of, int(bad[0]))}: column {col!r}: step {float(v[bad[0]])!r} is not a whole number")
        if len(v) and np.abs(v).max() >= 2**62:
            i = int(np.argmax(np.abs(v)))
            raise IngestError(f"{_where(file_of, i)}: column {col!r}: step {float(v[i])!r} is out of range")
        v = v.astype(np.int64)
    step = v - base
    bad = np.flatnonzero((step < 0) | (step > np.iinfo(np.int32).max))
    if len(bad):
        raise IngestError(f"{_where(file_of, int(bad[0]))}: column {col!r}: step {int(v[bad[0]])} "
                          f"is outside [{base}, {base + np.iinfo(np.int32).max}] (steps are stored as int32 from 0)")
    return step


def _times_ns(table: pa.Table, col: str, unit: str, file_of: Callable[[np.ndarray], str]) -> pa.Array | pa.ChunkedArray:
    """Times in int64 nanoseconds; a time that is missing, not finite or beyond int64 stays
    null (the doctor reports it as a missing value of ``t_ns`` naming file and row)."""
    tv = table.column(col)
    try:
        if pa.types.is_timestamp(tv.type):
            return tv.cast(pa.timestamp("ns")).cast(pa.int64())
        if pa.types.is_integer(tv.type):
            tv = tv.cast(pa.int64())
            return tv if TIME_UNITS[unit] == 1 else pc.multiply_checked(tv, TIME_UNITS[unit])
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as exc:
        raise IngestError(f"{file_of(np.array([0]))}: column {col!r}: times do not fit int64 nanoseconds ({exc})") from None
    x = _np(table, col, np.float64, file_of) * TIME_UNITS[unit]
    ok = np.isfinite(x) & (np.abs(x) < 2.0**63 - 1024)
    return pa.array(np.where(ok, np.round(np.where(ok, x, 0.0)), 0).astype(np.int64), mask=~ok)


_ACTION_BLOCK = 1 << 17


def _blockwise(mapper: Callable[..., tuple[np.ndarray, Any]], raw: np.ndarray, spec: Any) -> tuple[np.ndarray, Any]:
    """``mapper(raw, spec)`` block by block when the action table does not depend on the
    data (discrete actions with given values): the same result, with the mapper's
    temporaries the size of a block instead of the column."""
    if mapper is not map_discrete or spec.values is None or len(raw) <= _ACTION_BLOCK:
        return mapper(raw, spec)
    out = np.empty(len(raw), np.int32)
    atable = None
    for lo in range(0, len(raw), _ACTION_BLOCK):
        out[lo:lo + _ACTION_BLOCK], atable = mapper(raw[lo:lo + _ACTION_BLOCK], spec)
    return out, atable


def _is_list(t: pa.DataType) -> bool:
    return pa.types.is_list(t) or pa.types.is_large_list(t) or pa.types.is_fixed_size_list(t)


def _commands(table: pa.Table, spec: ActionSpec, list_col: bool, file_of: Callable[[np.ndarray], str]
              ) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """The continuous command of every row, ``(n, k)`` float64 (missing values NaN: the
    doctor reports them), each row's list length (-1 when not a list column or the list is
    missing; a row of another width than ``k`` gets a NaN command), and the component names.

    Several columns: one component each. A list column: the width is the number of
    component names when the spec gives them, else the most common list length; a row
    whose list has another length is flagged, never cut or padded."""
    n = table.num_rows
    if not list_col:
        x = np.column_stack([_np(table, c, np.float64, file_of) for c in spec.source_columns]) if n else np.zeros((0, len(spec.source_columns)))
        return x, np.full(n, -1, np.int64), spec.component_names(x.shape[1])
    c = table.column(spec.column).combine_chunks()
    if pa.types.is_fixed_size_list(c.type):
        c = c.cast(pa.list_(c.type.value_type))
    lengths = pc.list_value_length(c).fill_null(-1).to_numpy(zero_copy_only=False).astype(np.int64)
    try:
        flat = pc.list_flatten(c).cast(pa.float64()).fill_null(np.nan).to_numpy(zero_copy_only=False)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError, pa.ArrowTypeError):
        raise IngestError(f"{file_of(np.array([0]))}: column {spec.column!r}: lists of {c.type.value_type} are not "
                          "numeric commands") from None
    if spec.components is not None:
        k = len(spec.components)
    else:
        seen = lengths[lengths > 0]
        if not len(seen):
            raise IngestError(f"{file_of(np.array([0]))}: column {spec.column!r}: every command list is empty or missing")
        k = int(np.argmax(np.bincount(seen)))
    good = lengths == k  # a missing list (null) is a missing command: NaN; another length is flagged
    offsets = np.cumsum(np.r_[0, np.maximum(lengths, 0)])[:-1]  # into the flattened (non-null) values
    x = np.full((n, k), np.nan)
    rows = np.flatnonzero(good)
    x[rows] = flat[offsets[rows, None] + np.arange(k)]
    return x, lengths, spec.component_names(k, list_column=True)


def _width_findings(lengths: np.ndarray, spec: ActionSpec, atable: Any) -> list[tuple[str, np.ndarray, str, Any]]:
    """The doctor's findings for command lists of the wrong width (``validate(extra=...)``):
    ``lengths`` is each row's list length (-1: not a list, or missing)."""
    k = len(atable.dims)
    bad = (lengths >= 0) & (lengths != k)
    if not bad.any():
        return []
    msg = np.full(len(bad), "", dtype=object)
    msg[bad] = [f"a list of {m} values where the command has {k} components {list(atable.dims)}; its command is "
                "left missing" for m in lengths[bad]]
    return [("command_width", bad, spec.column, msg)]


def _type_conflict(tables: list[pa.Table], metas: list[dict[str, Any]]) -> str | None:
    """Which column has which type in which two files, when files disagree."""
    first: dict[str, tuple[pa.DataType, str]] = {}
    for t, m in zip(tables, metas, strict=True):
        for f in t.schema:
            if f.name in first and first[f.name][0] != f.type:
                a_type, a_path = first[f.name]
                try:
                    pa.concat_tables([pa.table({f.name: pa.array([], a_type)}), pa.table({f.name: pa.array([], f.type)})],
                                     promote_options="permissive")
                except (pa.ArrowInvalid, pa.ArrowTypeError, pa.ArrowNotImplementedError):
                    return (f"column {f.name!r} is {a_type} in {a_path} but {f.type} in {m['path']}; "
                            "give the column one type in every file")
            first.setdefault(f.name, (f.type, m["path"]))
    return None


def ingest_tables(
    inputs: Sequence[str | PathLike[str]],
    spec: ParquetSpec,
    *,
    on_error: str | None = None,
    progress: Callable[[str], None] | None = None,
) -> IngestResult:
    """Read, map, sort and check the inputs; returns the (clean) dataset and report."""
    on_error = on_error or spec.on_error
    if on_error not in ("fail", "quarantine"):
        raise IngestError(f"on_error must be 'fail' or 'quarantine', got {on_error!r}")
    paths = [Path(p) for p in inputs]
    if not paths:
        raise IngestError("no input files given")
    # every intermediate of the mapping (and the input's columns the dataset does not
    # share) is freed when _map returns, before validation and writing
    out, atable, dropped, metas, names, enc, width = _map(paths, spec, progress)
    units = dict(spec.observations.units)
    info = DatasetInfo(
        features=tuple(Feature(nm, units.get(nm, "")) for nm in names),
        action_table=atable,
        gamma=spec.gamma,
        horizon=spec.horizon,
        propensity_source="logged" if spec.propensity_column else "unknown",
        provenance={
            "inputs": metas,
            "spec": spec.raw,
            "spec_sha256": spec.sha256,
            "package_version": __version__,
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "generator": "offline-adp ingest parquet",
        },
        name=spec.name,
    )
    ds = TransitionDataset(out, info, _sorted_ids=enc)  # sorted by _map: not checked again
    del out, enc  # the dataset holds what it needs (its table, int64 codes)
    if progress:
        progress("validating")
    report = validate(ds, extra=width)  # names src_file/src_row of each finding
    result = IngestResult(ds, report, dropped_last_rows=dropped, inputs=metas)
    if not report.ok:
        if on_error == "fail":
            raise ValidationError(
                report.to_text() + "\nFix the input, or re-run with --on-error quarantine to set bad episodes aside.",
                report,
            )
        clean, rejected = split_quarantine(ds, report)
        result.dataset = clean
        result.quarantine = rejected
        result.quarantined_rows = rejected.num_rows
        result.quarantined_episodes = int(len(report.bad_episodes))
    return result


def _map(paths: list[Path], spec: ParquetSpec, progress: Callable[[str], None] | None
         ) -> tuple[pa.Table, Any, int, list[dict[str, Any]], list[str], pa.DictionaryArray | None, list[Any]]:
    """Read the inputs and map them through the spec: the dataset's table (sorted by
    episode and step), action table, dropped last rows, input metadata, feature names, the
    episode ids' encoding for the table's rows (None when rows were dropped), and the
    findings of command lists of the wrong width (for :func:`validate`'s ``extra``)."""
    tables, metas = [], []
    # input hashes (provenance) are computed in a thread while the tables are read
    with ThreadPoolExecutor(max_workers=1) as hasher:
        hashes = [hasher.submit(sha256_file, p) if p.is_file() else None for p in paths]
        for k, p in enumerate(paths):
            if progress:
                progress(f"reading {p}")
            t = _read(p, spec)
            ids = t.column(spec.episode.id)
            if ids.null_count:
                i = int(np.flatnonzero(np.asarray(pc.is_null(ids)))[0])
                raise IngestError(f"{p}: row {i} column {spec.episode.id!r}: episode id is missing (null); every row needs one")
            t = t.append_column("__file", pa.array(np.full(t.num_rows, k, np.int32))).append_column(
                "__row", pa.array(np.arange(t.num_rows, dtype=np.int64))
            )
            # unify id column type across files
            t = t.set_column(0, spec.episode.id, t.column(spec.episode.id).cast(pa.string()))
            src = spec.source_column
            if src and src != spec.episode.id:  # text labels: dictionary<int32, string> in every file
                j = t.column_names.index(src)
                c = t.column(j)
                if pa.types.is_dictionary(c.type) and pa.types.is_string(c.type.value_type):
                    pass
                elif pa.types.is_string(c.type) or pa.types.is_large_string(c.type):
                    t = t.set_column(j, src, pc.dictionary_encode(c.cast(pa.string())))
            tables.append(t)
            metas.append({"path": str(p), "sha256": None, "rows": t.num_rows})
            del t
        for m, h in zip(metas, hashes, strict=True):
            m["sha256"] = h.result() if h is not None else None
    try:
        table = pa.concat_tables(tables, promote_options="permissive")
    except (pa.ArrowInvalid, pa.ArrowTypeError, pa.ArrowNotImplementedError) as exc:
        raise IngestError(_type_conflict(tables, metas) or f"input files have incompatible column types: {exc}") from None
    names_of = np.array([m["path"] for m in metas], dtype=object)
    if table.num_rows == 0:  # e.g. a CSV with a header and no rows
        raise IngestError(f"{', '.join(str(m['path']) for m in metas)}: no rows (only a header, or empty tables); "
                          "nothing to ingest")

    # episodes may not span files (they would silently merge)
    ep_file = None if len(paths) == 1 else pa.table({"e": table.column(spec.episode.id), "f": table.column("__file")}).group_by("e").aggregate([("f", "count_distinct"), ("f", "min"), ("f", "max")])
    multi = ep_file.filter(pc.greater(ep_file.column("f_count_distinct"), 1)) if ep_file is not None else None
    if multi is not None and multi.num_rows:
        r = multi.slice(0, 1).to_pylist()[0]
        raise IngestError(
            f"episode id {r['e']!r} occurs in {names_of[r['f_min']]} and {names_of[r['f_max']]} "
            f"({multi.num_rows} ids in several files); give each file distinct episode ids"
        )

    # order within episodes
    order_col = spec.episode.step or spec.episode.order or spec.episode.time
    assert order_col is not None
    enc = sorted_encoding(table.column(spec.episode.id), table.column(order_col).to_numpy(zero_copy_only=False))
    if enc is None:  # sort only when needed (ties keep file order)
        idx = pc.sort_indices(table, sort_keys=[(spec.episode.id, "ascending"), (order_col, "ascending"), ("__file", "ascending"), ("__row", "ascending")])
        table = table.take(idx)
        enc = encode_strings(table.column(spec.episode.id))
    n = table.num_rows
    fidx = table.column("__file").to_numpy()
    rows = table.column("__row").to_numpy()

    def file_of(i: np.ndarray) -> str:
        return str(names_of[fidx[i[0]]]) if len(i) else "?"

    file_of.rows = rows  # type: ignore[attr-defined]  # row in its file, for _where

    ep_ids = table.column(spec.episode.id)
    codes = enc.indices.to_numpy(zero_copy_only=False)  # int32: a view
    first = np.r_[True, codes[1:] != codes[:-1]] if n else np.zeros(0, bool)
    last = np.r_[codes[1:] != codes[:-1], True] if n else np.zeros(0, bool)
    starts = np.flatnonzero(first)
    lens = np.diff(np.r_[starts, n])
    if spec.episode.step:
        step = _steps(table, spec.episode.step, spec.episode.step_base, file_of)
    else:
        # dense rank of the order value within the episode: ties share a step (doctor flags them)
        ov = table.column(order_col).to_numpy(zero_copy_only=False)
        new_val = np.r_[True, ov[1:] != ov[:-1]] if n else np.zeros(0, bool)
        new_val = new_val | first
        cum = np.cumsum(new_val) - 1
        step = cum - np.repeat(cum[starts], lens)

    # float64 columns stay the input's Arrow buffers (no copy); steps tables shift in numpy
    obs: list[Any] = [_f64(table, c, file_of) for c in spec.observations.columns]
    has_next = bool(spec.observations.next_columns)
    nxt_given: list[Any] | None = [_f64(table, c, file_of) for c in spec.observations.next_columns] if has_next else None

    term, term_null = _flag(table, spec.terminated_column, n, file_of)
    trunc_col, trunc_null = _flag(table, spec.truncated_column, n, file_of)
    # rule: an episode's end is truncated unless the terminal column says terminated
    trunc = trunc_col | (last & ~term)

    keep = np.ones(n, bool)
    dropped = 0
    if spec.kind == "transitions":
        assert nxt_given is not None
        nxt = nxt_given
    else:
        end_term = last & term
        nxt = []
        obs = [o.to_numpy() for o in obs]
        if nxt_given is not None:
            nxt_given = [x.to_numpy() for x in nxt_given]
        for j, o in enumerate(obs):
            x = np.empty_like(o)
            x[:-1] = o[1:]
            x[end_term] = o[end_term]  # placeholder: never bootstrapped through termination
            if n:
                x[-1] = o[-1]
            if has_next:
                sel = last & ~term
                x[sel] = nxt_given[j][sel]  # type: ignore[index]
            nxt.append(x)
        if not has_next:
            drop = last & ~term
            dropped = int(drop.sum())
            keep = ~drop
            d = np.flatnonzero(drop)
            prev = d - 1
            same = (prev >= 0) & (codes[np.maximum(prev, 0)] == codes[d])
            trunc = trunc.copy()
            trunc[prev[same]] = True  # the previous row becomes the episode's truncated end

    # actions from the rows that stay (a dropped row must not shape the bins)
    all_kept = bool(keep.all())
    aspec = spec.action
    list_col = not aspec.columns and _is_list(table.column(aspec.column).type)
    if list_col and aspec.type == "discrete":
        if aspec.type_declared:
            raise IngestError(f"{file_of(np.array([0]))}: column {aspec.column!r} holds lists (a command vector per row): "
                              "set action.type = 'continuous' (discrete actions are one label per row)")
        aspec = replace(aspec, type="continuous", components=aspec.names, names=None)  # names: its components
    elif aspec.type == "discrete" and (aspec.low is not None or aspec.high is not None or aspec.units is not None):
        raise IngestError(f"{file_of(np.array([0]))}: column {aspec.column!r} holds one label per row: action.low/high/"
                          "units are only for continuous commands (type = 'continuous')")
    commands: dict[str, Any] = {}
    widths = np.full(n, -1, np.int64)
    if aspec.type == "discrete":
        raw_action = table.column(aspec.column).to_numpy(zero_copy_only=False)
        if all_kept:
            action, atable = _blockwise(map_discrete, raw_action, aspec)
        else:
            action = np.full(n, -1, np.int32)
            action[keep], atable = map_discrete(raw_action[keep], aspec)
        del raw_action
    elif not aspec.exact and not aspec.columns and not list_col and all_kept and not (aspec.low or aspec.high or aspec.units):
        # a binned scalar column as before (block by block), its exact commands kept alongside
        raw_action = _np(table, aspec.column, np.float64, file_of)
        action, atable = _blockwise(bin_continuous, raw_action, aspec)
        commands = command_columns(raw_action, atable.dims)
        del raw_action
    else:
        x, widths, dims = _commands(table, aspec, list_col, file_of)
        where = f"{file_of(np.array([0]))}: action"
        vector = bool(aspec.columns) or list_col
        if all_kept:
            action, atable = command_actions(x, aspec, dims, vector=vector, where=where)
        else:
            action = np.full(n, -1, np.int32)
            action[keep], atable = command_actions(x[keep], aspec, dims, vector=vector, where=where)
        commands = command_columns(x, dims)
        del x
    if spec.cost_column:
        cost = _f64(table, spec.cost_column, file_of)
    else:
        cost = pc.negate(_f64(table, spec.reward_column, file_of))  # type: ignore[arg-type]

    names = list(spec.observations.names or spec.observations.columns)
    cols: dict[str, Any] = {S.EPISODE_ID: ep_ids, S.STEP: step.astype(np.int32) if isinstance(step, np.ndarray) else step}
    if spec.episode.time:
        cols[S.T_NS] = _times_ns(table, spec.episode.time, spec.episode.time_unit, file_of)
    for j, nm in enumerate(names):
        cols[S.obs_column(nm)] = obs[j]
    cols[S.ACTION] = action
    cols.update(commands)
    cols[S.COST] = cost
    for j, nm in enumerate(names):
        cols[S.next_obs_column(nm)] = nxt[j]
    cols[S.TERMINATED] = pa.array(term, mask=term_null) if term_null.any() else term
    cols[S.TRUNCATED] = pa.array(trunc, mask=trunc_null) if trunc_null.any() else trunc
    if spec.source_column:
        src = table.column(spec.source_column)
        if pa.types.is_dictionary(src.type):  # read as such: one dictionary for every chunk
            cols[S.SOURCE] = src.cast(pa.dictionary(pa.int32(), pa.string())).unify_dictionaries().combine_chunks()
        else:
            cols[S.SOURCE] = encode_strings(src.cast(pa.string()))
    else:
        cols[S.SOURCE] = pa.DictionaryArray.from_arrays(pa.array(np.zeros(n, np.int32)), pa.array([spec.source_value]))
    if spec.propensity_column:
        # a non-number names its file and row; a missing value stays null (the doctor's business)
        cols[S.BEHAVIOR_PROB] = _f64(table, spec.propensity_column, file_of, keep_nulls=True)
    cols["src_file"] = pa.DictionaryArray.from_arrays(pa.array(fidx.astype(np.int32, copy=False)), pa.array(names_of.astype(str).tolist()))
    cols["src_row"] = table.column("__row")
    # chunked columns stay chunked: the output shares the input's buffers where it can
    out = pa.table(cols)
    width = _width_findings(widths, aspec, atable)
    if not all_kept:
        out = out.filter(pa.array(keep))
        width = [(c, m[keep], col, msg) for c, m, col, msg in width]
    return out, atable, dropped, metas, names, enc if all_kept else None, width



def ingest_parquet(
    inputs: Sequence[str | PathLike[str]],
    spec: ParquetSpec | str | PathLike[str],
    out: str | PathLike[str],
    *,
    on_error: str | None = None,
    overwrite: bool = False,
    progress: Callable[[str], None] | None = None,
) -> IngestResult:
    """Ingest Parquet/CSV tables into a dataset directory at ``out`` (atomic write).

    Raises
    ------
    SpecError
        The spec is malformed.
    IngestError
        An input is unreadable or lacks a column the spec names.
    ValidationError
        The doctor found defects and ``on_error`` is ``"fail"`` (the default).
    """
    if not isinstance(spec, ParquetSpec):
        spec = load_parquet_spec(spec)
    with locked_directory(out, what="dataset"):  # a second ingest into `out` fails now, not at the end
        return _ingest_locked(inputs, spec, out, on_error=on_error, overwrite=overwrite, progress=progress)


def _ingest_locked(inputs: Sequence[str | PathLike[str]], spec: ParquetSpec, out: str | PathLike[str], *,
                   on_error: str | None, overwrite: bool, progress: Callable[[str], None] | None) -> IngestResult:
    if (Path(out).exists() or Path(out).is_symlink()) and not overwrite:
        raise IngestError(f"{out} already exists; pass overwrite=True (CLI: --overwrite) to replace it")
    res = ingest_tables(inputs, spec, on_error=on_error, progress=progress)
    if progress:
        progress(f"writing {out}")
    res.path = write_dataset(
        res.dataset,
        out,
        overwrite=overwrite,
        quarantine=res.quarantine,
        extra_meta={
            "ingest": {
                "doctor": res.report.summary(),
                "quarantined_rows": res.quarantined_rows,
                "quarantined_episodes": res.quarantined_episodes,
                "dropped_last_rows": res.dropped_last_rows,
            }
        },
    )
    return res
