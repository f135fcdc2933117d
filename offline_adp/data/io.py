"""Dataset directories on disk: writing them atomically, reading their tables back.

Layout (``docs/dataset-format.md``)::

    DIR/data/part-00000.parquet ...   transitions, LZ4, whole episodes per part
    DIR/meta/info.json                DatasetInfo + counts
    DIR/meta/episodes.parquet         one row per episode
    DIR/meta/stats.json               per-column statistics, counts per source/action
    DIR/quarantine/                   rejected episodes with a reason per row (optional)

This module sits below :mod:`offline_adp.data.dataset`: it writes any object with the
dataset's shape (:class:`DatasetToWrite`) and reads back a table and its
:class:`~offline_adp.data.info.DatasetInfo`;
:func:`offline_adp.data.dataset.read_dataset` (and ``TransitionDataset.load``) builds
the dataset from them. The filesystem primitives it uses (atomic directories, the write
lock) are :mod:`offline_adp.data.files`.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from os import PathLike
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from offline_adp.data import schema as S
from offline_adp.data.files import (
    atomic_directory,
    locked_directory,
    read_json_file,
    write_text_nofollow,
)
from offline_adp.data.info import DatasetInfo, json_numpy
from offline_adp.errors import (
    DatasetNotFoundError,
    FormatVersionWarning,
    OutputExistsError,
    SchemaError,
)

DEFAULT_ROWS_PER_PART = 500_000


class DatasetToWrite(Protocol):
    """What :func:`write_dataset` reads of a dataset (a
    :class:`~offline_adp.data.dataset.TransitionDataset` is one)."""

    table: pa.Table
    info: DatasetInfo

    def __len__(self) -> int: ...
    @property
    def n_episodes(self) -> int: ...
    @property
    def n_actions(self) -> int: ...
    @property
    def obs_columns(self) -> Sequence[str]: ...
    @property
    def next_obs_columns(self) -> Sequence[str]: ...
    def episode_table(self) -> pd.DataFrame: ...
    def fingerprint(self) -> str: ...
    def source_counts(self) -> dict[str, int]: ...


def write_json(path: Path, obj: Any) -> None:
    write_text_nofollow(path, json.dumps(obj, indent=2, default=json_numpy) + "\n")


def dataset_stats(ds: DatasetToWrite) -> dict[str, Any]:
    """Per-column statistics, counts per source and per action (``meta/stats.json``)."""
    stats: dict[str, Any] = {"n_transitions": len(ds), "n_episodes": ds.n_episodes, "columns": {}}
    buf = np.empty(0)
    for c in [*ds.obs_columns, S.COST, *ds.next_obs_columns]:
        x = ds.table.column(c).to_numpy()
        with np.errstate(over="ignore", invalid="ignore"):  # the check below decides
            total = np.add.reduce(x) if len(x) else np.nan
        if np.isfinite(total):  # a NaN or an infinity would make the sum NaN or infinite
            finite = x
        else:
            ok = np.isfinite(x)
            finite = x if ok.all() else x[ok]  # a copy only when something is not finite
            del ok
            total = None
        if not len(finite):
            stats["columns"][c] = {"non_finite": int(len(x))}
            continue
        if len(buf) < min(len(finite), _stats_block()):
            buf = np.empty(min(len(finite), _stats_block()))
        mean, std = _mean_std(finite, buf, total)
        stats["columns"][c] = {
            "mean": mean,
            "std": std,
            "min": float(finite.min()),
            "max": float(finite.max()),
            "non_finite": int(len(x) - len(finite)),
        }
    a = ds.table.column(S.ACTION).to_numpy()
    if ds.n_actions <= 16:  # one vectorised comparison per action: no index copy, no filtered copy
        counts = [np.count_nonzero(a == k) for k in range(ds.n_actions)]
    else:
        counts = np.bincount(a[(a >= 0) & (a < ds.n_actions)], minlength=ds.n_actions)
    stats["action_counts"] = {name: int(n) for name, n in zip(ds.info.action_table.names, counts, strict=True)}
    stats["source_counts"] = ds.source_counts()
    # counted in Arrow (bit-packed): no unpacking to numpy booleans
    term, trunc = ds.table.column(S.TERMINATED), ds.table.column(S.TRUNCATED)
    stats["terminated_episodes"] = _count_true(term)
    stats["truncated_episodes"] = _count_true(trunc)
    stats["terminated_and_truncated"] = _count_true(pc.and_(term, trunc))
    return stats


def _count_true(col: pa.ChunkedArray) -> int:
    """Number of true values (nulls count as false, as numpy's sum over ``to_numpy``)."""
    return int(pc.sum(col).as_py() or 0)


#: values per block of the squared deviations (:func:`_sq_dev_sum`): the block stays in cache
_STATS_BLOCK = 1 << 16
#: numpy's pairwise-summation block (``PW_BLOCKSIZE``): it splits only sums of more values
_NUMPY_PAIRWISE_BLOCK = 128


def _stats_block() -> int:
    """``_STATS_BLOCK``, at least numpy's own block: below it the split here is not numpy's
    (other bits), and below 16 a half rounded down to a multiple of 8 can be 0 (no end)."""
    return max(int(_STATS_BLOCK), _NUMPY_PAIRWISE_BLOCK)


def _mean_std(x: np.ndarray, buf: np.ndarray, total: float | None = None) -> tuple[float, float]:
    """``x.mean()`` and ``x.std()`` of a 1-D contiguous float64 array, bit for bit (numpy's own
    steps: the pairwise sum over n, then the pairwise sum of squared deviations), with the
    deviations block by block in ``buf`` (at least ``min(len(x), _stats_block())`` values,
    reused across columns) instead of a fresh array per call, and one sum for both
    (``total``, ``np.add.reduce(x)``, when the caller has it)."""
    n = len(x)
    mean = (np.add.reduce(x) if total is None else total) / n
    return float(mean), float(np.sqrt(_sq_dev_sum(x, mean, buf) / n))


def _sq_dev_sum(x: np.ndarray, mean: Any, buf: np.ndarray) -> Any:
    """``np.add.reduce((x - mean) ** 2)``, bit for bit: numpy sums a contiguous float64
    array pairwise, each half of ``n`` values split at ``n // 2`` rounded down to a multiple
    of 8; the halves are split the same way here down to blocks of at most
    :func:`_stats_block` values, whose squared deviations are formed in ``buf`` (in cache) and
    summed by numpy itself, and the partial sums added in numpy's order."""
    n = len(x)
    if n <= _stats_block():  # (at least 128: each half below is then at least 64 values)
        d = buf[:n]
        np.subtract(x, mean, out=d)
        np.multiply(d, d, out=d)
        return np.add.reduce(d)
    half = n // 2
    half -= half % 8
    return _sq_dev_sum(x[:half], mean, buf) + _sq_dev_sum(x[half:], mean, buf)


def _is_dir(p: Path) -> bool:
    """Whether ``p`` is a directory; an input it cannot stat counts as one (nothing to refuse
    here: reading it says what is wrong)."""
    try:
        return p.is_dir() or not p.exists()
    except OSError:
        return True


def check_dataset_output(out: str | PathLike[str], inputs: Sequence[str | PathLike[str]] = ()) -> None:
    """Refuse, before anything is written, an ingest's output directory ``out`` that would
    destroy what it reads or another dataset (``--overwrite`` replaces ``out`` as a whole):
    ``out`` equal to an input or containing one; or ``out`` inside an existing dataset
    directory (a directory with ``meta/info.json``: ``--out DS/data`` would replace that
    dataset's data). An output inside an input directory (a rosbag2 bag directory) destroys
    nothing read and is allowed. Paths are compared resolved (links followed).

    Parameters
    ----------
    out : str or os.PathLike
        The dataset directory to be written.
    inputs : sequence of str or os.PathLike
        The files or directories the ingest reads.

    Raises
    ------
    OutputExistsError
        Naming ``out`` and the input or dataset it overlaps.
    """
    target = Path(out).resolve()
    for src in inputs:
        p = Path(src).resolve()
        if p == target:
            raise OutputExistsError(f"the output {out} is the input {src}; write the dataset elsewhere")
        if target in p.parents:
            raise OutputExistsError(f"the output {out} contains the input {src} (writing it would replace the input); "
                                    "write the dataset elsewhere")
        if p in target.parents and not _is_dir(p):
            raise OutputExistsError(f"the output {out} lies inside the input {src}, a file; write the dataset "
                                    "elsewhere")
    parent = enclosing_dataset(target, itself=False)
    if parent is not None:
        raise OutputExistsError(f"the output {out} lies inside the dataset directory {parent}; writing it would "
                                "change that dataset: write the new dataset elsewhere")


def enclosing_dataset(path: str | PathLike[str], *, itself: bool = True) -> Path | None:
    """The dataset directory (one with ``meta/info.json``) that ``path`` is, with
    ``itself``, or lies inside; None when there is none (an unreadable directory on the
    way is not a dataset we can see). Paths are compared resolved."""
    target = Path(path).resolve()
    for d in ((target,) if itself else ()) + tuple(target.parents):
        try:
            if (d / S.INFO_FILE).is_file():
                return d
        except OSError:
            continue
    return None


def write_dataset(
    ds: DatasetToWrite,
    path: str | PathLike[str],
    *,
    overwrite: bool = False,
    rows_per_part: int = DEFAULT_ROWS_PER_PART,
    quarantine: pa.Table | None = None,
    extra_meta: dict[str, Any] | None = None,
) -> Path:
    """Write ``ds`` as a dataset directory at ``path``, atomically.

    Parts hold whole episodes and at most about ``rows_per_part`` rows (written in parallel) (an episode
    longer than that gets a part of its own). ``quarantine`` (rows rejected by the
    doctor, with a ``reason`` column) is written to ``quarantine/``. ``extra_meta`` is
    merged into ``info.json`` (e.g. the doctor's summary).
    """
    path = Path(path)
    ep = ds.episode_table()
    with locked_directory(path, what="dataset"), atomic_directory(path, overwrite=overwrite, clean_stale=True) as tmp:
        (tmp / S.DATA_DIR).mkdir()
        (tmp / S.META_DIR).mkdir()
        dictionary, encoding = _part_encodings(ds.table.schema)
        # column statistics (min/max, for readers that skip parts by value) on the integer
        # columns (steps, times, actions, source rows); the floats' are in meta/stats.json.
        # None on text (ids, labels): nothing here reads them, and they were 8% of the writing
        with_stats = [f.name for f in ds.table.schema if pa.types.is_integer(f.type)]
        table = _required_where_complete(ds.table)

        def write_part(k: int, lo: int, hi: int) -> None:
            write_parquet(
                table.slice(lo, hi - lo),
                tmp / S.DATA_DIR / S.PART_TEMPLATE.format(k),
                compression=_PART_COMPRESSION,
                use_dictionary=dictionary,
                column_encoding=encoding,
                write_statistics=with_stats,
                write_batch_size=_PART_WRITE_BATCH,
            )

        bounds = _part_bounds(ep["first_row"].to_numpy(), len(ds), rows_per_part)
        # Arrow releases the GIL while encoding: parts are written in parallel threads
        # the fingerprint and statistics are computed while the parts are written
        with ThreadPoolExecutor(max_workers=(os.cpu_count() or 1) + 1) as pool:
            for fut in [pool.submit(write_part, k, lo, hi) for k, (lo, hi) in enumerate(bounds)]:
                fut.result()
        # after the parts, one after the other: their temporaries never add up with the writers'
        summary = (ds.fingerprint(), dataset_stats(ds))
        info = ds.info.to_dict()
        info["n_transitions"] = len(ds)
        info["n_episodes"] = ds.n_episodes
        fingerprint, stats = summary
        info["fingerprint"] = fingerprint
        info["columns"] = {f.name: str(f.type) for f in ds.table.schema}
        if extra_meta:
            info.update(extra_meta)
        write_json(tmp / S.INFO_FILE, info)
        write_parquet(pa.Table.from_pandas(ep, preserve_index=False), tmp / S.EPISODES_FILE)
        write_json(tmp / S.STATS_FILE, stats)
        if quarantine is not None and quarantine.num_rows:
            (tmp / S.QUARANTINE_DIR).mkdir()
            write_parquet(quarantine, tmp / S.QUARANTINE_DIR / S.PART_TEMPLATE.format(0),
                          compression=S.PARQUET_COMPRESSION)
    return path


#: bytes gathered before each write to a Parquet file: the writer's many small writes (a
#: page header, then its page; a position query after each) become one system call per MiB.
#: The file's bytes are the same; 0.015 CPU-s less for the 2M-row benchmark's four parts
_WRITE_BUFFER = 1 << 20


def write_parquet(table: pa.Table, path: Path, **options: Any) -> None:
    """``pq.write_table(table, path, **options)``, byte for byte, through a write buffer
    (:data:`_WRITE_BUFFER`)."""
    with pa.OSFile(str(path), "wb") as raw, pa.BufferedOutputStream(raw, _WRITE_BUFFER) as sink:
        pq.write_table(table, sink, **options)


_DICTIONARY_COLUMNS = (S.TERMINATED, S.TRUNCATED)
#: written plain: steps (0, 1, 2, ... per episode) compress as well as their dictionary
#: codes, at 40% of the dictionary's CPU
_PLAIN_COLUMNS = (S.STEP,)
#: the parts' codec (Parquet's LZ4_RAW): 11% less CPU than zstd level -1 per part, files
#: 1.3% larger (byte-stream-split floats leave little but their exponents to compress;
#: docs/scaling.md). Datasets written with zstd parts read the same
_PART_COMPRESSION = "lz4"
#: values the Parquet writer takes per step (its default: 1024): 5% less CPU per part, the
#: same standard pages (cut at the same 1 MiB page size, checked every 64k values)
_PART_WRITE_BATCH = 1 << 16


def _required_where_complete(table: pa.Table) -> pa.Table:
    """``table`` (no copy) with every column without nulls declared non-nullable, the
    same in every part: Parquet then stores it as ``required``, without definition levels
    (encoding them was a third of the parts' writing CPU). Readers get the same values;
    :class:`~offline_adp.data.dataset.TransitionDataset` declares its columns nullable
    again, and a column with a null anywhere stays nullable in every part."""
    fields = [f.with_nullable(False) if not table.column(f.name).null_count else f for f in table.schema]
    return pa.Table.from_arrays(table.columns, schema=pa.schema(fields, metadata=table.schema.metadata))


def _part_encodings(schema: pa.Schema) -> tuple[list[str], dict[str, str]]:
    """Parquet encodings of a part's columns: dictionary pages where values repeat (ids,
    labels, flags); byte-stream-split for floats (their exponent bytes then compress:
    smaller and cheaper than plain zstd); plain for steps; delta for other integers
    (times, source rows: increasing; actions: half the CPU of a dictionary, for 0.1 byte
    a row more)."""
    dictionary, encoding = [], {}
    for f in schema:
        t = f.type.value_type if pa.types.is_dictionary(f.type) else f.type
        if pa.types.is_floating(f.type):
            encoding[f.name] = "BYTE_STREAM_SPLIT"
        elif f.name in _PLAIN_COLUMNS:
            encoding[f.name] = "PLAIN"
        elif pa.types.is_integer(f.type) and f.name not in _DICTIONARY_COLUMNS:
            encoding[f.name] = "DELTA_BINARY_PACKED"
        elif (
            pa.types.is_dictionary(f.type)
            or pa.types.is_string(t)
            or pa.types.is_large_string(t)
            or f.name in _DICTIONARY_COLUMNS
        ):
            dictionary.append(f.name)
    return dictionary, encoding


def _part_bounds(starts: np.ndarray, n_rows: int, rows_per_part: int) -> list[tuple[int, int]]:
    if n_rows == 0:
        return [(0, 0)]
    bounds: list[tuple[int, int]] = []
    lo = 0
    # cut at the first episode start at or beyond lo + rows_per_part, repeatedly
    while lo < n_rows:
        k = np.searchsorted(starts, lo + rows_per_part, side="left")
        hi = int(starts[k]) if k < len(starts) else n_rows
        if hi <= lo:  # single episode longer than rows_per_part
            nxt = np.searchsorted(starts, lo, side="right")
            hi = int(starts[nxt]) if nxt < len(starts) else n_rows
        bounds.append((lo, hi))
        lo = hi
    return bounds


def read_info(path: str | PathLike[str]) -> dict[str, Any]:
    """The raw ``meta/info.json`` of a dataset directory."""
    path = Path(path)
    info_path = path / S.INFO_FILE
    if not info_path.is_file():
        raise DatasetNotFoundError(
            f"{path} is not a dataset directory (no {S.INFO_FILE}); create one with "
            "`offline-adp ingest parquet ...` or `offline-adp simulate ...`"
        )
    return read_json_file(info_path, error=SchemaError)


def part_files(path: str | PathLike[str]) -> list[Path]:
    """The dataset's Parquet parts in order."""
    return sorted((Path(path) / S.DATA_DIR).glob("part-*.parquet"))


def read_dataset_table(path: str | PathLike[str]) -> tuple[pa.Table, DatasetInfo]:
    """The transitions table (all parts) and the info of a dataset directory written by
    :func:`write_dataset`; :func:`offline_adp.data.dataset.read_dataset` builds the dataset.

    Raises
    ------
    DatasetNotFoundError
        If ``path`` has no ``meta/info.json``.
    SchemaError
        If metadata or parts do not match the format.
    """
    path = Path(path)
    raw = read_info(path)
    info = DatasetInfo.from_dict(raw, where=str(path / S.INFO_FILE))
    if info.format_version != S.FORMAT_VERSION:
        warnings.warn(
            f"{path}: written with dataset format {info.format_version!r}, this package reads "
            f"{S.FORMAT_VERSION!r}; re-ingest if anything looks wrong",
            FormatVersionWarning,
            stacklevel=3,  # the caller of read_dataset
        )
    parts = part_files(path)
    if not parts:
        raise SchemaError(f"{path}: no data/part-*.parquet files")
    tables = []
    for p in parts:
        try:
            tables.append(pq.read_table(p))
        except (OSError, pa.ArrowInvalid) as exc:
            raise SchemaError(f"{p}: unreadable Parquet part ({exc})") from exc
    try:
        table = pa.concat_tables(tables, promote_options="permissive")
    except (pa.ArrowInvalid, pa.ArrowTypeError, pa.ArrowNotImplementedError) as exc:
        raise SchemaError(f"{_odd_part(parts, tables) or path}: parts have incompatible schemas ({exc})") from None
    return table, info


def _odd_part(parts: list[Path], tables: list[pa.Table]) -> str | None:
    """The first part whose type of a column differs from the first part's with that column,
    and the column (the concatenation's own error names neither the file nor both types)."""
    first: dict[str, tuple[Path, pa.DataType]] = {}
    for p, t in zip(parts, tables, strict=True):
        for f in t.schema:
            seen = first.setdefault(f.name, (p, f.type))
            if seen[1] != f.type:
                return f"{p}: column {f.name!r} is {f.type}, in {seen[0].name} {seen[1]}"
    return None


def read_quarantine(path: str | PathLike[str]) -> pa.Table | None:
    """Rows quarantined at ingestion (with a ``reason`` column), or None."""
    parts = sorted((Path(path) / S.QUARANTINE_DIR).glob("part-*.parquet"))
    return pa.concat_tables([pq.read_table(p) for p in parts]) if parts else None
