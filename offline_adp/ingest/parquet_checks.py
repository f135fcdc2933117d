"""Checks of a Parquet/CSV ingestion's columns (:mod:`offline_adp.ingest.parquet`) that refuse,
flag or warn about what the dataset would otherwise store wrongly without a word: null
action labels (never the label ``"None"``), JSON text where a command is expected, a
command read as one label per row.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from offline_adp.errors import IngestError, InvalidArgumentError, LogWarning
from offline_adp.ingest.parquet_columns import _where
from offline_adp.ingest.spec import ActionSpec


def action_labels(table: pa.Table, column: str,
                  file_of: Callable[[np.ndarray], str]) -> tuple[np.ndarray, np.ndarray | None]:
    """A discrete action column's labels and its null mask (None without nulls). A null
    label is never a label ("None"): it is given the value of another row for the mapping
    (so the action table holds only logged labels) and the caller makes its action null.

    Parameters
    ----------
    table : pyarrow.Table
    column : str
        The discrete action column.
    file_of : callable
        Row indices -> the file they came from (for the error).

    Returns
    -------
    (ndarray, ndarray or None)
        The labels, and the mask of null labels.

    Raises
    ------
    IngestError
        When every label is null.
    """
    c = table.column(column)
    raw = c.to_numpy(zero_copy_only=False)
    if not c.null_count:
        return raw, None
    null = np.asarray(pc.is_null(c))
    if null.all():
        raise IngestError(f"{file_of(np.array([0]))}: column {column!r}: every action label is missing (null)")
    raw = raw.copy()
    raw[null] = raw[int(np.argmin(null))]
    return raw, null


def _is_text(t: pa.DataType) -> bool:
    if pa.types.is_dictionary(t):
        t = t.value_type
    return pa.types.is_string(t) or pa.types.is_large_string(t)


def check_json_commands(table: pa.Table, spec: ActionSpec, file_of: Callable[[np.ndarray], str]) -> None:
    """Refuse an action column of text whose every value looks like JSON (an array or an
    object: ``[`` or ``{`` first): commands stored as JSON strings would otherwise become one
    discrete label per row. The error names the file, row and column.

    Parameters
    ----------
    table : pyarrow.Table
    spec : ActionSpec
        The spec's action table (its source columns, its declared ``values``).
    file_of : callable
        Row indices -> the file they came from.

    Raises
    ------
    IngestError
        Naming the file, row and column of the first JSON value.
    """
    for col in spec.source_columns:
        c = table.column(col)
        if not _is_text(c.type) or c.null_count == len(c):
            continue
        if spec.values is not None and any(isinstance(v, str) and v.lstrip()[:1] in ("[", "{") for v in spec.values):
            continue  # the spec names such labels itself
        if pa.types.is_dictionary(c.type):
            c = c.cast(c.type.value_type)
        head = pc.utf8_slice_codeunits(pc.utf8_ltrim_whitespace(c), 0, 1)
        if not pc.all(pc.is_in(head, pa.array(["[", "{"]))).as_py():
            continue
        i = int(np.argmax(np.asarray(pc.is_valid(c))))
        v = str(c[i].as_py())
        v = repr(v[:60]) + ("..." if len(v) > 60 else "")
        raise IngestError(f"{_where(file_of, i)}: column {col!r} holds JSON text ({v}): JSON commands are not "
                          "supported; give the components as separate numeric columns "
                          "(action.columns = [...], type = 'continuous') or store the command as a list column "
                          "(e.g. Parquet list<double>)")


#: A discrete action column read by default (no ``action.type``) with more distinct float
#: values than this, and more than half as many as rows, is probably a continuous command.
MANY_LABELS = 64
#: A discrete action column with a distinct label in every row and more labels than this is
#: probably a continuous command, whatever its type and whether ``type`` was declared.
ONE_PER_ROW_LABELS = 256


def warn_many_labels(raw: np.ndarray, n_labels: int, aspec: Any, where: str) -> None:
    """Warn (:class:`~offline_adp.errors.LogWarning`) when the discrete reading turned a column
    into about one action per row (a continuous command ingested as labels: nothing is
    dropped, but nothing is learnt): a float column read by default with more than
    :data:`MANY_LABELS` values in more than half of the rows, or any column with a distinct
    label in every row and more than :data:`ONE_PER_ROW_LABELS` of them.

    Parameters
    ----------
    raw : ndarray
        The column's values, one per row.
    n_labels : int
        The distinct labels the discrete reading made.
    aspec : ActionSpec
    where : str
        The input files, for the warning.
    """
    if n_labels > ONE_PER_ROW_LABELS and n_labels >= len(raw):
        warnings.warn(f"{where}: action column {aspec.column!r} was read as discrete labels and holds "
                      f"{n_labels} distinct labels in {len(raw)} rows (one per row): this looks like a continuous "
                      "command read as labels; if it is one, give it as numbers with action.type = 'continuous'",
                      LogWarning, stacklevel=3)
        return
    if aspec.type_declared or raw.dtype.kind != "f" or n_labels <= MANY_LABELS or n_labels <= len(raw) / 2:
        return
    warnings.warn(f"{where}: action column {aspec.column!r} was read as discrete labels (the default without "
                  f"action.type) and holds {n_labels} distinct values in {len(raw)} rows; if it is a continuous "
                  "command, set action.type = 'continuous' in the spec", LogWarning, stacklevel=3)


def check_order_column(table: pa.Table, col: str, files: np.ndarray) -> None:
    """Refuse a missing (null) or NaN value in the column that orders the rows of an episode
    (``episode.order``), as a null step is refused: the row's place in its episode is
    unknown. ``table`` is in file order with its ``__file``/``__row`` columns; the error
    names the file, row and column of the first such value.

    Parameters
    ----------
    table : pyarrow.Table
    col : str
        The order column.
    files : ndarray
        The input files, indexed by ``__file``.

    Raises
    ------
    IngestError
        Naming the file, row and column, and how many rows lack a value.
    """
    c = table.column(col)
    bad = pc.is_null(c, nan_is_null=True) if pa.types.is_floating(c.type) else pc.is_null(c)
    if not pc.any(bad).as_py():
        return
    mask = np.asarray(bad)
    i = int(np.argmax(mask))
    f = int(table.column("__file")[i].as_py())
    r = int(table.column("__row")[i].as_py())
    what = "NaN" if c[i].is_valid else "missing (null)"
    raise IngestError(f"{files[f]}: row {r}: column {col!r}: the order value is {what} ({int(mask.sum())} such rows); "
                      "every row needs one to place it in its episode")


def input_paths(inputs: Any) -> list[Path]:
    """The input files of an ingestion: one path (str or os.PathLike) or a list of them;
    anything else (None, a number, a list holding a non-path) is an
    :class:`~offline_adp.errors.InvalidArgumentError` naming the argument.

    Parameters
    ----------
    inputs : str, os.PathLike or iterable of them

    Returns
    -------
    list of Path
        Read once (a generator is consumed here).
    """
    if isinstance(inputs, (str, PathLike)):
        return [Path(inputs)]
    if isinstance(inputs, (bytes, dict)) or not hasattr(inputs, "__iter__"):
        raise InvalidArgumentError(f"inputs must be a path (str or os.PathLike) or a list of paths, got "
                                   f"{type(inputs).__name__}")
    paths = list(inputs)
    bad = [p for p in paths if not isinstance(p, (str, PathLike))]
    if bad:
        raise InvalidArgumentError(f"inputs must be paths (str or os.PathLike), got {type(bad[0]).__name__} "
                                   f"{bad[0]!r:.80}")
    return [Path(p) for p in paths]


def source_findings(src: pa.Array, codes: np.ndarray, column: str) -> list[tuple[str, np.ndarray, str, Any]]:
    """The doctor's findings (``validate(extra=...)``, check ``source_changed``) for rows whose
    source label differs from the previous row's of the same episode: an episode has one
    source (``meta/episodes.parquet`` keeps one). ``src`` is the dataset's dictionary-encoded
    source column in row order, ``codes`` each row's episode code (rows sorted by episode).

    Parameters
    ----------
    src : pyarrow.Array or ChunkedArray
    codes : ndarray
    column : str
        The column the findings name.

    Returns
    -------
    list of (str, ndarray, str, ndarray)
        ``(check, row mask, column, message per row)``, empty when every episode keeps one label.
    """
    n = len(src)
    if n < 2:
        return []
    if isinstance(src, pa.ChunkedArray):
        src = src.unify_dictionaries().combine_chunks()
    if len(pc.unique(src.dictionary)) != len(src.dictionary):  # codes comparable only over distinct labels
        src = pc.dictionary_encode(src.cast(pa.string()))
    s = src.indices.fill_null(-1).to_numpy(zero_copy_only=False)
    changed = np.zeros(n, bool)
    np.not_equal(s[1:], s[:-1], out=changed[1:])
    changed[1:] &= (codes[1:] == codes[:-1]) & (s[1:] >= 0) & (s[:-1] >= 0)  # a null is a null_value finding
    if not changed.any():
        return []
    rows = np.flatnonzero(changed)
    labels = src.dictionary.to_pylist()
    msg = np.full(n, "", dtype=object)
    msg[rows] = [f"source {labels[s[i]]!r} after {labels[s[i - 1]]!r} in the same episode; an episode has one source "
                 "(meta/episodes.parquet keeps one): give the episode one label, or split it" for i in rows]
    return [("source_changed", changed, column, msg)]
