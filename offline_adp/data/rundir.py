"""``RunDirectory``: the one owner of a run directory's layout, atomic writes and lock.

A fit run directory (``offline-adp fit --out RUN``, a pipeline's ``fit/``) and a
pipeline run directory are both run directories::

    RUN/../.RUN.lock     held while a process writes the run (a second writer fails at once)
    RUN/config.json      the resolved configuration, written before the work starts
    RUN/run.json         status, dataset fingerprint, versions, wall and CPU seconds
    RUN/checkpoint/      the last completed iteration (resumable algorithms)
    RUN/model/           the fitted artifacts (written last, as a whole)

Every file is written through :func:`offline_adp.data.files.atomic_file` (a temporary
name in the same directory, renamed over the target with ``os.replace``), and every
subdirectory through :func:`offline_adp.data.files.atomic_directory`; a rename replaces a symbolic link
planted at the target instead of writing through it, so nothing outside the run is
ever written. A crash leaves the previous version of each file, never half of one.
"""

from __future__ import annotations

import contextlib
import json
import re
import shutil
from collections.abc import Iterator
from os import PathLike
from pathlib import Path
from typing import Any

from offline_adp.data.files import (
    atomic_directory,
    atomic_file,
    locked_directory,
    read_json_file,
    write_text_nofollow,
)
from offline_adp.errors import ArtifactError, InvalidArgumentError, RunDirectoryError

#: What a run or pipeline name may be: no path separators, no glob characters.
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$"


def check_name(name: str, what: str = "name") -> str:
    """A pipeline/run name usable as one path component (letters, digits, ``._-``)."""
    if not isinstance(name, str) or not re.match(NAME_PATTERN, name) or name in (".", ".."):
        raise InvalidArgumentError(f"{what} {name!r} is not allowed: use letters, digits, '.', '_' and '-' "
                                   "(no path separators or glob characters), starting with a letter or digit")
    return name


def pipeline_hint(path: str | PathLike[str]) -> str:
    """Where ``path`` is a pipeline run directory (``offline-adp run``: its fitted run in
    ``fit/``, its metrics and report at the top), the words that send a user there, to append
    to an error about a missing ``model/`` or ``evaluation/``; else ``""``."""
    p = Path(path)
    if not ((p / "fit" / "model").is_dir() and (p / "manifest.json").is_file()):
        return ""
    fit = p / "fit"
    return (f"; {p} is a pipeline run directory (`offline-adp run`): its fitted run is {fit} (e.g. "
            f"`offline-adp evaluate {fit}`, `offline-adp report {fit}`), its metrics {p / 'metrics.json'} and its "
            f"report {p / 'report.html'}")


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
        """Hold the run's write lock for the block (:func:`offline_adp.data.files.locked_directory`,
        the same lock as dataset directories): a second writer gets
        :class:`~offline_adp.errors.LockedError` at once (exit 2 on the CLI). Re-entrant.
        Under the lock, a killed writer's temporaries are removed first."""
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
        """Write ``RUN/name`` atomically (:func:`~offline_adp.data.files.atomic_file`, without
        a lock of its own: the run's lock covers it); a symbolic link at the target is
        replaced, never followed."""
        target = self.file(name)
        with atomic_file(target, lock=False) as tmp:
            write_text_nofollow(tmp, text)
        return target

    def write_json(self, name: str, obj: Any) -> Path:
        return self.write_text(name, json.dumps(obj, indent=1, default=_json_or_str) + "\n")

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
        with atomic_file(target, lock=False) as tmp:
            shutil.copyfile(src, tmp, follow_symlinks=True)
        return target

    def remove(self, name: str) -> None:
        p = self.file(name)
        if p.is_symlink() or p.is_file():
            p.unlink()
        elif p.exists():
            shutil.rmtree(p)


def recorded_dataset(run_json: str | PathLike[str], info: dict[str, Any] | None = None) -> str | None:
    """The dataset path a run's ``run.json`` names, or None when it names none (no such key,
    null or empty); ``info``: the file's contents where the caller read them.

    ``dataset`` is the path as typed at the fit, so a relative one meant the fit's working
    directory; ``dataset_resolved`` (runs fitted since 2026-11-29) is its absolute path. For a
    relative ``dataset`` the absolute one is returned when it still holds a dataset, so a run
    finds its data from any directory (the relative path read from another directory could
    name other logs); an absolute ``dataset``, or one edited since (``dataset_resolved`` no
    longer ends with it), is returned as it is.
    Anything else there (a number, a list...) is an :class:`~offline_adp.errors.ArtifactError`
    naming the file and the key, not a ``TypeError`` from ``Path()`` or a path that silently
    means the current directory."""
    p = Path(run_json)
    doc = info if info is not None else read_json_file(p)
    value = doc.get("dataset")
    if value is None or value == "":
        return None
    for key, v in (("dataset", value), ("dataset_resolved", doc.get("dataset_resolved"))):
        if key == "dataset_resolved" and v is None:
            continue
        if not isinstance(v, str) or "\0" in v or not v:
            raise ArtifactError(f"{p}: {key!r} must be the path of the dataset directory (a string), found "
                                f"{type(v).__name__} {v!r:.60}; fit the run again or pass --dataset DIR")
    resolved = doc.get("dataset_resolved")
    typed = Path(value).parts
    if (resolved is not None and not Path(value).is_absolute() and Path(resolved).is_absolute()
            and ".." not in typed and Path(resolved).parts[-len(typed):] == typed  # not edited since
            and (Path(resolved) / "meta" / "info.json").is_file()):
        return str(resolved)
    return str(value)


def _json_or_str(o: Any) -> Any:
    """``json.dumps``'s ``default`` for a run's own files: numpy values as Python values,
    anything else as its ``str`` (a run file is written whatever a setting holds)."""
    if hasattr(o, "item"):
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)


def check_outside_run(run_dir: str | PathLike[str], out: str | PathLike[str], *, directory: bool = False) -> None:
    """Refuse an output that would replace or change the files of the run it reads (the
    one rule of ``export``, ``annotate`` and ``distill``): the run directory itself, a path
    that already exists in it, anything under its ``model/`` or ``checkpoint/``, and, for a
    ``directory`` output (a distilled run), anywhere inside it. A new file elsewhere in the
    run directory is fine. Checked before anything is written (a lock makes folders)."""
    run, target = Path(run_dir).resolve(), Path(out).resolve()
    if run != target and run not in target.parents:
        return
    if (directory or target == run or target.exists()
            or any(run / d in target.parents for d in ("model", "checkpoint"))):
        from offline_adp.errors import WriteError

        raise WriteError(f"--out {out} lies inside the run directory {run_dir}: it would replace or change the files "
                         "of the run; write it elsewhere (or, for a file, under a new name)")
