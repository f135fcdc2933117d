"""Other recording formats as message sources for the same spec, alignment and
provenance: rosbag2 SQLite bags (``.db3``) and ROS 1 ``.bag`` files, read with the
``rosbags`` library (its readers and type stores; message definitions come from the bag,
standard ROS 2 types from the Humble store when a bag does not carry them)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap.records import Message

SUFFIXES = (".bag", ".db3")


def is_rosbags_input(path: Path) -> bool:
    """A ROS 1 ``.bag`` file, a ``.db3`` file, or a rosbag2 directory stored as SQLite."""
    import os

    if path.suffix in SUFFIXES:
        return True
    if path.is_dir() and os.path.lexists(path / "metadata.yaml"):
        from offline_adp.ingest.mcap.bagmeta import read_bag_metadata

        return read_bag_metadata(path).storage == "sqlite3"
    return False


def read_rosbags(path: Path, topics: set[str], report: dict[str, Any]) -> Iterator[Message]:
    """Decoded messages of ``topics`` in file order (rosbag2: storage order; ROS 1: the
    bag's chunk order). ``report`` counts messages read and skipped per topic."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:  # pragma: no cover
        raise IngestError(f"{path}: reading .bag/.db3 needs the rosbags package (pip install rosbags)") from exc
    src = path.parent if path.suffix == ".db3" else path
    if src.is_dir():  # the bag's metadata.yaml is checked before rosbags reads it and the files it lists
        from offline_adp.ingest.mcap.bagmeta import read_bag_metadata

        read_bag_metadata(src)
    report.setdefault("messages", 0)
    report.setdefault("lost_chunks", [])
    skipped = report.setdefault("skipped", {})
    try:
        with AnyReader([src], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            conns = [c for c in reader.connections if c.topic in topics]
            for c in reader.connections:
                if c.topic not in topics:
                    skipped[c.topic] = skipped.get(c.topic, 0) + int(getattr(c, "msgcount", 0) or 0)
            if not conns:
                return
            for conn, t, raw in reader.messages(connections=conns):
                report["messages"] += 1
                yield Message(conn.topic, int(t), int(t), reader.deserialize(raw, conn.msgtype))
    except IngestError:
        raise
    except Exception as exc:  # noqa: BLE001 - rosbags raises many types for unreadable bags
        if type(exc).__module__.startswith("rosbags"):
            raise IngestError(f"{path}: cannot read as a ROS bag ({type(exc).__name__}: {exc})") from exc
        raise
