"""``mcap-info``: what a file holds, per topic."""

from __future__ import annotations

import contextlib
from os import PathLike
from pathlib import Path
from typing import Any

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap.decode import _Decoders, _open_reader, _safe_decoded, field_paths
from offline_adp.ingest.mcap.scan import _MAGIC, damage_text, scan_records


def mcap_info(path: str | PathLike[str]) -> dict[str, Any]:
    """Profile, library, summary/index presence, compression, time range, and per topic:
    schema, encoding, count, rate and the field paths of the first decodable message.

    Files without a summary, or whose summary cannot be read (a crashed recording), are
    scanned record by record instead; the result then says what was recovered and lost.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            size = f.seek(0, 2)
            f.seek(max(size - 8, 0))
            if size < 16 or f.read(8) != _MAGIC:  # no closing magic: cut short; the library would guess a summary
                return _scan_info(path)
            f.seek(0)
            reader = _open_reader(f)
            header = reader.get_header()
            summary = reader.get_summary()
        if summary is None or summary.statistics is None:
            return _scan_info(path)
    except IngestError:
        raise
    except Exception:  # noqa: BLE001 - no readable summary: fall back to the record scan
        return _scan_info(path)
    try:
        info: dict[str, Any] = {"file": str(path), "profile": header.profile, "library": header.library,
                                "summary": True, "topics": {}}
        st = summary.statistics
        info["indexed"] = bool(summary.chunk_indexes)
        info["compression"] = sorted({c.compression or "none" for c in summary.chunk_indexes})
        info["time_range_ns"] = [st.message_start_time, st.message_end_time]
        dur = max((st.message_end_time - st.message_start_time) / 1e9, 1e-9)
        for cid, ch in summary.channels.items():
            sch = summary.schemas.get(ch.schema_id)
            n = st.channel_message_counts.get(cid, 0)
            info["topics"][ch.topic] = {"schema": sch.name if sch else "", "encoding": ch.message_encoding,
                                        "messages": n, "rate_hz": round(n / dur, 3), "fields": None}
        with open(path, "rb") as f:
            reader = _open_reader(f)
            pending = set(info["topics"])
            for sch, ch, _msg, dec in _safe_decoded(reader, None):
                t = info["topics"].setdefault(ch.topic, {"schema": sch.name if sch else "", "encoding": ch.message_encoding,
                                                         "messages": None, "rate_hz": None, "fields": None})
                if t["fields"] is None:
                    t["fields"] = field_paths(dec)
                    pending.discard(ch.topic)
                    if not pending:
                        break
    except Exception as exc:  # noqa: BLE001 - any library error becomes ours, naming the file
        raise IngestError(f"{path}: cannot read as MCAP ({type(exc).__name__}: {exc})") from exc
    return info


def _scan_info(path: Path) -> dict[str, Any]:
    """``mcap_info`` by a record scan: counts, time range and rates from the messages."""
    report: dict[str, Any] = {}
    topics: dict[str, dict[str, Any]] = {}
    lo = hi = None
    decoders = _Decoders()
    try:
        with open(path, "rb") as f:
            for sch, ch, msg in scan_records(f, None, report):
                t = topics.get(ch.topic)
                if t is None:
                    t = topics[ch.topic] = {"schema": sch.name if sch else "", "encoding": ch.message_encoding,
                                            "messages": 0, "rate_hz": None, "fields": None}
                t["messages"] += 1
                lo = msg.log_time if lo is None else min(lo, msg.log_time)
                hi = msg.log_time if hi is None else max(hi, msg.log_time)
                if t["fields"] is None and (dec := decoders(sch, ch)) is not None:
                    with contextlib.suppress(Exception):  # an undecodable first message leaves fields unknown
                        t["fields"] = field_paths(dec(msg.data))
    except IngestError as exc:
        raise IngestError(f"{path}: cannot read as MCAP ({exc})") from None
    except Exception as exc:  # noqa: BLE001
        raise IngestError(f"{path}: cannot read as MCAP ({type(exc).__name__}: {exc})") from exc
    dur = max(((hi or 0) - (lo or 0)) / 1e9, 1e-9)
    for t in topics.values():
        t["rate_hz"] = round(t["messages"] / dur, 3)
    head = report.get("header", {})
    info = {"file": str(path), "profile": head.get("profile", ""), "library": head.get("library", ""), "summary": False,
            "indexed": False, "compression": sorted(report.get("compression", set())), "topics": topics,
            "scanned": True, **({"time_range_ns": [lo, hi]} if lo is not None else {})}
    text = damage_text(path, report)
    if text:
        info["damage"] = text
    return info
