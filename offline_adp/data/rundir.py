"""``RunDirectory``: the one owner of a run directory's layout, atomic writes and lock.

A fit run directory (``offline-adp fit --out RUN``, a pipeline's ``fit/``) and a
pipeline run directory are both run directories::

    RUN/../.RUN.lock     held while a process writes the run (a second writer fails at once)
    RUN/config.json      the resolved configuration, written before the work starts
    RUN/run.json         status, dataset fingerprint, versions, wall and CPU seconds
    RUN/checkpoint/      the last completed iteration (resumable algorithms)
    RUN/model/           the fitted artifacts (written last, as a whole)

Every file is written to a temporary name in the same directory and renamed over the
target (``os.replace``), and every subdirectory through
:func:`offline_adp.data.io.atomic_directory`; a rename replaces a symbolic link
planted at the target instead of writing through it, so nothing outside the run is
ever written. A crash leaves the previous version of each file, never half of one.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
from collections.abc import Iterator
from os import PathLike
from pathlib import Path
from typing import Any

from offline_adp.errors import (
    MAX_JSON_DEPTH,
    ArtifactError,
    InvalidArgumentError,
    OfflineADPError,
    RunDirectoryError,
    WriteError,
    json_depth,
)

#: What a run or pipeline name may be: no path separators, no glob characters.
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$"


def check_name(name: str, what: str = "name") -> str:
    """A pipeline/run name usable as one path component (letters, digits, ``._-``)."""
    if not isinstance(name, str) or not re.match(NAME_PATTERN, name) or name in (".", ".."):
        raise InvalidArgumentError(f"{what} {name!r} is not allowed: use letters, digits, '.', '_' and '-' "
                                   "(no path separators or glob characters), starting with a letter or digit")
    return name


class RunDirectory:
    """A run directory (see the module docstring).

    Parameters
    ----------
    path : path-like
        The directory; created (with its parents) by :meth:`lock`.
    """

    CONFIG = "config.json"
    STATUS = "run.json"
    MODEL = "model"
    CHECKPOINT = "checkpoint"

    def __init__(self, path: str | PathLike[str]) -> None:
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"RunDirectory({str(self.path)!r})"

    # ------------------------------------------------------------------ lock
    @contextlib.contextmanager
    def lock(self) -> Iterator[RunDirectory]:
        """Hold the run's write lock for the block (:func:`offline_adp.data.io.locked_directory`,
        the same lock as dataset directories): a second writer gets
        :class:`~offline_adp.errors.LockedError` at once (exit 2 on the CLI). Re-entrant.
        Under the lock, a killed writer's temporaries are removed first."""
        from offline_adp.data.io import locked_directory

        if self.path.is_symlink():
            raise RunDirectoryError(f"{self.path} is a symbolic link; give the real directory as the run directory")
        with locked_directory(self.path, what="run directory"):
            self.path.mkdir(parents=True, exist_ok=True)
            self.clean_stale_temporaries()
            yield self

    def clean_stale_temporaries(self) -> list[Path]:
        """Remove temporary files and directories of ours left by a killed writer
        (``.NAME.tmp-*``, ``.NAME.old-*``, ``*.tmp``); only safe under the lock."""
        removed = []
        for p in self.path.iterdir():
            if re.match(r"^\..+\.(tmp|old)-", p.name) or (p.name.endswith(".tmp") and p.name.startswith(".")):
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p, ignore_errors=True)
                else:
                    p.unlink(missing_ok=True)
                removed.append(p)
        return removed

    # ------------------------------------------------------------------ files
    def file(self, name: str) -> Path:
        """``RUN/name``, refusing names that would leave the directory."""
        p = self.path / name
        if Path(name).is_absolute() or ".." in Path(name).parts:
            raise InvalidArgumentError(f"{name!r}: not a file name inside {self.path}")
        return p

    def exists(self, name: str) -> bool:
        return self.file(name).exists()

    def write_text(self, name: str, text: str) -> Path:
        """Write ``RUN/name`` atomically (temporary file in the same folder, then rename);
        a symbolic link at the target is replaced, never followed."""
        target = self.file(name)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.parent / f".{target.name}.tmp"
        if tmp.is_symlink() or tmp.exists():
            tmp.unlink()
        if target.is_dir() and not target.is_symlink():
            raise WriteError(f"{target} is a directory, expected a file; remove it")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o666)
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(text)
            os.replace(tmp, target)
        finally:  # a failed write (full disk, Ctrl-C) leaves the previous file and no temporary
            tmp.unlink(missing_ok=True)
        return target

    def write_json(self, name: str, obj: Any) -> Path:
        return self.write_text(name, json.dumps(obj, indent=1, default=_json_default) + "\n")

    def read_json(self, name: str) -> dict[str, Any]:
        """Read ``RUN/name`` (a JSON object); a symbolic link there is refused (it was not
        written by us). Missing or corrupt: :class:`~offline_adp.errors.ArtifactError`
        naming the file."""
        p = self.file(name)
        if p.is_symlink():
            raise ArtifactError(f"{p} is a symbolic link, not a file this run wrote; remove it")
        return read_json_file(p, missing=f"missing (is {self.path} a run directory?)")

    @contextlib.contextmanager
    def subdirectory(self, name: str) -> Iterator[Path]:
        """Yield a temporary directory that replaces ``RUN/name`` as a whole on success."""
        from offline_adp.data.io import atomic_directory

        target = self.file(name)
        if target.is_symlink():
            target.unlink()
        with atomic_directory(target, overwrite=True) as tmp:
            yield tmp

    def copy_in(self, src: str | PathLike[str], name: str) -> Path:
        """Copy the file or directory ``src`` to ``RUN/name`` atomically, replacing what
        was there (a planted link included) without writing through it."""
        src = Path(src)
        if src.is_dir():
            with self.subdirectory(name) as tmp:
                shutil.copytree(src, tmp, dirs_exist_ok=True)
            return self.file(name)
        target = self.file(name)
        tmp = target.parent / f".{target.name}.tmp"
        if tmp.is_symlink() or tmp.exists():
            tmp.unlink()
        if target.is_dir() and not target.is_symlink():
            raise WriteError(f"{target} is a directory, expected a file; remove it")
        try:
            shutil.copyfile(src, tmp, follow_symlinks=True)
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        return target

    def remove(self, name: str) -> None:
        p = self.file(name)
        if p.is_symlink() or p.is_file():
            p.unlink()
        elif p.exists():
            shutil.rmtree(p)


def _json_default(o: Any) -> Any:
    if hasattr(o, "item"):
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)


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
