"""``mcap-info``: what a file holds, per topic, from a record scan (no index or summary
needed, damage shown, nothing refused that can be read)."""

from __future__ import annotations

from array import array
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap.decode import _ABSENT, _Decoders, _key_of, field_values, get_path
from offline_adp.ingest.mcap.scan import damage_text, scan_records

RESTART_S = 1.0  # a topic's log_time jumping back more than this starts a new epoch (as [episodes] restart)
LIST_MESSAGES = 2000  # messages per topic decoded for the values of its lists' string fields
MAX_PERIODS = 1_000_000  # periods kept per topic for the median (then every other one)


class _Topic:
    """Running statistics of one topic: count, epochs, periods within epochs."""

    def __init__(self) -> None:
        self.n = 0
        self.last: int | None = None
        self.restarts = 0
        self.periods = array("q")
        self.stride = 1
        self.first_fields: list[dict[str, Any]] | None = None
        self.error: str | None = None
        self.first: int | None = None
        self.long: list[tuple[int, int]] = []  # (time before, length) of the first periods over 1 s
        # per (list, string field of its elements), e.g. ("transforms", "child_frame_id"): in how many
        # messages each value appears (the first LIST_MESSAGES messages)
        self.lists: dict[tuple[str, str], dict[str, int]] = {}
        self.quaternions: list[str] = []
        self.list_messages = 0
        self.firsts: dict[tuple[str, str], set[str]] = {}  # the values of element [0]
        self.repeated: dict[tuple[str, str], set[str]] = {}  # values found twice in one message

    def set_first(self, decoded: Any) -> None:
        """Field paths, types and samples of the first decodable message; its lists of records."""
        self.first_fields = [{"path": p, "type": _type_name(v), "sample": _sample(v)}
                             for p, v in field_values(decoded)]
        paths = {x["path"] for x in self.first_fields if x["type"] in ("float", "int")}
        #: quaternions (x, y, z, w under one path): a heading is read with { yaw_of = path }
        self.quaternions = [p[:-2] for p in sorted(paths) if p.endswith(".w")
                            and all(p[:-1] + c in paths for c in "xyz")]
        for x in self.first_fields:
            head, _, key = x["path"].partition("[0].")
            if key and x["type"] == "string" and "." not in key and "[" not in key and "[0]" not in head:
                self.lists[(head, key)] = {}
        self.count_lists(decoded)

    def count_lists(self, decoded: Any) -> None:
        """Count the values of the lists' string fields in one more message (up to LIST_MESSAGES)."""
        if not self.lists or self.list_messages >= LIST_MESSAGES:
            return
        self.list_messages += 1
        for (head, key), counts in self.lists.items():
            try:
                values = [str(v) for el in get_path(decoded, head) if (v := _key_of(el, key)) is not _ABSENT]
            except Exception:  # noqa: BLE001 - a message without that list: nothing to count
                continue
            if values:
                self.firsts.setdefault((head, key), set()).add(values[0])
            if len(set(values)) < len(values):  # a value twice in one message: no selector picks one element
                self.repeated.setdefault((head, key), set()).update(v for v in values if values.count(v) > 1)
            for v in list(dict.fromkeys(values))[:64]:
                if v in counts or len(counts) < 64:
                    counts[v] = counts.get(v, 0) + 1

    def selectable(self) -> dict[str, dict[str, int]]:
        """The lists whose first element differs from message to message (``transforms[0]`` is
        not one thing): ``transforms[].child_frame_id`` -> {value: messages holding it}, most
        frequent first."""
        out = {}
        for (head, key), counts in self.lists.items():
            if len(self.firsts.get((head, key), ())) >= 2:
                out[f"{head}[].{key}"] = dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))
        return out

    def repeated_values(self) -> dict[str, list[str]]:
        """Of :meth:`selectable`'s lists: the values some message holds twice (a selector on
        them would match two elements)."""
        return {f"{h}[].{k}": sorted(self.repeated[(h, k)]) for h, k in self.lists
                if (h, k) in self.repeated and len(self.firsts.get((h, k), ())) >= 2}

    def add(self, t: int) -> None:
        self.n += 1
        self.first = t if self.first is None else self.first
        if self.last is not None:
            d = t - self.last
            if d > 1e9 and len(self.long) < 64:  # a gap is over 1 s: where the first ones are, for the user
                self.long.append((self.last, d))
            if d < -RESTART_S * 1e9:
                self.restarts += 1
            elif d > 0 and self.n % self.stride == 0:
                self.periods.append(d)
                if len(self.periods) >= MAX_PERIODS:
                    self.periods = self.periods[::2]
                    self.stride *= 2
        self.last = t if self.last is None or t > self.last or t < self.last - RESTART_S * 1e9 else self.last

    def rate(self) -> dict[str, Any]:
        """Rate as the median period within epochs; gaps (periods > 5 x median and 1 s) counted."""
        if self.n == 0:
            return {"rate_hz": None, "status": "empty"}
        p = np.frombuffer(self.periods, dtype=np.int64) if len(self.periods) else np.zeros(0, np.int64)
        if not len(p):
            return {"rate_hz": None, "restarts": self.restarts, "gaps": 0,
                    "status": "1 message" if self.n == 1 else "no period (all messages at one time)"}
        med = float(np.median(p))
        gap = max(5 * med, 1e9)
        gaps = int((p > gap).sum()) * self.stride
        med = float(np.median(p[p <= gap])) if (p <= gap).any() else med
        first = self.first if self.first is not None else 0
        at = [{"after_s": round((t0 - first) / 1e9, 3), "length_s": round(d / 1e9, 3)}
              for t0, d in self.long if d > gap][:3]  # seconds after the topic's first message
        return {"rate_hz": round(1e9 / med, 3), "restarts": self.restarts, "gaps": gaps,
                **({"gaps_at": at} if gaps else {}), "status": "ok"}


def _type_name(v: Any) -> str:
    if isinstance(v, bool | np.bool_):
        return "bool"
    if isinstance(v, int | np.integer):
        return "int"
    if isinstance(v, float | np.floating):
        return "float"
    if isinstance(v, str):
        return "string"
    if isinstance(v, bytes | bytearray):
        return "bytes"
    return "null" if v is None else type(v).__name__


def _sample(v: Any) -> Any:
    if isinstance(v, bytes | bytearray):
        return f"<{len(v)} bytes>"
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, str) and len(v) > 60:
        return v[:57] + "..."
    return v


def mcap_info(path: str | PathLike[str]) -> dict[str, Any]:
    """Describe an MCAP file by scanning its records.

    Returns the profile and library, whether it has a summary, its compression, time
    range and damage (corrupt chunks, a cut, with the messages lost), and per topic:
    schema, encoding, message count, rate (median period per epoch, Hz) with the time
    restarts and gaps counted, ``status`` (``ok``, ``empty``, ``1 message``, or why it
    cannot be decoded), the field paths (``fields``) and per field its type and a sample
    value (``field_info``) from the first decodable message. A channel whose schema no
    decoder can parse is listed with the reason; the rest of the file is described.

    Every input ``ingest`` reads is described: a ROS 1 ``.bag``, a rosbag2 bag directory
    (SQLite or MCAP storage) or one of its ``.db3`` parts (the bag it belongs to) are read
    with rosbags (:func:`rosbag_info`); a ROS 1 bag cut short is scanned record by record.

    Raises
    ------
    IngestError
        Only when the file cannot be read at all (missing, not MCAP or a ROS bag, a
        ``.db3`` part without its bag's ``metadata.yaml``, a refused ``metadata.yaml``).
    """
    path = Path(path)
    if path.is_dir() or path.suffix in (".bag", ".db3"):
        return rosbag_info(path)
    if not path.is_file():
        raise IngestError(f"{path}: no such file")
    report: dict[str, Any] = {}
    topics: dict[int, _Topic] = {}
    decoders = _Decoders()
    lo = hi = None
    try:
        with open(path, "rb") as f:
            for sch, ch, msg in scan_records(f, None, report):
                t = topics.get(ch.id)
                if t is None:
                    t = topics[ch.id] = _Topic()
                lt = int(msg.log_time)
                t.add(lt)
                lo = lt if lo is None else min(lo, lt)
                hi = lt if hi is None else max(hi, lt)
                if t.first_fields is None and t.error is None:
                    try:
                        dec = decoders(sch, ch)
                        if dec is None:
                            t.error = (f"no installed decoder reads message encoding {ch.message_encoding!r} "
                                       f"(schema encoding {getattr(sch, 'encoding', '')!r})")
                        else:
                            t.set_first(dec(msg.data))
                    except IngestError as exc:
                        t.error = str(exc)
                    except Exception as exc:  # noqa: BLE001 - a message its decoder cannot read
                        t.error = f"first message not decodable ({type(exc).__name__}: {exc})"
                elif t.lists and t.list_messages < LIST_MESSAGES:
                    try:
                        t.count_lists(decoders(sch, ch)(msg.data))
                    except Exception:  # noqa: BLE001 - a later message that does not decode: not counted
                        pass
    except IngestError as exc:
        raise IngestError(f"{path}: cannot read as MCAP ({exc})") from None
    except OSError as exc:
        raise IngestError(f"{path}: cannot read ({exc})") from exc
    out_topics: dict[str, Any] = {}
    for cid, ch in sorted(report.get("channels", {}).items()):
        sch = report.get("schemas", {}).get(ch.schema_id)
        t = topics.get(cid, _Topic())
        entry = {"schema": sch.name if sch else "", "encoding": ch.message_encoding, "messages": t.n, **t.rate(),
                 "fields": [x["path"] for x in t.first_fields] if t.first_fields else None,
                 "field_info": t.first_fields, "list_values": t.selectable(),
                 "list_values_repeated": t.repeated_values(),
                 "quaternions": t.quaternions}
        if t.error:
            entry["status"] = "not decodable: " + t.error
        key = ch.topic if ch.topic not in out_topics else f"{ch.topic} (channel {cid})"
        out_topics[key] = entry
    head = report.get("header", {})
    info: dict[str, Any] = {"file": str(path), "profile": head.get("profile", ""), "library": head.get("library", ""),
                            "summary": _has_summary(path), "compression": sorted(report.get("compression", set())),
                            "topics": out_topics, "scanned": True, "messages": report.get("messages", 0)}
    info["indexed"] = info["summary"]
    return _with_range_and_damage(info, path, report, lo, hi)


def info_inputs(files: list[str | PathLike[str]]) -> list[Path]:
    """What ``mcap-info FILES`` describes, in order, each once: MCAP files; an MCAP bag
    directory part by part (each part's damage shown); a ROS 1 bag; a SQLite bag (its
    directory, or any of its ``.db3`` parts) as the bag."""
    from offline_adp.ingest.mcap.rosbags_source import is_rosbags_input
    from offline_adp.ingest.mcap.sources import bag_files, rosbag2_directory

    out: list[Path] = []
    seen: set[Path] = set()
    for f in files:
        p = Path(f)
        bag = rosbag2_directory(p) if p.suffix == ".db3" or p.is_dir() else None
        items = [p] if bag is None else [bag] if is_rosbags_input(bag) else bag_files(bag)
        for q in items:
            if q.resolve() not in seen:
                seen.add(q.resolve())
                out.append(q)
    return out


def rosbag_info(path: str | PathLike[str]) -> dict[str, Any]:
    """:func:`mcap_info` of a ROS bag: a ROS 1 ``.bag``, a rosbag2 bag directory, or a
    ``.db3`` part (its bag, which its ``metadata.yaml`` must list). Same keys; per topic
    the message type as ``schema`` and the serialization as ``encoding``; ``profile`` is
    ``ros1`` or ``ros2``, ``library`` the storage, ``indexed`` whether the reader had the
    bag's index (a ROS 1 bag without it is scanned, its damage shown)."""
    from offline_adp.ingest.mcap.rosbags_source import BagTopic, raw_messages
    from offline_adp.ingest.mcap.sources import rosbag2_directory

    path = Path(path)
    bag = rosbag2_directory(path) if path.suffix == ".db3" or path.is_dir() else path
    assert bag is not None
    if not bag.exists():
        raise IngestError(f"{path}: no such file")
    storage = "rosbag1"
    if bag.is_dir():
        import os

        from offline_adp.ingest.mcap.bagmeta import read_bag_metadata

        if not os.path.lexists(bag / "metadata.yaml"):
            from offline_adp.ingest.mcap.sources import bag_files

            files = bag_files(bag)  # *.mcap parts without metadata: described one by one (mcap_info)
            raise IngestError(f"{bag}: a directory of {len(files)} MCAP file(s) without metadata.yaml; describe each "
                              f"part (offline-adp mcap-info {bag}/*.mcap)")
        storage = read_bag_metadata(bag).storage or "mcap"
    report: dict[str, Any] = {}
    topics: dict[BagTopic, _Topic] = {}
    lo = hi = None
    for bt, t, raw, deserialize in raw_messages(bag, None, report):
        tp = topics.get(bt)
        if tp is None:
            tp = topics[bt] = _Topic()
        tp.add(t)
        lo = t if lo is None else min(lo, t)
        hi = t if hi is None else max(hi, t)
        if tp.first_fields is None and tp.error is None:
            try:
                tp.set_first(deserialize(raw, bt.msgtype))
            except Exception as exc:  # noqa: BLE001 - a message its type store cannot read
                tp.error = f"first message not decodable ({type(exc).__name__}: {exc})"
        elif tp.lists and tp.list_messages < LIST_MESSAGES:
            try:
                tp.count_lists(deserialize(raw, bt.msgtype))
            except Exception:  # noqa: BLE001 - a later message that does not decode: not counted
                pass
    out_topics: dict[str, Any] = {}
    for bt in report.get("bag_topics", {}):
        tp = topics.get(bt, _Topic())
        entry = {"schema": bt.msgtype, "encoding": bt.encoding, "messages": tp.n, **tp.rate(),
                 "fields": [x["path"] for x in tp.first_fields] if tp.first_fields else None,
                 "field_info": tp.first_fields, "list_values": tp.selectable(),
                 "list_values_repeated": tp.repeated_values(),
                 "quaternions": tp.quaternions}
        if tp.error:
            entry["status"] = "not decodable: " + tp.error
        key = bt.topic if bt.topic not in out_topics else f"{bt.topic} ({bt.msgtype})"
        out_topics[key] = entry
    scanned = "ros1_connections" in report
    info: dict[str, Any] = {"file": str(bag), "profile": "ros1" if storage == "rosbag1" else "ros2",
                            "library": f"{storage} (read with rosbags)" + (", record scan" if scanned else ""),
                            "summary": not scanned, "compression": sorted(report.get("compression", set())),
                            "topics": out_topics, "scanned": scanned, "messages": report.get("messages", 0),
                            "indexed": not scanned}
    return _with_range_and_damage(info, bag, report, lo, hi)


def _with_range_and_damage(info: dict[str, Any], path: Path, report: dict[str, Any], lo: int | None,
                           hi: int | None) -> dict[str, Any]:
    """``info`` with the time range of what was read and the one-line damage report, if any
    (the end of every description, an MCAP file's or a bag's)."""
    if lo is not None:
        info["time_range_ns"] = [lo, hi]
    if report.get("empty"):
        info["damage"] = "empty file (0 bytes)"
    elif (text := damage_text(path, report)):
        info["damage"] = text
    return info


def _has_summary(path: Path) -> bool:
    """Whether the file ends with a footer pointing at a summary section."""
    import struct

    from offline_adp.ingest.mcap.scan import _MAGIC

    try:
        with open(path, "rb") as f:
            size = f.seek(0, 2)
            if size < 8 + 9 + 20 + 8:
                return False
            f.seek(size - 8 - 29)
            tail = f.read(29 + 8)
        if tail[-8:] != _MAGIC or tail[0] != 0x02:
            return False
        summary_start = struct.unpack_from("<Q", tail, 9)[0]
        return 0 < summary_start < size
    except OSError:
        return False
