"""Reading and writing dataset directories, atomically; file fingerprints.

Layout (``docs/dataset-format.md``)::

    DIR/data/part-00000.parquet ...   transitions, LZ4, whole episodes per part
    DIR/meta/info.json                DatasetInfo + counts
    DIR/meta/episodes.parquet         one row per episode
    DIR/meta/stats.json               per-column statistics, counts per source/action
    DIR/quarantine/                   rejected episodes with a reason per row (optional)
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import json
import os
import secrets
import shutil
import threading
import warnings
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from offline_adp.data import schema as S
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import DatasetInfo
from offline_adp.errors import (
    DatasetNotFoundError,
    FormatVersionWarning,
    LockedError,
    OutputExistsError,
    SchemaError,
    WriteError,
)

DEFAULT_ROWS_PER_PART = 500_000


def sha256_file(path: str | PathLike[str], chunk: int = 1 << 20) -> str:
    """sha256 of a file's bytes, hex."""
    h = hashlib.sha256()
    buf = bytearray(chunk)  # one buffer, refilled: no fresh allocation (and page zeroing) per block
    view = memoryview(buf)
    with open(path, "rb", buffering=0) as f:
        while size := f.readinto(buf):
            h.update(view[:size])
    return h.hexdigest()


_HELD: dict[str, list[Any]] = {}  # lock file -> [FileLock, depth]: re-entrant within a process
_HELD_GUARD = threading.Lock()


def lock_path(target: str | PathLike[str]) -> Path:
    """The lock file guarding writes to ``target``: ``.NAME.lock`` next to it."""
    t = Path(target).absolute()
    return t.parent / f".{t.name}.lock"


@contextlib.contextmanager
def locked_directory(target: str | PathLike[str], *, what: str = "directory") -> Iterator[Path]:
    """Hold the exclusive write lock of ``target`` (a dataset or run directory, or an
    output file) for the block.

    The lock is an OS file lock (``flock``, the lock :mod:`filelock` takes) on
    ``.NAME.lock`` next to ``target``, released when the block ends or the process dies
    (no stale locks after ``kill -9``). Re-entrant within one process (an ingest holding
    the lock can call :func:`write_dataset`). A second process gets a :class:`LockedError`
    at once, rather than waiting or silently replacing the first one's output.

    The lock file is removed when the lock is released. That is safe only because the
    holder unlinks it *before* unlocking and every taker checks, once it holds the lock,
    that the file it locked is still the one at the path (else it retries on the new
    one): the race filelock warns of (two processes each holding a lock on a different
    inode) cannot happen. A lock file a killed process left is simply taken over.

    Yields the lock file's path.
    """
    lp = lock_path(target)
    key = str(lp)
    with _HELD_GUARD:
        held = _HELD.get(key)
        if held is not None:
            held[1] += 1
    if held is None:
        try:
            lp.parent.mkdir(parents=True, exist_ok=True)
            handle = _acquire(lp, target, what)
        except OSError as exc:
            from offline_adp.errors import os_error_message

            raise WriteError(f"cannot lock {target} for writing: {os_error_message(exc, lp)}") from None
        with _HELD_GUARD:
            _HELD[key] = held = [handle, 1]
    try:
        yield lp
    finally:
        with _HELD_GUARD:
            held[1] -= 1
            last = held[1] == 0
            if last:
                del _HELD[key]
        if last:
            _release(lp, held[0])


def _acquire(lp: Path, target: str | PathLike[str], what: str) -> Any:
    """Take the lock on ``lp`` without waiting (see :func:`locked_directory`)."""
    def locked() -> LockedError:
        return LockedError(f"{target}: another process is writing this {what} (lock {lp} is held); "
                           "wait for it to finish or write somewhere else")

    try:
        import fcntl
    except ImportError:  # no flock (Windows): filelock's lock; its file stays
        from filelock import FileLock, Timeout

        lock = FileLock(lp, timeout=0)
        try:
            lock.acquire()
        except Timeout:
            raise locked() from None
        return lock
    for _ in range(100):
        fd = os.open(lp, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0), 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise locked() from None
        except BaseException:
            os.close(fd)
            raise
        try:  # the holder before us may have removed (unlinked) the file we locked
            current = os.stat(lp, follow_symlinks=False)
        except FileNotFoundError:
            current = None
        if current is not None and os.path.samestat(os.fstat(fd), current):
            return fd
        os.close(fd)  # a removed lock file: take the new one
    raise locked()


def _release(lp: Path, handle: Any) -> None:
    """Remove the lock file while still holding it, then unlock (see :func:`locked_directory`)."""
    if not isinstance(handle, int):
        handle.release()
        return
    try:
        with contextlib.suppress(OSError):  # a read-only parent: the file stays, harmlessly
            if os.path.samestat(os.fstat(handle), os.stat(lp, follow_symlinks=False)):
                os.unlink(lp)
    finally:
        os.close(handle)  # closing the descriptor releases the flock


def _remove(path: Path) -> None:
    """Remove a file, directory tree or symlink without following a symlink."""
    if path.is_symlink() or not path.is_dir():
        path.unlink(missing_ok=True)
    else:
        shutil.rmtree(path, ignore_errors=True)


def _new_sibling(target: Path, tag: str) -> Path:
    """A fresh directory ``.NAME.tag-XXXXXXXX`` next to ``target`` with normal permissions
    (0777 minus the umask, unlike ``mkdtemp``'s 0700), never an existing path or link."""
    for _ in range(100):
        p = target.parent / f".{target.name}.{tag}-{secrets.token_hex(4)}"
        try:
            os.mkdir(p)
            return p
        except FileExistsError:
            continue
    raise WriteError(f"{target.parent}: cannot create a temporary directory for {target.name}")


def clean_stale_temporaries(target: str | PathLike[str]) -> list[Path]:
    """Remove ``.NAME.tmp-*`` / ``.NAME.old-*`` left next to ``target`` by killed writes.

    Call it only while holding :func:`locked_directory` on ``target`` (every writer of
    ``target`` does, so whatever is there then is stale). Symlinks are removed, never
    followed. Returns what was removed.
    """
    target = Path(target)
    if not target.parent.is_dir():
        return []
    gone = []
    for pattern in (f".{target.name}.tmp-*", f".{target.name}.old-*"):
        for p in target.parent.glob(glob.escape(pattern[:-1]) + "*"):
            _remove(p)
            gone.append(p)
    return gone


@contextlib.contextmanager
def atomic_directory(target: str | PathLike[str], *, overwrite: bool = False, clean_stale: bool = False) -> Iterator[Path]:
    """Yield a temporary directory next to ``target``; on success rename it to ``target``.

    A crash or exception inside the block removes the temporary directory and leaves
    ``target`` as it was (absent, or the previous version when overwriting). The
    temporary directory is new (never a planted path or link) and gets normal
    permissions; a ``target`` that is a symlink is replaced, not followed. With
    ``clean_stale`` (only while holding :func:`locked_directory` on ``target``), temporary
    directories left by killed writes of ``target`` are removed first.
    """
    target = Path(target)
    if clean_stale:
        clean_stale_temporaries(target)
    if (target.exists() or target.is_symlink()) and not overwrite:
        raise OutputExistsError(f"{target} already exists; pass overwrite=True (CLI: --overwrite) to replace it")
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = _new_sibling(target, "tmp")
    trash = None
    try:
        yield tmp
        if target.exists() or target.is_symlink():
            trash = _new_sibling(target, "old")
            os.replace(target, trash / "old")
            try:
                os.replace(tmp, target)
            except BaseException:
                os.replace(trash / "old", target)  # the previous version back in place
                raise
        else:
            os.replace(tmp, target)
    except BaseException:
        _remove(tmp)
        raise
    finally:  # the set-aside previous version, once the target is whole again (new or restored)
        if trash is not None and (target.exists() or not (trash / "old").exists()):
            _remove(trash)


def write_text_nofollow(path: str | PathLike[str], text: str) -> None:
    """Write ``text`` to ``path`` without following a symlink planted at ``path``
    (``O_NOFOLLOW``: a link there is an error, not a write to wherever it points)."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0), 0o666)
    except OSError as exc:
        if path.is_symlink():
            raise WriteError(f"{path} is a symbolic link; refusing to write through it") from None
        raise WriteError(f"{path}: cannot write ({exc.strerror})") from None
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)


@contextlib.contextmanager
def atomic_file(target: str | PathLike[str], *, what: str = "file", lock: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to ``target``; on success rename it to ``target``.

    The one helper for output *files* (a compare's JSON, a raw table, ...): the temporary
    (``.NAME.tmp-XXXXXXXX``) is removed whatever happens, so a failed write (full disk,
    read-only folder, Ctrl-C) leaves ``target`` as it was. A ``target`` that is a
    directory is refused before anything is written; a symbolic link at ``target`` is
    replaced, not followed. With ``lock``, the write holds :func:`locked_directory` on
    ``target`` (a second writer fails at once).
    """
    target = Path(target)
    if target.is_dir() and not target.is_symlink():
        raise WriteError(f"{target} is a directory; expected a {what} path (name a file, e.g. {target / 'out'}"
                         f"{target.suffix or ''})")
    with locked_directory(target, what=what) if lock else contextlib.nullcontext():
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.parent / f".{target.name}.tmp-{secrets.token_hex(4)}"
        try:
            yield tmp
            os.replace(tmp, target)
        finally:
            if tmp.exists() or tmp.is_symlink():
                _remove(tmp)


def atomic_write_text(target: str | PathLike[str], text: str, *, what: str = "file") -> Path:
    """Write ``text`` to ``target`` through :func:`atomic_file`."""
    with atomic_file(target, what=what) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(target)


def write_json(path: Path, obj: Any) -> None:
    from offline_adp.data.info import _json_default

    write_text_nofollow(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def dataset_stats(ds: TransitionDataset) -> dict[str, Any]:
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
        if len(buf) < len(finite):
            buf = np.empty(len(finite))
        mean, std = _mean_std(finite, buf[:len(finite)], total)
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


def _mean_std(x: np.ndarray, buf: np.ndarray, total: float | None = None) -> tuple[float, float]:
    """``x.mean()`` and ``x.std()`` of a 1-D float64 array, bit for bit (numpy's own steps:
    the pairwise sum over n, then the sum of squared deviations), with the deviations in
    ``buf`` (reused across columns) instead of a fresh array per call, and one sum for both
    (``total``, ``np.add.reduce(x)``, when the caller has it)."""
    n = len(x)
    mean = (np.add.reduce(x) if total is None else total) / n
    np.subtract(x, mean, out=buf)
    np.multiply(buf, buf, out=buf)
    return float(mean), float(np.sqrt(np.add.reduce(buf) / n))


def write_dataset(
    ds: TransitionDataset,
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
            pq.write_table(
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
        pq.write_table(pa.Table.from_pandas(ep, preserve_index=False), tmp / S.EPISODES_FILE)
        write_json(tmp / S.STATS_FILE, stats)
        if quarantine is not None and quarantine.num_rows:
            (tmp / S.QUARANTINE_DIR).mkdir()
            pq.write_table(quarantine, tmp / S.QUARANTINE_DIR / S.PART_TEMPLATE.format(0), compression=S.PARQUET_COMPRESSION)
    return path


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
        elif pa.types.is_dictionary(f.type) or pa.types.is_string(t) or pa.types.is_large_string(t) or f.name in _DICTIONARY_COLUMNS:
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
    from offline_adp.data.rundir import read_json_file

    return read_json_file(info_path, error=SchemaError)


def part_files(path: str | PathLike[str]) -> list[Path]:
    """The dataset's Parquet parts in order."""
    return sorted((Path(path) / S.DATA_DIR).glob("part-*.parquet"))


def read_dataset(path: str | PathLike[str]) -> TransitionDataset:
    """Read a dataset directory written by :func:`write_dataset`.

    Raises
    ------
    DatasetNotFoundError
        If ``path`` has no ``meta/info.json``.
    SchemaError
        If metadata or columns do not match the format.
    """
    path = Path(path)
    raw = read_info(path)
    info = DatasetInfo.from_dict(raw, where=str(path / S.INFO_FILE))
    if info.format_version != S.FORMAT_VERSION:
        warnings.warn(
            f"{path}: written with dataset format {info.format_version!r}, this package reads "
            f"{S.FORMAT_VERSION!r}; re-ingest if anything looks wrong",
            FormatVersionWarning,
            stacklevel=2,
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
        raise SchemaError(f"{path}: parts have incompatible schemas ({exc})") from None
    try:
        return TransitionDataset(table, info)
    except SchemaError as exc:
        raise SchemaError(f"{path}: {exc}") from None


def read_quarantine(path: str | PathLike[str]) -> pa.Table | None:
    """Rows quarantined at ingestion (with a ``reason`` column), or None."""
    parts = sorted((Path(path) / S.QUARANTINE_DIR).glob("part-*.parquet"))
    return pa.concat_tables([pq.read_table(p) for p in parts]) if parts else None
