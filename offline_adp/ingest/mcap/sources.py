"""Input files -> recordings (globs, split recordings)."""

from __future__ import annotations

import re
from collections.abc import Sequence
from os import PathLike
from pathlib import Path
from typing import Any

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap.spec import McapSpec


def resolve_sources(files: Sequence[str | PathLike[str]], spec: McapSpec) -> list[list[Path]]:
    """Input files grouped into recordings, in a deterministic order.

    ``files`` (or, when empty, the spec's ``[sources] files`` globs, relative to the spec
    file) are expanded; with ``split_recordings`` the parts of one split recording
    (rosbag2's ``NAME_0.mcap``, ``NAME_1.mcap`` ... in one directory) form one recording,
    read in part order. Every other file is a recording of its own.
    """
    import glob

    pats = [str(f) for f in files] or [str(Path(spec.base_dir) / g) for g in spec.files]
    if not pats:
        raise IngestError("no MCAP files given (pass FILES or set [sources] files in the spec)")
    paths: list[Path] = []
    for p in pats:
        hits = sorted(glob.glob(p)) if any(ch in p for ch in "*?[") else [p]
        if not hits:
            raise IngestError(f"{p}: no file matches")
        for h in hits:
            if not Path(h).is_file():
                raise IngestError(f"{h}: no such file")
            if Path(h) not in paths:
                paths.append(Path(h))
    groups: dict[Any, list[tuple[int, Path]]] = {}
    for p in paths:
        m = re.fullmatch(r"(.*)_(\d+)\.mcap", p.name) if spec.split_recordings else None
        key = (str(p.parent), m.group(1)) if m else (str(p),)
        groups.setdefault(key, []).append((int(m.group(2)) if m else 0, p))
    return [[p for _, p in sorted(g)] for g in groups.values()]
