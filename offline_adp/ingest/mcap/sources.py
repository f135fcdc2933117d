"""Input files -> recordings (globs, split recordings)."""

from __future__ import annotations

import re
from collections.abc import Sequence
from os import PathLike
from pathlib import Path
from typing import Any

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap.spec import McapSpec


def bag_files(directory: Path) -> list[Path]:
    """The MCAP files of a rosbag2 bag directory (what ``ros2 bag record`` writes:
    ``metadata.yaml`` and ``NAME_0.mcap``, ``NAME_1.mcap`` ...), in the order
    ``metadata.yaml`` gives (``relative_file_paths``); without it, the ``*.mcap`` files in
    part order."""
    import os

    if os.path.lexists(directory / "metadata.yaml"):
        from offline_adp.ingest.mcap.bagmeta import read_bag_metadata

        meta = read_bag_metadata(directory)
        if meta.storage == "sqlite3":
            raise IngestError(f"{directory}: a rosbag2 SQLite bag (read through rosbags), not MCAP files")
        return list(meta.files)
    found = sorted(directory.glob("*.mcap"), key=lambda p: (re.sub(r"_\d+$", "", p.stem),
                                                           int(m.group(1)) if (m := re.search(r"_(\d+)$", p.stem))
                                                           else 0))
    if not found:
        raise IngestError(f"{directory}: a directory without metadata.yaml or *.mcap files (not a rosbag2 bag)")
    return found


def resolve_sources(files: Sequence[str | PathLike[str]], spec: McapSpec) -> list[list[Path]]:
    """Input files grouped into recordings, in a deterministic order.

    ``files`` (or, when empty, the spec's ``[sources] files`` globs, relative to the spec
    file) are expanded; a rosbag2 bag directory is one recording, its files in the order
    of its ``metadata.yaml``; with ``split_recordings`` the parts of one split recording
    (rosbag2's ``NAME_0.mcap``, ``NAME_1.mcap`` ... in one directory) form one recording,
    read in part order. Every other file is a recording of its own.
    """
    import glob

    pats = [str(f) for f in files] or [str(Path(spec.base_dir) / g) for g in spec.files]
    if not pats:
        raise IngestError("no MCAP files given (pass FILES or set [sources] files in the spec)")
    seen: set[Path] = set()
    groups: dict[Any, list[tuple[int, Path]]] = {}  # in input order
    for p in pats:
        hits = sorted(glob.glob(p)) if any(ch in p for ch in "*?[") else [p]
        if not hits:
            raise IngestError(f"{p}: no file matches")
        for h in hits:
            path = Path(h)
            bag = rosbag2_directory(path)
            if bag is not None:  # a rosbag2 bag (its directory or one of its parts): one recording, read once
                key = ("bag", str(bag.resolve()))
                if key in groups:
                    continue
                from offline_adp.ingest.mcap.rosbags_source import is_rosbags_input

                groups[key] = [(0, bag)] if is_rosbags_input(bag) else list(enumerate(bag_files(bag)))
                continue
            if not path.is_file():
                raise IngestError(f"{h}: no such file")
            if path.resolve() in seen:
                continue
            seen.add(path.resolve())
            m = re.fullmatch(r"(.*)_(\d+)\.mcap", path.name) if spec.split_recordings else None
            key = (str(path.parent), m.group(1)) if m else (str(path),)
            groups.setdefault(key, []).append((int(m.group(2)) if m else 0, path))
    return [[p for _, p in sorted(g)] for g in groups.values()]


def rosbag2_directory(path: Path) -> Path | None:
    """The rosbag2 bag a path stands for: a directory, or a SQLite part (``.db3``) of a
    bag, whose ``metadata.yaml`` must list it (a part is never read on its own: the bag
    is, once, however many of its parts are given). None for anything else."""
    import os

    if path.is_dir():
        return path
    if path.suffix != ".db3":
        return None
    if not path.is_file():
        raise IngestError(f"{path}: no such file")
    bag = path.parent
    if not os.path.lexists(bag / "metadata.yaml"):
        raise IngestError(f"{path}: a rosbag2 SQLite part without its bag's metadata.yaml ({bag / 'metadata.yaml'} is "
                          "missing; the rosbags reader needs it to read the part: copy the bag's metadata.yaml "
                          "next to it, or run `ros2 bag reindex` on the directory)")
    from offline_adp.ingest.mcap.bagmeta import read_bag_metadata

    meta = read_bag_metadata(bag)
    real = path.resolve()
    if not any(f.resolve() == real for f in meta.files):
        raise IngestError(f"{path}: not listed in {bag / 'metadata.yaml'} (relative_file_paths = "
                          f"{list(meta.entries)[:10]})")
    return bag
