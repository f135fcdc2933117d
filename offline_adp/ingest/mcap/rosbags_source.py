"""Other recording formats as message sources for the same spec, alignment and
provenance: rosbag2 SQLite bags (``.db3``) and ROS 1 ``.bag`` files, read with the
``rosbags`` library (its readers and type stores; message definitions come from the bag,
standard ROS 2 types from the Humble store when a bag does not carry them). A ROS 1 bag
whose index is missing (cut short) is read by a record scan (``ros1scan``) instead."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap.records import Message

SUFFIXES = (".bag", ".db3")


@dataclass(frozen=True)
class BagTopic:
    """A connection of a bag as described by ``mcap-info``."""

    topic: str
    msgtype: str
    encoding: str


def is_rosbags_input(path: Path) -> bool:
    """A ROS 1 ``.bag`` file, a ``.db3`` file, or a rosbag2 directory stored as SQLite."""
    import os

    if path.suffix in SUFFIXES:
        return True
    if path.is_dir() and os.path.lexists(path / "metadata.yaml"):
        from offline_adp.ingest.mcap.bagmeta import read_bag_metadata

        return read_bag_metadata(path).storage == "sqlite3"
    return False


def _rosbags() -> tuple[Any, Any, Any]:
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:  # pragma: no cover
        raise IngestError("reading .bag/.db3 needs the rosbags package (pip install rosbags)") from exc
    return AnyReader, Stores, get_typestore


def raw_messages(path: Path, topics: set[str] | None, report: dict[str, Any]
                 ) -> Iterator[tuple[BagTopic, int, bytes, Callable[[bytes, str], Any]]]:
    """(topic, time ns, serialized message, deserializer) of ``topics`` (None: all), in
    the reader's order (rosbag2: storage order; ROS 1: time order, or file order when
    the index is missing and the bag is scanned). ``report`` gets ``messages`` (read),
    ``skipped`` (per other topic), ``bag_topics`` (every connection, with its message
    count when the bag's index gives it) and, for a scanned ROS 1 bag, the damage keys of
    :func:`offline_adp.ingest.mcap.scan.damage_text`."""
    AnyReader, Stores, get_typestore = _rosbags()
    src = path.parent if path.suffix == ".db3" else path
    if src.is_dir():  # the bag's metadata.yaml is checked before rosbags reads it and the files it lists
        from offline_adp.ingest.mcap.bagmeta import read_bag_metadata

        read_bag_metadata(src)
    elif not src.is_file():
        raise IngestError(f"{path}: no such file")
    report.setdefault("messages", 0)
    report.setdefault("lost_chunks", [])
    skipped = report.setdefault("skipped", {})
    bag_topics = report.setdefault("bag_topics", {})
    try:
        reader = AnyReader([src], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises many types for unreadable bags
        if not _unreadable(exc):
            raise
        if path.suffix == ".bag" and path.is_file() and _ros1_magic(path):  # no usable index: scan the records
            yield from _scan_ros1_bag(path, topics, report)
            return
        raise IngestError(f"{path}: cannot read as a ROS bag ({type(exc).__name__}: {exc})") from None
    try:
        ros1 = not reader.is2
        for c in reader.connections:
            enc = "ros1" if ros1 else getattr(getattr(c, "ext", None), "serialization_format", "cdr")
            bt = BagTopic(c.topic, c.msgtype, enc)
            n = int(getattr(c, "msgcount", 0) or 0)
            bag_topics[bt] = bag_topics.get(bt, 0) + n
            if topics is not None and c.topic not in topics:
                skipped[c.topic] = skipped.get(c.topic, 0) + n
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        if not conns:
            return
        by_conn = {id(c): BagTopic(c.topic, c.msgtype, "ros1" if ros1 else
                                   getattr(getattr(c, "ext", None), "serialization_format", "cdr")) for c in conns}
        for conn, t, raw in reader.messages(connections=conns):
            report["messages"] += 1
            yield by_conn[id(conn)], int(t), raw, reader.deserialize
    except IngestError:
        raise
    except Exception as exc:  # noqa: BLE001
        if _unreadable(exc):
            raise IngestError(f"{path}: cannot read as a ROS bag ({type(exc).__name__}: {exc})") from None
        raise
    finally:
        reader.close()


def _unreadable(exc: Exception) -> bool:
    """An error that says the bag's bytes are damaged, not that our code is wrong: rosbags'
    own, and what its readers let through from a corrupt file (a damaged SQLite database,
    undecodable text, a short struct)."""
    import sqlite3
    import struct

    return (type(exc).__module__.startswith("rosbags")
            or isinstance(exc, sqlite3.Error | UnicodeDecodeError | struct.error | EOFError))


def _ros1_magic(path: Path) -> bool:
    from offline_adp.ingest.mcap.ros1scan import MAGIC

    try:
        with open(path, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def _scan_ros1_bag(path: Path, topics: set[str] | None, report: dict[str, Any]
                   ) -> Iterator[tuple[BagTopic, int, bytes, Callable[[bytes, str], Any]]]:
    """A ROS 1 bag without its index, record by record; types from each connection's
    message definition, deserialized as rosbags' AnyReader does."""
    from rosbags.typesys import Stores, get_typestore
    from rosbags.typesys.msg import get_types_from_msg

    from offline_adp.ingest.mcap.ros1scan import scan_ros1

    store = get_typestore(Stores.EMPTY)
    known: dict[int, BagTopic] = {}
    skipped = report["skipped"]
    bag_topics = report["bag_topics"]

    def deserialize(raw: bytes, msgtype: str) -> Any:
        return store.deserialize_ros1(raw, msgtype)

    with open(path, "rb") as f:
        for c, t, raw in scan_ros1(f, report):
            bt = known.get(c.id)
            if bt is None or bt.msgtype != c.msgtype:
                bt = known[c.id] = BagTopic(c.topic, c.msgtype, "ros1")
                bag_topics.setdefault(bt, 0)
                if c.msgtype not in store.fielddefs:
                    try:
                        store.register(get_types_from_msg(c.msgdef, c.msgtype))
                    except Exception as exc:  # noqa: BLE001 - a definition rosbags cannot parse
                        raise IngestError(f"{path}: topic {c.topic!r}: message definition of {c.msgtype} not "
                                          f"readable ({type(exc).__name__}: {exc})") from None
            bag_topics[bt] += 1
            if topics is not None and c.topic not in topics:
                skipped[c.topic] = skipped.get(c.topic, 0) + 1
                report["messages"] -= 1
                continue
            yield bt, t, raw, deserialize


def read_rosbags(path: Path, topics: set[str], report: dict[str, Any]) -> Iterator[Message]:
    """Decoded messages of ``topics`` in the reader's order (see :func:`raw_messages`).
    ``report`` counts messages read and skipped per topic."""
    for bt, t, raw, deserialize in raw_messages(path, topics, report):
        yield Message(bt.topic, t, t, deserialize(raw, bt.msgtype))
