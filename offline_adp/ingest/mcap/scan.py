"""Record-level scan of an MCAP file with recovery from damage (no index or summary needed)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from offline_adp.errors import IngestError, InvalidArgumentError

_MAGIC = b"\x89MCAP0\r\n"


MAX_RECORD_BYTES = 1 << 30  # largest record (or chunk, uncompressed) read; larger ones are damage
MAX_CHANNELS = 65535  # channel and schema ids are 16-bit in MCAP


def _lost_in(opcode: int, body_start: bytes) -> int | None:
    """Messages lost in a record cut short: 1 for a message, None (unknown) for a chunk, else 0."""
    from mcap.opcode import Opcode

    if opcode == Opcode.MESSAGE:
        return 1
    if opcode == Opcode.CHUNK:
        return None
    return 0


def scan_records(f: Any, topics: set[str] | None, report: dict[str, Any], *,
                 max_record_bytes: int = MAX_RECORD_BYTES, max_channels: int = MAX_CHANNELS):
    """(schema, channel, message) of ``topics`` in file order, record by record.

    No index or summary is needed. A chunk that cannot be decompressed or fails its CRC is
    skipped (its offset and time range go to ``report["lost_chunks"]``) and reading goes
    on with the next record; a file that ends inside a record (a crash during recording)
    or whose record framing is broken stops there (``report["lost_from_offset"]``).
    Everything before the damage is kept. ``report["messages_lost"]`` says how many
    messages the cut cost (0, 1, or None: unknown, a chunk). Record lengths are checked
    against the file size and ``max_record_bytes``, a chunk's declared uncompressed size
    against ``max_record_bytes`` and 1024 x its compressed size, before anything is
    allocated; more than ``max_channels`` channels or schemas is an error.
    ``report["messages"]`` counts the messages read,
    ``report["skipped"]`` the messages of other topics per topic (not decoded).
    """
    import struct
    from io import BytesIO

    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Chunk, Header, Message, Schema
    from mcap.stream_reader import breakup_chunk

    schemas: dict[int, Any] = report.setdefault("schemas", {})
    channels: dict[int, Any] = report.setdefault("channels", {})
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
                if len(schemas) > max_channels:
                    raise IngestError(f"more than {max_channels} schemas (a corrupt or hostile file?)")
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
                if len(channels) > max_channels:
                    raise IngestError(f"more than {max_channels} channels (a corrupt or hostile file?)")
            elif isinstance(rec, Message):
                if not (0 <= rec.log_time < 1 << 63 and 0 <= rec.publish_time < 1 << 63):
                    raise IngestError(f"a message on channel {rec.channel_id} has log_time {rec.log_time} / "
                                      f"publish_time {rec.publish_time} ns, beyond the int64 range (a corrupt record?)")
                ch = channels.get(rec.channel_id)
                if ch is not None and (topics is None or ch.topic in topics):
                    report["messages"] += 1
                    yield schemas.get(ch.schema_id), ch, rec
                elif ch is not None:
                    skipped[ch.topic] = skipped.get(ch.topic, 0) + 1

    parsers = {Opcode.SCHEMA: Schema.read, Opcode.CHANNEL: Channel.read}
    lost = report["lost_chunks"]
    indexed: dict[str, Any] | None = None  # the lost chunk whose message-index records may follow
    n_lost, prev_op = 0, None
    while True:
        # message-index records directly after a lost chunk say what it held (its messages' log times)
        if len(lost) > n_lost:
            indexed = lost[-1] if prev_op == Opcode.CHUNK else None
        elif prev_op != Opcode.MESSAGE_INDEX:
            indexed = None
        n_lost = len(lost)
        offset = f.tell()
        head = f.read(9)
        if len(head) < 9:
            if offset < size:
                report.update(lost_from_offset=offset, damaged="the file ends inside a record header",
                              messages_lost=_lost_in(head[0], b"") if head else 0)
            elif "data_end" not in report:
                report.update(lost_from_offset=offset, damaged="the file ends without its data-end record",
                              messages_lost=0)
            return
        opcode, length = struct.unpack("<BQ", head)
        prev_op = opcode
        if opcode == Opcode.DATA_END or opcode == Opcode.FOOTER:
            report["data_end"] = True
            return
        if length > size - offset - 9:
            report.update(lost_from_offset=offset, damaged=f"a record of {length} bytes does not fit in the file "
                                                           "(cut short, or its length is corrupt)",
                          messages_lost=_lost_in(opcode, f.read(16)))
            return
        if length > max_record_bytes:
            report.update(lost_from_offset=offset, damaged=f"a record of {length} bytes is larger than the limit "
                                                           f"of {max_record_bytes} bytes", messages_lost=None)
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
            limit = min(max_record_bytes, len(chunk.data) if not chunk.compression else 1024 * len(chunk.data) + 65536)
            if chunk.uncompressed_size > limit:  # declared sizes are untrusted: check before allocating
                report["lost_chunks"].append({"offset": offset, "start_ns": int(chunk.message_start_time),
                                              "end_ns": int(chunk.message_end_time),
                                              "error": f"declares {chunk.uncompressed_size} bytes uncompressed from "
                                                       f"{len(chunk.data)} ({chunk.compression or 'none'}), more than "
                                                       f"the limit of {limit}"})
                continue
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
                report["lost_chunks"].append({"offset": offset,
                                              "error": f"message record: {type(exc).__name__}: {exc}"})
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
        elif opcode == Opcode.MESSAGE_INDEX and indexed is not None:
            _index_of_lost_chunk(indexed, body)


def _index_of_lost_chunk(chunk: dict[str, Any], body: bytes) -> None:
    """Add one message-index record (a channel's messages in the chunk: log time, offset)
    to ``chunk["_index"]`` (channel id -> log times). These uncompressed records follow the
    chunk in an indexed file, so they survive damage to its compressed data; a malformed
    one is ignored (``chunk["_index_damaged"]``)."""
    import struct

    try:
        channel_id, n = struct.unpack_from("<HI", body, 0)
        if n % 16 or 6 + n > len(body):
            raise InvalidArgumentError("bad records length")
        import numpy as np

        times = np.frombuffer(body, dtype="<u8", count=n // 8, offset=6)[0::2].astype(np.int64)
    except Exception:  # noqa: BLE001 - a damaged index only makes the accounting unknown
        chunk["_index_damaged"] = True
        return
    chunk.setdefault("_index", {}).setdefault(int(channel_id), []).extend(times.tolist())


def damage_text(path: Path, report: dict[str, Any]) -> str | None:
    """The one-line damage report of a file, or None when it read cleanly."""
    parts = []
    chunks = [c for c in report.get("lost_chunks", ()) if not c.get("message")]
    bad = [c for c in report.get("lost_chunks", ()) if c.get("message")]  # undecodable messages (quarantine)
    if chunks:
        offs = ", ".join(str(c["offset"]) for c in chunks[:5])
        parts.append(f"lost {len(chunks)} corrupt chunk(s) at offset(s) {offs} ({chunks[0]['error']})")
    if bad:
        parts.append(f"{len(bad)} message(s) that do not decode, their episodes set aside (first: {bad[0]['error']})")
    if "lost_from_offset" in report:
        n = report.get("messages_lost")
        lost = ("an unknown number of messages lost" if n is None else "no message lost" if n == 0
                else f"{n} message(s) lost")
        parts.append(f"cut at offset {report['lost_from_offset']} ({report['damaged']}; {lost})")
    if not parts:
        return None
    return f"recovered {report['messages']} messages of file {path}, " + "; ".join(parts)
