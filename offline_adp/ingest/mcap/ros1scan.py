"""Record scan of a ROS 1 bag (format 2.0) that needs no index: how a bag cut short
(a crash during recording: its index, written last, is missing) is recovered.

The rosbags reader needs the index at the end of the file; this scan reads the records
from the start instead: the bag header, chunk records (uncompressed, bz2 or lz4) holding
connection and message-data records, and connection / message-data records outside
chunks. It stops at the first record that does not fit in the file (the cut) and says
where (``report["lost_from_offset"]``); a chunk that cannot be decompressed is skipped and
counted (``report["lost_chunks"]``). Every length is checked against the file size (and
a chunk's declared uncompressed size against a limit and its compressed size) before
anything is allocated. Messages come in file order with their connection's topic,
type (normalized as rosbags does: ``pkg/msg/Name``) and message definition.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from offline_adp.errors import IngestError, InvalidArgumentError

MAGIC = b"#ROSBAG V2.0\n"
MAX_HEADER_BYTES = 1 << 24  # a record header (connection headers carry message definitions)
MAX_RECORD_BYTES = 1 << 30  # a record's data, or a chunk uncompressed
MAX_CONNECTIONS = 1 << 16
OP_MSG, OP_BAG_HEADER, OP_INDEX, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = 0x02, 0x03, 0x04, 0x05, 0x06, 0x07


@dataclass(frozen=True)
class Ros1Connection:
    id: int
    topic: str
    msgtype: str
    msgdef: str
    md5sum: str


def _fields(buf: bytes | memoryview) -> dict[str, bytes]:
    """The ``name=value`` fields of a record header (each prefixed by its uint32 length)."""
    out: dict[str, bytes] = {}
    pos, n = 0, len(buf)
    while pos < n:
        if pos + 4 > n:
            raise InvalidArgumentError("a header field length runs past the header")
        size = struct.unpack_from("<I", buf, pos)[0]
        pos += 4
        if size > n - pos:
            raise InvalidArgumentError(f"a header field of {size} bytes runs past the header")
        name, sep, value = bytes(buf[pos:pos + size]).partition(b"=")
        if not sep:
            raise InvalidArgumentError("a header field without '='")
        out[name.decode("utf-8", "replace")] = value
        pos += size
    return out


def _u32(h: dict[str, bytes], k: str) -> int:
    v = h.get(k)
    if v is None or len(v) != 4:
        raise InvalidArgumentError(f"header field {k!r} missing or not 4 bytes")
    return struct.unpack("<I", v)[0]


def _time(h: dict[str, bytes], k: str) -> int:
    v = h.get(k)
    if v is None or len(v) != 8:
        raise InvalidArgumentError(f"header field {k!r} missing or not 8 bytes")
    sec, nsec = struct.unpack("<II", v)
    return sec * 1_000_000_000 + nsec


def _decompress(kind: str, data: bytes, size: int) -> bytes:
    if kind == "none":
        out = data
    elif kind == "bz2":
        import bz2

        out = bz2.BZ2Decompressor().decompress(data, max_length=size + 1)
    elif kind == "lz4":
        import lz4.frame

        out = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=size + 1)
    else:
        raise InvalidArgumentError(f"compression {kind!r} is not supported")
    if len(out) != size:
        raise InvalidArgumentError(f"chunk declares {size} bytes uncompressed, holds {len(out)}")
    return out


def scan_ros1(f: Any, report: dict[str, Any]) -> Iterator[tuple[Ros1Connection, int, bytes]]:
    """(connection, time ns, serialized message) of every message record, in file order."""
    from rosbags.typesys.msg import normalize_msgtype

    conns: dict[int, Ros1Connection] = report.setdefault("ros1_connections", {})
    report.setdefault("messages", 0)
    report.setdefault("lost_chunks", [])
    size = f.seek(0, 2)
    f.seek(0)
    if size == 0:
        report["empty"] = True
        return
    if f.read(len(MAGIC)) != MAGIC:
        raise IngestError("not a ROS 1 bag of format 2.0 (bad magic line)")

    def records(buf: memoryview, base: int, limit_hdr: int) -> Iterator[tuple[int, int, dict[str, bytes], memoryview]]:
        """(offset, op, header, data) of the records in an in-memory buffer (a chunk)."""
        pos, n = 0, len(buf)
        while pos < n:
            if pos + 4 > n:
                raise InvalidArgumentError(f"a record header length runs past the chunk at offset {base + pos}")
            hl = struct.unpack_from("<I", buf, pos)[0]
            if hl > min(limit_hdr, n - pos - 8):
                raise InvalidArgumentError(f"a record header of {hl} bytes does not fit in the chunk at offset "
                                           f"{base + pos}")
            h = _fields(buf[pos + 4:pos + 4 + hl])
            dl = struct.unpack_from("<I", buf, pos + 4 + hl)[0]
            start = pos + 8 + hl
            if dl > n - start:
                raise InvalidArgumentError(f"a record of {dl} bytes does not fit in the chunk at offset {base + pos}")
            yield base + pos, _op(h), h, buf[start:start + dl]
            pos = start + dl

    def _op(h: dict[str, bytes]) -> int:
        v = h.get("op")
        if v is None or len(v) != 1:
            raise InvalidArgumentError("a record without its op field")
        return v[0]

    def handle(op: int, h: dict[str, bytes], data: memoryview | bytes) -> Iterator[tuple[Ros1Connection, int, bytes]]:
        if op == OP_CONNECTION:
            cid = _u32(h, "conn")
            if cid not in conns and len(conns) >= MAX_CONNECTIONS:
                raise IngestError(f"more than {MAX_CONNECTIONS} connections (a corrupt or hostile file?)")
            topic = h.get("topic", b"").decode("utf-8", "replace")
            d = _fields(data)
            typ = d.get("type", b"").decode("utf-8", "replace")
            conns[cid] = Ros1Connection(cid, "/" * topic.startswith("/") + "/".join(x for x in topic.split("/") if x),
                                        normalize_msgtype(typ) if typ else "",
                                        d.get("message_definition", b"").decode("utf-8", "replace"),
                                        d.get("md5sum", b"").decode("ascii", "replace"))
        elif op == OP_MSG:
            cid = _u32(h, "conn")
            c = conns.get(cid)
            if c is None:
                raise InvalidArgumentError(f"a message of connection {cid} before its connection record")
            report["messages"] += 1
            yield c, _time(h, "time"), bytes(data)

    while True:
        offset = f.tell()
        head = f.read(4)
        if len(head) < 4:
            if offset < size:
                report.update(lost_from_offset=offset, damaged="the file ends inside a record header",
                              messages_lost=None)
            elif "index_seen" not in report:
                report.update(lost_from_offset=offset, damaged="the file ends without its index (cut short)",
                              messages_lost=0)
            return
        hl = struct.unpack("<I", head)[0]
        if hl > min(MAX_HEADER_BYTES, size - offset - 8):
            report.update(lost_from_offset=offset, damaged=f"a record header of {hl} bytes does not fit in the file "
                                                           "(cut short, or its length is corrupt)", messages_lost=None)
            return
        hbytes = f.read(hl)
        dlb = f.read(4)
        try:
            h = _fields(hbytes)
            op = _op(h)
        except ValueError as exc:
            report.update(lost_from_offset=offset, damaged=f"a corrupt record header ({exc})", messages_lost=None)
            return
        dl = struct.unpack("<I", dlb)[0]
        if dl > size - f.tell():
            report.update(lost_from_offset=offset, damaged=f"a record of {dl} bytes does not fit in the file "
                                                           "(cut short, or its length is corrupt)",
                          messages_lost=1 if op == OP_MSG else None if op == OP_CHUNK else 0)
            return
        if op in (OP_BAG_HEADER, OP_INDEX, OP_CHUNK_INFO):
            if op == OP_CHUNK_INFO:  # the index's chunk records come last: the bag was closed
                report["index_seen"] = True
            f.seek(dl, 1)
            continue
        if dl > MAX_RECORD_BYTES:
            report.update(lost_from_offset=offset, damaged=f"a record of {dl} bytes is larger than the limit of "
                                                           f"{MAX_RECORD_BYTES} bytes", messages_lost=None)
            return
        data = f.read(dl)
        if op == OP_CHUNK:
            try:
                kind = h.get("compression", b"").decode("ascii", "replace")
                usize = _u32(h, "size")
                limit = min(MAX_RECORD_BYTES, dl if kind == "none" else 1024 * dl + 65536)
                if usize > limit:
                    raise InvalidArgumentError(f"declares {usize} bytes uncompressed from {dl} ({kind}), more "
                                               f"than the limit of {limit}")
                inner = list(records(memoryview(_decompress(kind, data, usize)), offset, MAX_HEADER_BYTES))
            except Exception as exc:  # noqa: BLE001 - bz2/lz4/framing errors of several types
                report["lost_chunks"].append({"offset": offset, "error": f"{type(exc).__name__}: {exc}"})
                continue
            report.setdefault("compression", set()).add(kind)
            for _, iop, ih, idata in inner:
                try:
                    yield from handle(iop, ih, idata)
                except ValueError as exc:
                    report["lost_chunks"].append({"offset": offset, "error": f"ValueError: {exc}"})
                    break
        else:
            try:
                yield from handle(op, h, data)
            except ValueError as exc:
                report["lost_chunks"].append({"offset": offset, "error": f"ValueError: {exc}"})
