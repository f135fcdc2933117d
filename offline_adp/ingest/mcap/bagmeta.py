"""A rosbag2 bag directory's ``metadata.yaml``, read as untrusted input.

The file is read with a size cap (a regular file, checked against its size before
reading), parsed without YAML aliases (a "billion laughs" file cannot expand), and its
``relative_file_paths`` are confined to the bag directory: no absolute paths, no ``..``,
no symbolic link leading out of it, regular files only, each file listed once. Every
refusal is one ``IngestError`` naming ``metadata.yaml`` and the entry at fault.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

from offline_adp.errors import IngestError

MAX_METADATA_BYTES = 1 << 20  # a real metadata.yaml is a few kB (one entry per topic and file)
MAX_FILES = 100_000
# "": no storage_identifier (MCAP assumed, as before rosbag2 wrote one)  # relative_file_paths entries
STORAGES = ("mcap", "sqlite3", "")


@dataclass(frozen=True)
class BagMetadata:
    """What ingestion needs of a bag's metadata: its storage and its files, in order."""

    directory: Path
    storage: str
    files: tuple[Path, ...]
    entries: tuple[str, ...]  # relative_file_paths as written


def _loader() -> Any:
    import yaml

    class NoAliasLoader(yaml.SafeLoader):
        """PyYAML's safe loader refusing aliases (``*name``): without them the parsed
        document is no larger than the text."""

        def compose_node(self, parent: Any, index: Any) -> Any:
            if self.check_event(yaml.events.AliasEvent):
                event = self.peek_event()
                raise yaml.YAMLError(f"YAML alias *{event.anchor} at line {event.start_mark.line + 1} "
                                     "(aliases are not allowed in a bag's metadata)")
            return super().compose_node(parent, index)

    return NoAliasLoader


def read_bounded(path: Path, limit: int, what: str) -> bytes:
    """The bytes of a regular file no larger than ``limit`` (checked before reading)."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise IngestError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    if not stat.S_ISREG(st.st_mode):
        raise IngestError(f"{path}: {what} is not a regular file")
    if st.st_size > limit:
        raise IngestError(f"{path}: {what} is {st.st_size} bytes, more than the limit of {limit} bytes")
    try:
        with open(path, "rb") as f:
            data = f.read(limit + 1)
    except OSError as exc:
        raise IngestError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    if len(data) > limit:
        raise IngestError(f"{path}: {what} grew beyond the limit of {limit} bytes while being read")
    return data


def parse_metadata_text(text: str, meta: Path) -> dict[str, Any]:
    """The ``rosbag2_bagfile_information`` mapping of a metadata.yaml text (aliases refused)."""
    try:
        import yaml
    except ImportError:  # pragma: no cover - PyYAML comes with the locked environment
        raise IngestError(f"{meta}: reading a rosbag2 metadata.yaml needs PyYAML (pip install pyyaml)") from None
    try:
        doc = yaml.load(text, Loader=_loader())  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise IngestError(f"{meta}: not valid bag metadata ({' '.join(str(exc).split())})") from None
    except RecursionError:
        raise IngestError(f"{meta}: not valid bag metadata (nested too deeply)") from None
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise IngestError(f"{meta}: no 'rosbag2_bagfile_information' mapping (not a rosbag2 metadata.yaml)")
    return info


def read_bag_metadata(directory: str | os.PathLike[str]) -> BagMetadata:
    """Read and check ``directory/metadata.yaml`` (see the module docstring)."""
    directory = Path(directory)
    meta = directory / "metadata.yaml"
    if not os.path.lexists(meta):
        raise IngestError(f"{directory}: no metadata.yaml (not a rosbag2 bag directory)")
    root = directory.resolve()
    if meta.is_symlink() and not _inside(meta.resolve(), root):
        raise IngestError(f"{meta}: a symbolic link leading out of the bag directory")
    text = read_bounded(meta, MAX_METADATA_BYTES, "the bag's metadata").decode("utf-8", errors="replace")
    info = parse_metadata_text(text, meta)
    storage = info.get("storage_identifier", "")
    if not isinstance(storage, str):
        raise IngestError(f"{meta}: storage_identifier is {type(storage).__name__}, not a name")
    if storage not in STORAGES:
        raise IngestError(f"{directory}: a rosbag2 bag stored as {storage!r}, not MCAP or SQLite (convert it "
                          "with `ros2 bag convert`, or record with --storage mcap)")
    rel = info.get("relative_file_paths")
    if rel is None or rel == []:
        raise IngestError(f"{meta}: lists no files (relative_file_paths)")
    if not isinstance(rel, list):
        raise IngestError(f"{meta}: relative_file_paths is a {type(rel).__name__}, not a list of file names")
    if len(rel) > MAX_FILES:
        raise IngestError(f"{meta}: relative_file_paths lists {len(rel)} files, more than the limit of {MAX_FILES}")
    files: list[Path] = []
    seen: dict[Path, str] = {}
    for i, entry in enumerate(rel):
        where = f"{meta}: relative_file_paths[{i}] = {entry!r}"
        if not isinstance(entry, str) or not entry.strip():
            raise IngestError(f"{where} is not a file name")
        p, w = PurePosixPath(entry), PureWindowsPath(entry)
        if p.is_absolute() or w.is_absolute() or w.drive or entry.startswith(("/", "\\")):
            raise IngestError(f"{where} is an absolute path (files must lie inside the bag directory)")
        if ".." in p.parts or ".." in w.parts:
            raise IngestError(f"{where} contains '..' (files must lie inside the bag directory)")
        # the rosbags reader opens the entry's file name in the bag directory (older bags
        # wrote "bagname/bagname_0.db3"); MCAP storage is read by this package as written
        f = directory / (p.name if storage == "sqlite3" else p)
        real = f.resolve()
        if not _inside(real, root):
            raise IngestError(f"{where} leads out of the bag directory (a symbolic link to {real})")
        try:
            st = os.stat(f)
        except OSError:
            raise IngestError(f"{where}: the file is missing ({f})") from None
        if not stat.S_ISREG(st.st_mode):
            raise IngestError(f"{where} is not a regular file")
        if real in seen:
            raise IngestError(f"{where} lists the same file as {seen[real]!r} (each file of a bag is listed once)")
        seen[real] = entry
        files.append(f)
    return BagMetadata(directory, storage, tuple(files), tuple(str(x) for x in rel))


def _inside(path: Path, root: Path) -> bool:
    return path == root or root in path.parents
