"""The canonical form of a dataset's table (used by :class:`~offline_adp.data.dataset.TransitionDataset`
on construction): the required columns checked, every format column cast to its type, the
columns in the format's order and the rows sorted by ``(episode_id, step)``, with the
episode-id encoding when the rows were already in order.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from offline_adp.data import schema as S
from offline_adp.data.columns import sorted_encoding
from offline_adp.data.info import DatasetInfo
from offline_adp.errors import SchemaError

_CASTS: dict[str, pa.DataType] = {
    S.EPISODE_ID: pa.string(),
    S.STEP: pa.int32(),
    S.T_NS: pa.int64(),
    S.ACTION: pa.int32(),
    S.COST: pa.float64(),
    S.TERMINATED: pa.bool_(),
    S.TRUNCATED: pa.bool_(),
    S.SOURCE: pa.dictionary(pa.int32(), pa.string()),
    S.BEHAVIOR_PROB: pa.float64(),
}


def _canonical(table: pa.Table, info: DatasetInfo, sorted_ids: pa.DictionaryArray | None = None
               ) -> tuple[pa.Table, pa.DictionaryArray | None, bool]:
    """Check required columns, cast to canonical types and sort by (episode_id, step).

    Returns the table, the episode-id encoding when it is already valid for the returned
    table (rows were in order), and whether the rows were in order. ``sorted_ids`` (for a
    caller that has already sorted the rows, e.g. the Parquet ingestion) is that encoding,
    computed by :func:`~offline_adp.data.columns.sorted_encoding` or after a sort: the
    order is then not checked a second time.
    """
    names = table.column_names
    feature_cols = [S.obs_column(f) for f in info.feature_names] + [S.next_obs_column(f) for f in info.feature_names]
    missing = [c for c in (*S.REQUIRED_COLUMNS, *feature_cols) if c not in names]
    if missing:
        raise SchemaError(
            f"table is missing required columns {missing}; it has {names}. "
            "See docs/dataset-format.md for the columns a dataset needs."
        )
    casts = dict(_CASTS)
    casts.update({c: pa.float64() for c in feature_cols})
    cols = []
    for name in names:
        col = table.column(name)
        target = casts.get(name)
        if target is not None and col.type != target:
            try:
                if name == S.EPISODE_ID and pa.types.is_dictionary(col.type):
                    col = col.cast(col.type.value_type)
                col = col.cast(target)
            except (pa.ArrowInvalid, pa.ArrowNotImplementedError, pa.ArrowTypeError) as exc:
                raise SchemaError(f"column {name!r}: cannot cast {col.type} to {target}: {exc}") from exc
        cols.append(col)
    order = [n for n in _column_order(info) if n in names] + [n for n in names if n not in _column_order(info)]
    table = pa.table(dict(zip(names, cols, strict=True))).select(order)
    ids = table.column(S.EPISODE_ID)
    if ids.null_count:  # a row without an episode cannot be placed in one (or sorted)
        i = int(np.flatnonzero(np.asarray(pc.is_null(ids)))[0])
        raise SchemaError(f"row {i}: episode_id is missing (null) in {ids.null_count} rows; every row needs "
                          "an episode id")
    if not table.num_rows:
        return table, None, True
    if sorted_ids is not None and len(sorted_ids) == table.num_rows:
        return table, sorted_ids, True
    enc = _sorted_encoding(table)
    if enc is None:
        idx = pc.sort_indices(table, sort_keys=[(S.EPISODE_ID, "ascending"), (S.STEP, "ascending")])
        return table.take(idx), None, False
    return table, enc, True


def _column_order(info: DatasetInfo) -> list[str]:
    commands = info.action_table.command_columns if info.action_table.continuous else []
    return [
        S.EPISODE_ID,
        S.STEP,
        S.T_NS,
        *[S.obs_column(f) for f in info.feature_names],
        S.ACTION,
        *commands,
        S.COST,
        *[S.next_obs_column(f) for f in info.feature_names],
        S.TERMINATED,
        S.TRUNCATED,
        S.SOURCE,
        S.BEHAVIOR_PROB,
    ]






def _sorted_encoding(table: pa.Table) -> pa.DictionaryArray | None:
    return sorted_encoding(table.column(S.EPISODE_ID), table.column(S.STEP).to_numpy())
