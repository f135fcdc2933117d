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
    meta = directory / "metadata.yaml"
    if meta.is_file():
        text = meta.read_text(errors="replace")
        try:
            import yaml

            info = (yaml.safe_load(text) or {}).get("rosbag2_bagfile_information", {})
            rel = [str(x) for x in info.get("relative_file_paths") or []]
            storage = str(info.get("storage_identifier", ""))
        except ImportError:  # pragma: no cover - a plain reading of the two keys
            block = re.search(r"relative_file_paths:\s*\n((?:\s*-\s*.+\n?)+)", text)
            rel = re.findall(r"-\s*(\S+)", block.group(1)) if block else []
            m = re.search(r"storage_identifier:\s*(\S+)", text)
            storage = m.group(1) if m else ""
        except Exception as exc:  # noqa: BLE001 - yaml errors of several types
            raise IngestError(f"{meta}: cannot read the bag's metadata ({type(exc).__name__}: {exc})") from None
        if storage and storage != "mcap":
            raise IngestError(f"{directory}: a rosbag2 bag stored as {storage!r}, not MCAP or SQLite (convert it "
                              "with `ros2 bag convert`, or record with --storage mcap)")
        if not rel:
            raise IngestError(f"{meta}: lists no files (relative_file_paths)")
        files = [directory / r for r in rel]
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            raise IngestError(f"{directory}: metadata.yaml lists {missing}, which are missing")
        return files
    found = sorted(directory.glob("*.mcap"), key=lambda p: (re.sub(r"_\d+$", "", p.stem),
                                                           int(m.group(1)) if (m := re.search(r"_(\d+)$", p.stem)) else 0))
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
            if path.is_dir():  # a rosbag2 bag: one recording
                from offline_adp.ingest.mcap.rosbags_source import is_rosbags_input

                groups[("bag", str(path))] = [(0, path)] if is_rosbags_input(path) else list(enumerate(bag_files(path)))
                continue
            if not path.is_file():
                raise IngestError(f"{h}: no such file")
            if path in seen:
                continue
            seen.add(path)
            m = re.fullmatch(r"(.*)_(\d+)\.mcap", path.name) if spec.split_recordings else None
            key = (str(path.parent), m.group(1)) if m else (str(path),)
            groups.setdefault(key, []).append((int(m.group(2)) if m else 0, path))
    return [[p for _, p in sorted(g)] for g in groups.values()]
