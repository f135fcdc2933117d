"""Filesystem primitives: atomic writes, the write lock, bounded reads, file fingerprints.

Nothing here knows what a dataset or a run is: :mod:`offline_adp.data.io` (dataset
directories) and :mod:`offline_adp.data.rundir` (run directories) are built on it, and so
is every other writer of an output file or directory.

- writes: :func:`atomic_directory` (a directory replaced as a whole), :func:`atomic_file`
  (the one helper for output files; :func:`atomic_write_text` on top of it),
  :func:`write_text_nofollow` (a file inside a temporary directory, never through a link);
- the lock: :func:`locked_directory` (``.NAME.lock`` next to the target, re-entrant,
  exclusive across processes), :func:`clean_stale_temporaries`;
- bounded reads of files this package wrote: :func:`read_json_file` (size and depth
  capped, a device or FIFO refused) and :func:`read_table_file`;
- :func:`sha256_file`.
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
from collections.abc import Iterator
from os import PathLike
from pathlib import Path
from typing import Any

from offline_adp.errors import (
    MAX_JSON_DEPTH,
    ArtifactError,
    LockedError,
    OfflineADPError,
    OutputExistsError,
    WriteError,
    json_depth,
)


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
def atomic_directory(target: str | PathLike[str], *, overwrite: bool = False,
                     clean_stale: bool = False) -> Iterator[Path]:
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
    ``target`` (a second writer fails at once) and first removes the temporaries of writes
    of ``target`` killed before (``kill -9`` leaves them; nothing else can be writing it).
    """
    target = Path(target)
    if target.is_dir() and not target.is_symlink():
        raise WriteError(f"{target} is a directory; expected a {what} path (name a file, e.g. {target / 'out'}"
                         f"{target.suffix or ''})")
    with locked_directory(target, what=what) if lock else contextlib.nullcontext():
        if lock:
            clean_stale_temporaries(target)
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


def read_json_file(path: str | PathLike[str], *, missing: str = "missing",
                   error: type[OfflineADPError] = ArtifactError) -> dict[str, Any]:
    """Read a JSON object written by this package (``run.json``, ``metrics.json``, ...).

    A missing, unreadable, truncated or non-object file raises
    ``error`` (default :class:`~offline_adp.errors.ArtifactError`) whose message starts with the file's path
    (``missing`` is what it says when the file does not exist), never a raw
    ``JSONDecodeError``.
    """
    p = Path(path)
    try:
        obj = json.loads(_regular_bytes(p, MAX_JSON_BYTES, error).decode("utf-8"))
    except FileNotFoundError:
        raise error(f"{p}: {missing}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise error(f"{p}: not valid JSON ({exc}); the file is corrupt or truncated, write it again") from None
    except RecursionError:
        raise error(f"{p}: JSON nested deeper than {MAX_JSON_DEPTH} levels; not a file this package wrote") from None
    except OSError as exc:
        raise error(f"{p}: cannot be read ({exc.strerror or exc})") from None
    if not isinstance(obj, dict):
        raise error(f"{p}: expected a JSON object, found {type(obj).__name__}")
    if json_depth(obj) > MAX_JSON_DEPTH:
        raise error(f"{p}: JSON nested deeper than {MAX_JSON_DEPTH} levels; not a file this package wrote")
    return obj


#: The largest JSON file of a run or dataset read (``metrics.json``, ``run.json``,
#: ``meta/info.json``...): far above any this package writes.
MAX_JSON_BYTES = 256 << 20


def _regular_bytes(p: Path, cap: int, error: type[OfflineADPError]) -> bytes:
    """The bytes of ``p`` if it is a regular file of at most ``cap`` bytes (a device such
    as ``/dev/zero``, a FIFO or a directory is refused without blocking); else ``error``."""
    import stat

    fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{p}: not a regular file (a directory, device, pipe or socket)")
        if st.st_size > cap:
            raise error(f"{p}: {st.st_size} bytes, more than such a file can be ({cap} bytes)")
        raw = f.read(cap + 1)
    if len(raw) > cap:
        raise error(f"{p}: more than {cap} bytes, more than such a file can be")
    return raw


def read_table_file(path: str | PathLike[str]) -> Any:
    """Read a Parquet (``.parquet``) or CSV table written by this package as a
    ``pandas.DataFrame``; a missing or corrupt file raises
    :class:`~offline_adp.errors.ArtifactError` naming it."""
    import pandas as pd
    import pyarrow as pa

    p = Path(path)
    try:
        if p.suffix == ".parquet":
            return pd.read_parquet(p)
        return pd.read_csv(p)
    except FileNotFoundError:
        raise ArtifactError(f"{p}: missing") from None
    except (OSError, ValueError, pa.ArrowException, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise ArtifactError(f"{p}: not a readable {'Parquet' if p.suffix == '.parquet' else 'CSV'} table ({exc}); "
                            "the file is corrupt or truncated, write it again") from None
