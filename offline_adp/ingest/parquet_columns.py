"""The columns of a Parquet/CSV ingestion (:mod:`offline_adp.ingest.parquet`): the user's file
read as it is (only the spec's columns; CSV text checked to be UTF-8), and each column
converted to what the dataset format stores (numbers, flags, steps from 0 in int32, times in
int64 nanoseconds, actions block by block, continuous commands from columns or lists), an
error naming the file and row of the first value that does not convert.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from offline_adp.data.columns import bool_values
from offline_adp.errors import IngestError
from offline_adp.ingest.actions import map_discrete
from offline_adp.ingest.spec import TIME_UNITS, ActionSpec, ParquetSpec


def _read(path: Path, spec: ParquetSpec) -> pa.Table:
    fmt = spec.format
    if fmt == "auto":
        suffix = "".join(path.suffixes[-2:]).lower()
        fmt = "csv" if ".csv" in suffix or ".tsv" in suffix else "parquet"
    cols = spec.needed_columns()
    try:
        if fmt == "csv":
            # columns compared as text (episode ids, source labels, text action labels) are read
            # as the file's exact text: type inference would make '007' and '7' (or '1.1' and
            # '1.10') one value
            table = pacsv.read_csv(path, read_options=pacsv.ReadOptions(),
                                   parse_options=pacsv.ParseOptions(delimiter=spec.csv_delimiter),
                                   convert_options=pacsv.ConvertOptions(
                                       column_types={c: pa.binary() for c in spec.text_columns()}))
            try:
                available = table.column_names
            except UnicodeDecodeError:
                raise IngestError(f"{path}: the header (column names) is not UTF-8 text; save the file as "
                                  "UTF-8") from None
            table = _csv_text(table, spec)
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
        from offline_adp.config import did_you_mean

        raise IngestError(f"{path}: spec needs columns {missing} that the file does not have"
                          f"{did_you_mean(missing, available)}; it has {available}")
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
                    raise IngestError(f"{path}: row {i} column {name!r}: not UTF-8 text; save the "
                                      "file as UTF-8") from None
            raise IngestError(f"{path}: column {name!r} holds binary data, not text or numbers")
    return table


def _csv_text(table: pa.Table, spec: ParquetSpec) -> pa.Table:
    """A CSV's text columns (read as bytes) as strings; a column that is not UTF-8 stays
    binary (:func:`_read` names its first bad cell). An empty cell is a missing value (null),
    as the CSV reader makes it of a number column: a missing id, source or label, reported."""
    for c in spec.text_columns():
        if c not in table.column_names:
            continue
        j = table.column_names.index(c)
        try:
            col = table.column(j).cast(pa.string())
        except pa.ArrowInvalid:
            continue
        col = pc.if_else(pc.equal(col, ""), pa.scalar(None, pa.string()), col)
        table = table.set_column(j, c, col)
    return table


def _one_chunk(table: pa.Table, j: int) -> pa.Table:
    """``table`` with column ``j``, if it is fixed-width (numbers, flags, times) and in
    several chunks (one per Parquet row group, CSV block or input file), combined into one:
    one copy here instead of one at every later ``to_numpy`` (the mapping, the doctor, the
    statistics, the episode table). Text columns stay chunked (they are encoded chunk by
    chunk). The written parts are the same (their pages do not depend on the chunking)."""
    c = table.column(j)
    t = c.type
    if c.num_chunks > 1 and (pa.types.is_integer(t) or pa.types.is_floating(t) or pa.types.is_boolean(t)
                             or pa.types.is_temporal(t)):
        return table.set_column(j, table.field(j), pa.chunked_array([c.combine_chunks()], t))
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
    numeric = (
        pa.types.is_boolean(c.type)
        or pa.types.is_integer(c.type)
        or pa.types.is_floating(c.type)
        or pa.types.is_decimal(c.type)
    )
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
            # nulls -> NaN, reported by the doctor
            return c.cast(pa.float64()).to_numpy(zero_copy_only=False).astype(dtype)
        raise IngestError(f"{_where(file_of, int(bad[0]))}: column {col!r} is missing ({len(bad)} missing values "
                          "in the column)")
    return c.to_numpy(zero_copy_only=False).astype(dtype, copy=False)


def _f64(table: pa.Table, col: str, file_of: Callable[[np.ndarray], str], *,
         keep_nulls: bool = False) -> pa.ChunkedArray:
    """A numeric column as float64 in Arrow, without a copy when it already is float64:
    what :func:`_np` gives for ``np.float64`` (nulls -> NaN, reported by the doctor; with
    ``keep_nulls`` they stay null), without the conversion to numpy."""
    c = table.column(col)
    numeric = (
        pa.types.is_integer(c.type)
        or pa.types.is_floating(c.type)
        or pa.types.is_decimal(c.type)
        or pa.types.is_boolean(c.type)
    )
    if not numeric:
        return pa.chunked_array([pa.array(_np(table, col, np.float64, file_of),
                                          mask=np.asarray(pc.is_null(c)) if keep_nulls and c.null_count else None)])
    if pa.types.is_integer(c.type):
        _check_exact_integers(c, col, file_of)
    if c.type != pa.float64():
        c = c.cast(pa.float64(), safe=False)
    if c.null_count and not keep_nulls:
        c = c.fill_null(np.nan)
    return c


def _check_exact_integers(c: pa.ChunkedArray, col: str, file_of: Callable[[np.ndarray], str]) -> None:
    """An integer column converted to float64 must not hold a value beyond 2^53, which a
    float64 would round silently; the error names the file, row, column and value."""
    mm = pc.min_max(c).as_py()
    if mm["min"] is None or (-(2**53) <= mm["min"] and mm["max"] <= 2**53):
        return
    big = pc.greater(c, pa.scalar(2**53, c.type))
    if not pa.types.is_unsigned_integer(c.type):
        big = pc.or_(big, pc.less(c, pa.scalar(-(2**53), c.type)))
    i = int(np.argmax(np.asarray(big.fill_null(False))))
    raise IngestError(f"{_where(file_of, i)}: column {col!r}: integer {c[i].as_py()} is beyond 2^53, where a float64 "
                      "would round it (the dataset stores floats); rescale the column, e.g. subtract an offset")


def _flag(table: pa.Table, col: str | None, n: int, file_of: Callable[[np.ndarray],
                                                                      str]) -> tuple[np.ndarray, np.ndarray | None]:
    """A bool flag column (a fresh array, the caller's to change) and its null mask, None
    without nulls (a null flag is kept null: the doctor reports it, it never silently
    becomes False)."""
    if not col:
        return np.zeros(n, bool), None
    c = table.column(col)
    if not pa.types.is_boolean(c.type):
        if pa.types.is_integer(c.type) or pa.types.is_floating(c.type):
            v = c.to_numpy(zero_copy_only=False)
            bad = np.flatnonzero(~np.isin(v, [0, 1]) & ~np.isnan(v.astype(np.float64)))
            if len(bad):
                raise IngestError(f"{_where(file_of, int(bad[0]))}: column {col!r}: {v[bad[0]]!r} is not a flag "
                                  "(true/false or 0/1)")
            c = pc.not_equal(c, 0)
        else:
            raise IngestError(f"{file_of(np.array([0]))}: column {col!r} of type {c.type} is not a flag column "
                              "(bool or 0/1)")
    null = np.asarray(pc.is_null(c)) if c.null_count else None
    return bool_values(c), null  # a null as False (and in the mask)


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
        if pa.types.is_unsigned_integer(c.type) and mm["max"] > np.iinfo(np.int64).max:  # as int64 it would wrap
            i = int(np.argmax(np.asarray(pc.greater(c, pa.scalar(np.iinfo(np.int64).max, c.type)))))
            raise IngestError(f"{_where(file_of, i)}: column {col!r}: step {c[i].as_py()} is outside "
                              f"[{base}, {base + np.iinfo(np.int32).max}] (steps are stored as int32 from 0)")
    v = _np(table, col, np.float64 if not pa.types.is_integer(c.type) else np.int64, file_of)
    if v.dtype.kind == "f":
        bad = np.flatnonzero(~np.isfinite(v) | (v != np.round(v)))
        if len(bad):
            raise IngestError(f"{_where(file_of, int(bad[0]))}: column {col!r}: step {float(v[bad[0]])!r} is not a "
                              "whole number")
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
        raise IngestError(f"{file_of(np.array([0]))}: column {col!r}: times do not fit int64 "
                          f"nanoseconds ({exc})") from None
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


def check_command_column(table: pa.Table, column: str, file_of: Callable[[np.ndarray], str]) -> None:
    """A command column must hold numbers a float64 keeps exactly: not booleans (a flag is not
    a command), not integers beyond 2^53 (they would be rounded, and commands are kept as
    logged); the error names the file, the row and the column."""
    col = table.column(column)
    t = col.type.value_type if _is_list(col.type) else col.type
    if pa.types.is_boolean(t):
        raise IngestError(f"{file_of(np.array([0]))}: column {column!r} holds booleans: a command is numeric (map "
                          "a flag with action.type = 'discrete')")
    if pa.types.is_integer(t) and table.num_rows:
        whole = col.combine_chunks()
        flat = whole if pa.types.is_integer(whole.type) else pc.list_flatten(whole)
        v = flat.fill_null(0).to_numpy(zero_copy_only=False)  # compared as integers: 2^53 + 1 rounds to 2^53
        big = np.flatnonzero((v > 2**53) | (v < -(2**53)) if v.dtype.kind == "i" else v > 2**53)
        if len(big):
            row = int(big[0])
            if flat is not whole:  # a list column: the row holding that value
                ends = np.cumsum(pc.list_value_length(whole).fill_null(0).to_numpy(zero_copy_only=False))
                row = int(np.searchsorted(ends, row, side="right"))
            rows = getattr(file_of, "rows", None)
            at = f" row {int(rows[row])}" if rows is not None else ""
            raise IngestError(f"{file_of(np.array([row]))}:{at} column {column!r}: integer command beyond 2^53 (a "
                              "float64 would round it, and commands are kept exactly as logged); rescale the column")


def _commands(table: pa.Table, spec: ActionSpec, list_col: bool, file_of: Callable[[np.ndarray], str]
              ) -> tuple[np.ndarray, np.ndarray | None, tuple[str, ...]]:
    """The continuous command of every row, ``(n, k)`` float64 (missing values NaN: the
    doctor reports them), each row's list length (None when not a list column; -1 where the
    list is missing; a row of another width than ``k`` gets a NaN command), and the component names.

    Several columns: one component each. A list column: the width is the number of
    component names when the spec gives them, else the most common list length; a row
    whose list has another length is flagged, never cut or padded."""
    n = table.num_rows
    for col in (spec.source_columns if not list_col else [spec.column]):
        check_command_column(table, col, file_of)
    if not list_col:
        x = (
            np.column_stack([_np(table, c, np.float64, file_of) for c in spec.source_columns])
            if n
            else np.zeros((0, len(spec.source_columns)))
        )
        return x, None, spec.component_names(x.shape[1])
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
        seen = lengths >= 0
        if seen.any() and not (lengths[seen] == k).any():  # no row can have a command: say why
            i = int(np.argmax(seen))
            widths = sorted({int(m) for m in np.unique(lengths[seen])})
            raise IngestError(f"{_where(file_of, i)}: column {spec.column!r}: [command_width] lists of "
                              f"{' or '.join(map(str, widths))} values against {k} names {list(spec.components)} "
                              f"(action.names): no row has a command of {k} components; give one name per list entry")
    else:
        seen = lengths[lengths > 0]
        if not len(seen):
            raise IngestError(f"{file_of(np.array([0]))}: column {spec.column!r}: every command list is "
                              "empty or missing")
        k = int(np.argmax(np.bincount(seen)))
    good = lengths == k  # a missing list (null) is a missing command: NaN; another length is flagged
    offsets = np.cumsum(np.r_[0, np.maximum(lengths, 0)])[:-1]  # into the flattened (non-null) values
    x = np.full((n, k), np.nan)
    rows = np.flatnonzero(good)
    x[rows] = flat[offsets[rows, None] + np.arange(k)]
    return x, lengths, spec.component_names(k, list_column=True)


def _width_findings(lengths: np.ndarray | None, spec: ActionSpec,
                    atable: Any) -> list[tuple[str, np.ndarray, str, Any]]:
    """The doctor's findings for command lists of the wrong width (``validate(extra=...)``):
    ``lengths`` is each row's list length (-1: not a list, or missing; None: no list column)."""
    if lengths is None:
        return []
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
                    pa.concat_tables([pa.table({f.name: pa.array([], a_type)}),
                                      pa.table({f.name: pa.array([], f.type)})],
                                     promote_options="permissive")
                except (pa.ArrowInvalid, pa.ArrowTypeError, pa.ArrowNotImplementedError):
                    return (f"column {f.name!r} is {a_type} in {a_path} but {f.type} in {m['path']}; "
                            "give the column one type in every file")
            first.setdefault(f.name, (f.type, m["path"]))
    return None
