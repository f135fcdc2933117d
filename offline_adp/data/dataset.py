"""TransitionDataset: an Arrow table of transitions plus its metadata.

One row per transition ``(x_t, a_t, c_t, x_{t+1})``, sorted by ``(episode_id, step)``.
All array access is columnar (numpy views or single conversions); nothing loops over
rows in Python.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from os import PathLike
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc

from offline_adp.data import schema as S
from offline_adp.data.canonical import _canonical, _column_order
from offline_adp.data.columns import _FEW_LABELS, encode_strings, episode_sums, hash_column
from offline_adp.data.info import DatasetInfo
from offline_adp.data.io import read_dataset_table, write_dataset
from offline_adp.errors import InvalidArgumentError, SchemaError


@dataclass(frozen=True)
class TransitionArrays:
    """The dataset as numpy arrays, ready for vectorised algorithms.

    Attributes
    ----------
    obs, next_obs : ndarray, shape (n, d)
        Observation features in ``info.features`` order.
    action : ndarray of int32, shape (n,)
        Index into the action table.
    cost : ndarray of float64, shape (n,)
    terminated, truncated : ndarray of bool, shape (n,)
    step : ndarray of int32, shape (n,)
    episode : ndarray of int64, shape (n,)
        Index into ``TransitionDataset.episode_ids``.
    behavior_prob : ndarray of float64 or None
        Logged propensity of the logged action (NaN where null), if the column exists.
    """

    obs: np.ndarray
    action: np.ndarray
    cost: np.ndarray
    next_obs: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    step: np.ndarray
    episode: np.ndarray
    behavior_prob: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.cost.shape[0])

    @property
    def episode_starts(self) -> np.ndarray:
        """Row index of the first transition of each episode."""
        return np.flatnonzero(np.r_[True, self.episode[1:] != self.episode[:-1]]) if len(self) else np.zeros(0, int)


class TransitionDataset:
    """Logged transitions with their metadata (the *trace data* access model).

    Parameters
    ----------
    table : pyarrow.Table
        Columns of the dataset format (``docs/dataset-format.md``). Columns are cast to
        their canonical types and rows sorted by ``(episode_id, step)``. Extra columns
        (e.g. provenance such as ``src_file``) are kept unchanged.
    info : DatasetInfo
        Features, action table, hints and provenance.

    Raises
    ------
    SchemaError
        If a required column is missing or cannot be cast to its type.
    """

    def __init__(self, table: pa.Table, info: DatasetInfo, *, _sorted_ids: pa.DictionaryArray | None = None) -> None:
        self.info = info
        self.table, enc, self.was_sorted = _canonical(table, info, _sorted_ids)
        self._codes: np.ndarray | None = None
        self._codes64: np.ndarray | None = None
        self._episode_ids: np.ndarray | None = None
        if enc is not None:  # the sortedness check already encoded the ids in order
            self._set_codes(enc)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_pandas(cls, df: pd.DataFrame, info: DatasetInfo) -> TransitionDataset:
        """Build from a DataFrame with the format's column names."""
        return cls(pa.Table.from_pandas(df, preserve_index=False), info)

    @classmethod
    def from_arrays(
        cls,
        info: DatasetInfo,
        *,
        episode_id: Sequence[str] | np.ndarray,
        step: np.ndarray,
        obs: np.ndarray,
        action: np.ndarray,
        cost: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        source: Sequence[str] | np.ndarray | str = "unknown",
        behavior_prob: np.ndarray | None = None,
        t_ns: np.ndarray | None = None,
        extra: dict[str, Any] | None = None,
    ) -> TransitionDataset:
        """Build from numpy arrays (obs and next_obs of shape (n, d) in feature order);
        ``extra`` columns (e.g. provenance such as ``src_file``) are kept as they are."""
        n = len(cost)
        obs = np.asarray(obs, dtype=np.float64).reshape(n, -1)
        next_obs = np.asarray(next_obs, dtype=np.float64).reshape(n, -1)
        cols: dict[str, Any] = {S.EPISODE_ID: pa.array(np.asarray(episode_id).astype(str), pa.string())}
        cols[S.STEP] = np.asarray(step, dtype=np.int32)
        if t_ns is not None:
            cols[S.T_NS] = np.asarray(t_ns, dtype=np.int64)
        for j, name in enumerate(info.feature_names):
            cols[S.obs_column(name)] = obs[:, j]
        cols[S.ACTION] = np.asarray(action, dtype=np.int32)
        cols[S.COST] = np.asarray(cost, dtype=np.float64)
        for j, name in enumerate(info.feature_names):
            cols[S.next_obs_column(name)] = next_obs[:, j]
        cols[S.TERMINATED] = np.asarray(terminated, dtype=bool)
        cols[S.TRUNCATED] = np.asarray(truncated, dtype=bool)
        if isinstance(source, str):
            src = pa.DictionaryArray.from_arrays(pa.array(np.zeros(n, np.int32)), pa.array([source]))
        else:
            src = pc.dictionary_encode(pa.array(np.asarray(source).astype(str), pa.string()))
        cols[S.SOURCE] = src
        if behavior_prob is not None:
            cols[S.BEHAVIOR_PROB] = np.asarray(behavior_prob, dtype=np.float64)
        cols.update(extra or {})
        return cls(pa.table(cols), info)

    @classmethod
    def load(cls, path: str | PathLike[str]) -> TransitionDataset:
        """Read a dataset directory (see :func:`read_dataset`)."""
        return read_dataset(path)

    def save(self, path: str | PathLike[str], *, overwrite: bool = False, **kwargs: Any) -> None:
        """Write atomically to a dataset directory (see :func:`offline_adp.data.io.write_dataset`)."""
        write_dataset(self, path, overwrite=overwrite, **kwargs)

    @classmethod
    def concat(cls, datasets: Sequence[TransitionDataset]) -> TransitionDataset:
        """Concatenate datasets with the same features and action table.

        Episode ids must be disjoint (otherwise two episodes would merge); provenance of
        the parts is kept under ``provenance["parts"]``.
        """
        if not datasets:
            raise SchemaError("concat needs at least one dataset")
        first = datasets[0].info
        for k, d in enumerate(datasets[1:], start=1):
            if d.info.feature_names != first.feature_names:
                raise SchemaError(
                    f"concat: dataset {k} has features {d.info.feature_names}, dataset 0 has {first.feature_names}"
                )
            if d.info.action_table != first.action_table:
                raise SchemaError(f"concat: dataset {k} has a different action table than dataset 0")
        ids = np.concatenate([d.episode_ids for d in datasets])
        uniq, counts = np.unique(ids, return_counts=True)
        if (counts > 1).any():
            raise SchemaError(
                f"concat: episode ids occur in more than one dataset, e.g. {uniq[counts > 1][:5].tolist()}; "
                "prefix them per dataset before concatenating"
            )
        tables = [d.table for d in datasets]
        table = pa.concat_tables(tables, promote_options="permissive")
        prop = {d.info.propensity_source for d in datasets}
        info = first.replace(
            provenance={"parts": [dict(d.info.provenance) for d in datasets]},
            propensity_source=prop.pop() if len(prop) == 1 else "unknown",
        )
        return cls(table, info)

    # ------------------------------------------------------------------ basic properties
    def __len__(self) -> int:
        return self.table.num_rows

    def __repr__(self) -> str:
        return (
            f"TransitionDataset({len(self)} transitions, {self.n_episodes} episodes, "
            f"features={self.info.feature_names}, n_actions={self.n_actions})"
        )

    @property
    def feature_names(self) -> list[str]:
        return self.info.feature_names

    @property
    def obs_columns(self) -> list[str]:
        return [S.obs_column(n) for n in self.info.feature_names]

    @property
    def next_obs_columns(self) -> list[str]:
        return [S.next_obs_column(n) for n in self.info.feature_names]

    @property
    def n_actions(self) -> int:
        return self.info.n_actions

    @property
    def has_propensities(self) -> bool:
        return S.BEHAVIOR_PROB in self.table.column_names

    def _set_codes(self, enc: pa.DictionaryArray) -> None:
        # the encoding's own indices (int32, a read-only view): widened only if episode_index is read
        self._codes = enc.indices.to_numpy(zero_copy_only=False)
        self._codes64 = None
        self._episode_ids = np.asarray(enc.dictionary.to_pylist(), dtype=object)

    def _episode_codes(self) -> tuple[np.ndarray, np.ndarray]:
        if self._codes is None:
            self._set_codes(encode_strings(self.table.column(S.EPISODE_ID)))
        assert self._codes is not None and self._episode_ids is not None
        return self._codes, self._episode_ids

    @property
    def episode_ids(self) -> np.ndarray:
        """Episode ids in dataset (sorted) order."""
        return self._episode_codes()[1]

    @property
    def n_episodes(self) -> int:
        return len(self.episode_ids)

    @property
    def episode_index(self) -> np.ndarray:
        """Per row, the index of its episode in :attr:`episode_ids` (int64)."""
        if self._codes64 is None:
            self._codes64 = self._episode_codes()[0].astype(np.int64)
        return self._codes64

    @property
    def episode_codes(self) -> np.ndarray:
        """:attr:`episode_index` in its encoding's integer type (int32 as a rule), read-only:
        no int64 copy of the column (16 MB at 2M rows) for readers that only index with it."""
        return self._episode_codes()[0]

    def column(self, name: str) -> np.ndarray:
        """One column as a numpy array (strings/dictionaries as object arrays)."""
        if name not in self.table.column_names:
            raise SchemaError(f"no column {name!r}; columns are {self.table.column_names}")
        col = self.table.column(name)
        if pa.types.is_dictionary(col.type):
            col = col.cast(col.type.value_type)
        return col.to_numpy()

    def _matrix(self, columns: list[str], dtype: np.dtype | type) -> np.ndarray:
        out = np.empty((len(self), len(columns)), dtype=dtype)
        for j, c in enumerate(columns):
            out[:, j] = self.table.column(c).to_numpy()
        return out

    def arrays(self, dtype: np.dtype | type = np.float64) -> TransitionArrays:
        """Columns as numpy arrays (obs/next_obs as 2-D ``dtype``), no per-row Python."""
        t = self.table
        return TransitionArrays(
            obs=self._matrix(self.obs_columns, dtype),
            action=t.column(S.ACTION).to_numpy().astype(np.int32, copy=False),
            cost=t.column(S.COST).to_numpy().astype(np.float64, copy=False),
            next_obs=self._matrix(self.next_obs_columns, dtype),
            terminated=t.column(S.TERMINATED).to_numpy(),
            truncated=t.column(S.TRUNCATED).to_numpy(),
            step=t.column(S.STEP).to_numpy(),
            episode=self.episode_index,
            behavior_prob=(
                t.column(S.BEHAVIOR_PROB).to_numpy(zero_copy_only=False).astype(np.float64)
                if self.has_propensities
                else None
            ),
        )

    def commands(self) -> np.ndarray | None:
        """The exact command of every row, ``(n, n_dims)`` float64, from the
        ``action_value.<dim>`` columns; ``None`` when the dataset does not carry them all."""
        cols = self.info.action_table.command_columns
        if not all(c in self.table.column_names for c in cols):
            return None
        return self._matrix(cols, np.float64)

    def to_pandas(self) -> pd.DataFrame:
        """The table as a DataFrame (``source`` as a categorical)."""
        return self.table.to_pandas()

    # ------------------------------------------------------------------ selections
    def take(self, rows: np.ndarray) -> TransitionDataset:
        """Rows by index (or boolean mask), keeping metadata."""
        rows = np.asarray(rows)
        if rows.dtype == bool:
            return TransitionDataset(self.table.filter(pa.array(rows)), self.info)
        return TransitionDataset(self.table.take(pa.array(rows)), self.info)

    def select_episodes(self, episodes: Iterable[str] | np.ndarray) -> TransitionDataset:
        """Keep the episodes whose ids are given (or whose boolean mask over
        :attr:`episode_ids` is true)."""
        ep = np.asarray(list(episodes) if not isinstance(episodes, np.ndarray) else episodes)
        if ep.dtype == bool:
            keep_codes = ep
        else:
            keep_codes = np.isin(self.episode_ids, ep.astype(object))
        return self.take(keep_codes[self.episode_index])

    def episodes(self) -> Iterator[tuple[str, TransitionDataset]]:
        """Yield ``(episode_id, dataset_of_that_episode)`` in order (zero-copy slices)."""
        codes, ids = self._episode_codes()
        bounds = np.r_[np.flatnonzero(np.r_[True, codes[1:] != codes[:-1]]), len(codes)] if len(codes) else [0]
        for k in range(len(bounds) - 1):
            lo, hi = int(bounds[k]), int(bounds[k + 1])
            yield str(ids[codes[lo]]), TransitionDataset(self.table.slice(lo, hi - lo), self.info)

    def split(self, valid_fraction: float = 0.2, seed: int = 0) -> tuple[TransitionDataset, TransitionDataset]:
        """Split by episode into (train, validation), seeded and reproducible."""
        if not 0.0 < valid_fraction < 1.0:
            raise InvalidArgumentError(f"valid_fraction must be in (0, 1), got {valid_fraction}")
        n = self.n_episodes
        n_valid = int(round(valid_fraction * n))
        if n_valid == 0 or n_valid == n:
            raise InvalidArgumentError(f"cannot split {n} episodes with valid_fraction={valid_fraction}")
        perm = np.random.default_rng(seed).permutation(n)
        valid = np.zeros(n, bool)
        valid[perm[:n_valid]] = True
        return self.select_episodes(~valid), self.select_episodes(valid)

    def filter_source(self, *sources: str) -> TransitionDataset:
        """Keep rows whose ``source`` is one of ``sources``."""
        col = self.table.column(S.SOURCE).cast(pa.string())
        mask = pc.is_in(col, value_set=pa.array(list(sources), pa.string()))
        return TransitionDataset(self.table.filter(mask), self.info)

    def states_at(self, t: int) -> np.ndarray:
        """Observations at step ``t`` of every episode that reaches it, shape (m, d)."""
        mask = pc.equal(self.table.column(S.STEP), pa.scalar(t, pa.int32()))
        sub = self.table.filter(mask)
        return np.column_stack([sub.column(c).to_numpy() for c in self.obs_columns]) if sub.num_rows else np.zeros(
            (0, len(self.obs_columns))
        )

    def source_counts(self) -> dict[str, int]:
        """Number of transitions per ``source`` label."""
        col = self.table.column(S.SOURCE)
        if pa.types.is_dictionary(col.type) and len(col) and not col.null_count:  # count codes, not strings
            col = col.unify_dictionaries()
            words = col.chunk(0).dictionary.cast(pa.string())
            counts: dict[str, int] = {}
            for code, count in _code_counts([c.indices for c in col.chunks], len(words)):
                word = str(words[code].as_py())
                counts[word] = counts.get(word, 0) + int(count)  # a dictionary may repeat a word
            return counts
        vc = pc.value_counts(col.cast(pa.string()))
        return {str(v["values"]): int(v["counts"]) for v in vc.to_pylist()}

    # ------------------------------------------------------------------ summaries
    def episode_table(self) -> pd.DataFrame:
        """One row per episode: id, length, source, return (total cost), end flags, first row."""
        a_codes, ids = self._episode_codes()
        n_ep = len(ids)
        starts = np.r_[0, np.flatnonzero(a_codes[1:] != a_codes[:-1]) + 1] if len(self) else np.zeros(0, int)
        lengths = np.diff(np.r_[starts, len(self)])
        last = starts + lengths - 1
        cost = self.table.column(S.COST).to_numpy()
        total = episode_sums(a_codes, starts, cost, n_ep) if len(self) else np.zeros(0)
        src_col = self.table.column(S.SOURCE)
        source = src_col.take(pa.array(starts)).cast(pa.string()).to_numpy(zero_copy_only=False) if len(self) else None
        df = pd.DataFrame(
            {
                S.EPISODE_ID: ids.astype(str),
                "length": lengths.astype(np.int64),
                S.SOURCE: source if len(self) else np.array([], dtype=object),
                "total_cost": total,
                S.TERMINATED: _values_at(self.table.column(S.TERMINATED), last) if len(self) else np.zeros(0, bool),
                S.TRUNCATED: _values_at(self.table.column(S.TRUNCATED), last) if len(self) else np.zeros(0, bool),
                "first_row": starts.astype(np.int64),
            }
        )
        if S.T_NS in self.table.column_names and len(self):
            df["t_start_ns"] = self.table.column(S.T_NS).to_numpy()[starts]
        return df

    def fingerprint(self) -> str:
        """sha256 of the content (columns and metadata that define the data), hex.

        Depends on the values only: independent of chunking, of Arrow buffer layout and of
        provenance (extra columns such as ``src_file`` and the ``provenance`` metadata are
        left out): two datasets with the same rows, features and action table have the same
        fingerprint. Each column is hashed canonically
        (:func:`~offline_adp.data.columns.hash_column`): its name, its null mask, and its
        values with nulls zeroed (integers exactly, never through float: as int32 when
        their type holds only int32 values, else int64; floats with every NaN one NaN and
        -0.0 as 0.0; booleans as bytes; strings as their distinct values, length-prefixed
        UTF-8, and int32 codes in first-appearance order).

        This is definition v3 (2026-11-26); :meth:`matches_fingerprint` also recognises
        the fingerprints written under the earlier definitions.
        """
        return self._fingerprint(3)

    def _fingerprint(self, version: int) -> str:
        """Fingerprint definition v3 (int32 codes and narrow integers) or v2 (2026-11-25
        to 2026-11-26: codes and every integer as int64); the same bytes otherwise."""
        h = hashlib.sha256()
        h.update(f"offline_adp fingerprint v{version}\x00".encode())
        h.update(repr((self.info.feature_names, self.info.action_table.to_dict())).encode())
        known = set(_column_order(self.info))
        for name in sorted(c for c in self.table.column_names if c in known):
            enc = self._episode_codes() if name == S.EPISODE_ID and len(self) else None
            hash_column(h, name, self.table.column(name), enc, narrow=version >= 3)
        return h.hexdigest()

    def matches_fingerprint(self, stored: Any) -> bool:
        """Whether a stored fingerprint is this data's: the current one (v3), or, for what
        was written under an earlier definition, v2 (2026-11-25 to 2026-11-26) or
        :meth:`legacy_fingerprint` (before 2026-11-25), so existing datasets and runs stay
        valid. The older definitions are computed only when the current one differs."""
        if not isinstance(stored, str):
            return False
        return stored == self.fingerprint() or stored == self._fingerprint(2) or stored == self.legacy_fingerprint()

    def legacy_fingerprint(self) -> str:
        """The fingerprint as defined until 2026-11-25 (integers hashed as stored, strings
        joined), kept only to recognise fingerprints stored then (:meth:`matches_fingerprint`)."""
        h = hashlib.sha256()
        h.update(repr((self.info.feature_names, self.info.action_table.to_dict())).encode())
        known = set(_column_order(self.info))
        for name in sorted(c for c in self.table.column_names if c in known):
            col = self.table.column(name)
            h.update(name.encode())
            if name == S.EPISODE_ID:
                codes, ids = self._episode_codes()
                h.update(codes.astype(np.int64).tobytes())  # as int64 in this definition
                h.update("\x00".join(map(str, ids)).encode())
            elif pa.types.is_dictionary(col.type) or pa.types.is_string(col.type) or pa.types.is_large_string(col.type):
                if pa.types.is_dictionary(col.type):
                    col = col.cast(col.type.value_type)
                enc = encode_strings(col)
                h.update(enc.indices.to_numpy(zero_copy_only=False).astype(np.int64).tobytes())
                h.update("\x00".join(map(str, enc.dictionary.to_pylist())).encode())
            else:
                arr = col.to_numpy()
                if arr.dtype.kind == "f":
                    arr = arr + 0.0
                if col.null_count:
                    h.update(np.asarray(pc.is_null(col)).tobytes())
                h.update(np.ascontiguousarray(arr).tobytes())
        return h.hexdigest()


def read_dataset(path: str | PathLike[str]) -> TransitionDataset:
    """Read a dataset directory written by :func:`~offline_adp.data.io.write_dataset`
    (``TransitionDataset.save``).

    Raises
    ------
    DatasetNotFoundError
        If ``path`` has no ``meta/info.json``.
    SchemaError
        If metadata or columns do not match the format.
    """
    table, info = read_dataset_table(path)
    try:
        return TransitionDataset(table, info)
    except SchemaError as exc:
        raise SchemaError(f"{path}: {exc}") from None


def _values_at(col: pa.ChunkedArray, rows: np.ndarray) -> np.ndarray:
    """``col.to_numpy()[rows]``, converting only those rows when the column has no nulls
    (with nulls, the whole column's object array as before)."""
    return col.to_numpy()[rows] if col.null_count else col.take(pa.array(rows)).to_numpy()


def _code_counts(indices: list[pa.Array], n_codes: int) -> list[tuple[int, int]]:
    """``(code, count)`` of the codes used, in order of first appearance (as Arrow's
    ``value_counts``); a few codes (the source labels) by one comparison each, no hash table."""
    if n_codes > _FEW_LABELS:
        vc = pc.value_counts(pa.chunked_array(indices))
        return list(zip(vc.field("values").to_pylist(), vc.field("counts").to_pylist(), strict=True))
    seen: list[tuple[int, int, int]] = []  # (first row, code, count)
    for code in range(n_codes):
        count, first, at = 0, -1, 0
        for ind in indices:
            hit = ind.to_numpy(zero_copy_only=False) == code
            k = int(np.count_nonzero(hit))
            if k and first < 0:
                first = at + int(np.argmax(hit))
            count, at = count + k, at + len(ind)
        if count:
            seen.append((first, code, count))
    return [(code, count) for _, code, count in sorted(seen)]
