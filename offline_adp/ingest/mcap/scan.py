"""Record-level scan of an MCAP file with recovery from damage (no index or summary needed)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from offline_adp.errors import IngestError

_MAGIC = b"\x89MCAP0\r\n"


def scan_records(f: Any, topics: set[str] | None, report: dict[str, Any]):
    """(schema, channel, message) of ``topics`` in file order, record by record.

    No index or summary is needed. A chunk that cannot be decompressed or fails its CRC is
    skipped (its offset and time range go to ``report["lost_chunks"]``) and reading goes
    on with the next record; a file that ends inside a record (a crash during recording)
    or whose record framing is broken stops there (``report["lost_from_offset"]``).
    Everything before the damage is kept. ``report["messages"]`` counts the messages read,
    ``report["skipped"]`` the messages of other topics per topic (not decoded).
    """
    import struct
    from io import BytesIO

    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Chunk, Header, Message, Schema
    from mcap.stream_reader import breakup_chunk

    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    report.setdefault("messages", 0)
    report.setdefault("lost_chunks", [])
    skipped = report.setdefault("skipped", {})
    size = f.seek(0, 2)
    f.seek(0)
    if size == 0:
        report["empty"] = True
        return
    if f.read(8) != _MAGIC:
        raise IngestError("not an MCAP file (bad magic bytes)")

    def wanted(records: Any):
        for rec in records:
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
            elif isinstance(rec, Message):
                ch = channels.get(rec.channel_id)
                if ch is not None and (topics is None or ch.topic in topics):
                    report["messages"] += 1
                    yield schemas.get(ch.schema_id), ch, rec
                elif ch is not None:
                    skipped[ch.topic] = skipped.get(ch.topic, 0) + 1

    parsers = {Opcode.SCHEMA: Schema.read, Opcode.CHANNEL: Channel.read}
    while True:
        offset = f.tell()
        head = f.read(9)
        if len(head) < 9:
            if offset < size:
                report.update(lost_from_offset=offset, damaged="the file ends inside a record header")
            elif "data_end" not in report:
                report.update(lost_from_offset=offset, damaged="the file ends without its data-end record")
            return
        opcode, length = struct.unpack("<BQ", head)
        if opcode == Opcode.DATA_END or opcode == Opcode.FOOTER:
            report["data_end"] = True
            return
        if length > size - offset - 9:
            report.update(lost_from_offset=offset, damaged=f"a record of {length} bytes does not fit in the file "
                                                           "(cut short, or its length is corrupt)")
            return
        body = f.read(length)
        stream = ReadDataStream(BytesIO(body))
        if opcode == Opcode.CHUNK:
            try:
                chunk = Chunk.read(stream)
            except Exception as exc:  # noqa: BLE001 - a corrupt chunk header: skip the record
                report["lost_chunks"].append({"offset": offset, "error": f"{type(exc).__name__}: {exc}"})
                continue
            report.setdefault("compression", set()).add(chunk.compression or "none")
            try:
                records = breakup_chunk(chunk, validate_crc=True)
            except Exception as exc:  # noqa: BLE001 - zstd/lz4/CRC errors of many library types
                report["lost_chunks"].append({"offset": offset, "start_ns": int(chunk.message_start_time),
                                              "end_ns": int(chunk.message_end_time),
                                              "error": f"{type(exc).__name__}: {exc}"})
                continue
            yield from wanted(records)
        elif opcode == Opcode.MESSAGE:
            try:
                rec = Message.read(stream, length)
            except Exception as exc:  # noqa: BLE001
                report["lost_chunks"].append({"offset": offset, "error": f"message record: {type(exc).__name__}: {exc}"})
                continue
            yield from wanted([rec])
        elif opcode == Opcode.HEADER:
            try:
                h = Header.read(stream)
                report["header"] = {"profile": h.profile, "library": h.library}
            except Exception as exc:  # noqa: BLE001
                report["lost_chunks"].append({"offset": offset, "error": f"header record: {type(exc).__name__}: {exc}"})
        elif opcode in parsers:
            try:
                yield from wanted([parsers[opcode](stream)])
            except Exception as exc:  # noqa: BLE001
                report["lost_chunks"].append({"offset": offset, "error": f"{type(exc).__name__}: {exc}"})


def damage_text(path: Path, report: dict[str, Any]) -> str | None:
    """The one-line damage report of a file, or None when it read cleanly."""
    parts = []
    if report.get("lost_chunks"):
        offs = ", ".join(str(c["offset"]) for c in report["lost_chunks"][:5])
        parts.append(f"lost {len(report['lost_chunks'])} corrupt chunk(s) at offset(s) {offs} "
                     f"({report['lost_chunks'][0]['error']})")
    if "lost_from_offset" in report:
        parts.append(f"lost from offset {report['lost_from_offset']} ({report['damaged']})")
    if not parts:
        return None
    return f"recovered {report['messages']} messages of file {path}, " + "; ".join(parts)
