"""MCAP logs -> dataset (the only module that imports ``mcap``).

Reading: a record-level scan of each file in file order (no index or summary needed).
A chunk that fails to decompress or to match its CRC is skipped and reported ("lost
chunk at offset Y"), and reading continues with the next record; a file cut short
(crash during recording) keeps every complete record before the cut and reports
"recovered N messages of file X, lost from offset Y". Per ``on_error`` the damage fails
the ingestion or is reported and the episodes it touched are left out.

Assembly streams: messages go into per-stream buffers; once every stream has moved
``reorder_window`` seconds past a step, the step is aligned (``nearest``, ``previous``,
``linear`` with ``max_age``), joined to the episode being assembled, and the buffers are
pruned. Memory is bounded by the episode being assembled plus the reorder window, not
by the file. Time sources that go backwards (``log_time`` restarting between
concatenated episodes) start a new *epoch*: an episode boundary.

Spec (TOML), see ``docs/ingestion-spec.md``::

    [sources]  files (globs, relative to the spec), split_recordings
    [clock]    topic | rate_hz (+ reference), time, reorder_window
    [episodes] topic, id_field, event_field, terminated_field, source_field, gap,
               restart, per_file, end_when, terminal_when
    [[streams]] topic, role, time, align, max_age, missing, fill, fields = {name = "path"}
    [action]   topic, field, time, align, max_age, + the Parquet spec's action keys
    [cost]     terms = [{field, op, weight, at}] | field | reward, terminal_cost
    [source]   value | by_file = {glob = label}
    [hints]    gamma, horizon
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import re
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp._version import __version__
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import DatasetInfo, Feature
from offline_adp.data.io import sha256_file, write_dataset
from offline_adp.data.validate import split_quarantine, validate
from offline_adp.errors import IngestError, SpecError, ValidationError
from offline_adp.ingest.actions import bin_continuous, map_discrete
from offline_adp.ingest.spec import ActionSpec, _check_keys


# ----------------------------------------------------------------------------- decoding
class JsonDecoderFactory:
    """Decodes ``json`` message encoding to dicts."""

    def decoder_for(self, message_encoding: str, schema: Any) -> Any:
        if message_encoding == "json":
            return lambda data: json.loads(data)
        return None


def decoder_factories() -> list[Any]:
    out: list[Any] = [JsonDecoderFactory()]
    try:
        from mcap_ros2.decoder import DecoderFactory as Ros2

        out.append(Ros2())
    except ImportError:  # pragma: no cover
        pass
    try:
        from mcap_protobuf.decoder import DecoderFactory as Proto

        out.append(Proto())
    except ImportError:  # pragma: no cover
        pass
    return out


class _Decoders:
    """The decoder of each (message encoding, schema) pair, looked up once; None when no
    installed decoder reads it."""

    def __init__(self) -> None:
        self.factories = decoder_factories()
        self.cache: dict[tuple[str, int | None], Any] = {}

    def __call__(self, sch: Any, ch: Any) -> Any:
        key = (ch.message_encoding, None if sch is None else sch.id)
        if key not in self.cache:
            self.cache[key] = next((d for fac in self.factories if (d := fac.decoder_for(ch.message_encoding, sch))
                                    is not None), None)
        return self.cache[key]


_TOKEN = re.compile(r"([^.\[\]]+)|\[(\d+)\]")


def get_path(msg: Any, path: str) -> Any:
    """Value at a dotted path with list indices (``transforms[0].transform.translation.x``)."""
    cur = msg
    for name, index in _TOKEN.findall(path):
        if index:
            cur = cur[int(index)]
        elif isinstance(cur, dict):
            cur = cur[name]
        else:
            cur = getattr(cur, name)
    return cur


def to_ns(value: Any) -> int:
    """A time value in ns: ``{sec, nanosec}`` (ROS 2), ``{sec, nsec}``, or float seconds."""
    for s, n in (("sec", "nanosec"), ("sec", "nsec"), ("secs", "nsecs")):
        if isinstance(value, dict) and s in value:
            return int(value[s]) * 1_000_000_000 + int(value.get(n, 0))
        if hasattr(value, s):
            return int(getattr(value, s)) * 1_000_000_000 + int(getattr(value, n, 0))
    return int(round(float(value) * 1e9))


def field_paths(msg: Any, prefix: str = "", depth: int = 0) -> list[str]:
    """Leaf field paths of a decoded message (for ``mcap-info``)."""
    if depth > 6:
        return [prefix]
    if isinstance(msg, dict):
        items = list(msg.items())
    elif hasattr(msg, "__slots__") or hasattr(msg, "__dict__"):
        names = getattr(msg, "__slots__", None) or [k for k in vars(msg) if not k.startswith("_")]
        items = [(k, getattr(msg, k)) for k in names]
    elif isinstance(msg, list | tuple) and msg:
        return field_paths(msg[0], f"{prefix}[0]", depth + 1)
    else:
        return [prefix]
    out: list[str] = []
    for k, v in items:
        out += field_paths(v, f"{prefix}.{k}" if prefix else str(k), depth + 1)
    return out


def _open_reader(f: Any) -> Any:
    from mcap.reader import make_reader

    return make_reader(f, decoder_factories=decoder_factories())


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


def _decoded(messages: Any):
    """Decode (schema, channel, message) triples; channels no decoder understands are
    skipped (a needed topic that yields nothing is reported by the caller, by name)."""
    decoders = _Decoders()
    for sch, ch, msg in messages:
        if (dec := decoders(sch, ch)) is not None:
            yield sch, ch, msg, dec(msg.data)


def _safe_decoded(reader: Any, topics: Sequence[str] | None):
    """Decoded messages of an indexed reader, in file order."""
    return _decoded(reader.iter_messages(topics=topics, log_time_order=False))


# ----------------------------------------------------------------------------- spec
ROLES = ("obs", "aux", "cost", "reward", "terminal", "episode")


@dataclass(frozen=True)
class StreamSpec:
    """One topic's fields, how they are timed and aligned to the steps, and what a missing
    value means. ``role``: ``obs`` fields are features; the others are auxiliary values
    (usable in cost terms and episode conditions): ``aux`` (nothing more),
    ``cost``/``reward`` (the cost, or the
    negated reward, when ``[cost]`` declares no terms), ``terminal`` (non-zero marks a
    terminal step), ``episode`` (a change of value starts a new episode)."""

    topic: str
    fields: dict[str, str]
    time: str = "log_time"
    align: str = "nearest"
    max_age: float = 0.1
    missing: str = "error"
    fill: float = 0.0
    role: str = "obs"


@dataclass(frozen=True)
class Condition:
    """``field op value`` on an aligned field (no expression is evaluated)."""

    field: str
    op: str
    value: float

    def holds(self, x: np.ndarray) -> np.ndarray:
        return _OPS[self.op](x, self.value)


_OPS = {"==": np.equal, "!=": np.not_equal, "<": np.less, "<=": np.less_equal, ">": np.greater, ">=": np.greater_equal}


@dataclass(frozen=True)
class McapSpec:
    clock_topic: str | None
    clock_time: str
    streams: tuple[StreamSpec, ...]
    action_stream: StreamSpec
    action: ActionSpec
    cost_terms: tuple[dict[str, Any], ...]
    terminal_cost: float | None = None
    cost_field: str | None = None
    reward_field: str | None = None
    rate_hz: float | None = None
    reorder_window: float = 2.0
    episode_topic: str | None = None
    episode_fields: dict[str, str] = field(default_factory=dict)
    gap: float = 1.0
    restart: float = 1.0
    per_file: bool = False
    end_when: tuple[Condition, ...] = ()
    terminal_when: tuple[Condition, ...] = ()
    source_value: str = "unknown"
    source_by_file: dict[str, str] = field(default_factory=dict)
    files: tuple[str, ...] = ()
    split_recordings: bool = True
    gamma: float | None = None
    horizon: int | None = None
    name: str = ""
    on_error: str = "fail"
    raw: dict[str, Any] = field(default_factory=dict, compare=False)
    text: str = field(default="", compare=False)
    base_dir: str = field(default=".", compare=False)

    @property
    def obs_names(self) -> list[str]:
        return [n for s in self.streams if s.role == "obs" for n in s.fields]

    @property
    def aux_names(self) -> list[str]:
        return [n for s in self.streams if s.role != "obs" for n in s.fields]


_ALIGN = ("nearest", "previous", "linear")
_STREAM_KEYS = {"topic", "fields", "time", "align", "max_age", "missing", "fill", "role"}


def _stream(d: dict[str, Any], where: str, fields_required: bool = True) -> StreamSpec:
    _check_keys(d, _STREAM_KEYS | ({"field"} if not fields_required else set()), where)
    if "topic" not in d:
        raise SpecError(f"{where}: missing required key 'topic'")
    s = StreamSpec(topic=d["topic"], fields=dict(d.get("fields", {})), time=d.get("time", "log_time"),
                   align=d.get("align", "nearest"), max_age=float(d.get("max_age", 0.1)),
                   missing=d.get("missing", "error"), fill=float(d.get("fill", 0.0)), role=d.get("role", "obs"))
    if s.align not in _ALIGN:
        raise SpecError(f"{where}.align: expected one of {list(_ALIGN)}, got {s.align!r}")
    if s.missing not in ("fill", "drop_step", "error"):
        raise SpecError(f"{where}.missing: expected 'fill', 'drop_step' or 'error', got {s.missing!r}")
    if s.role not in ROLES:
        raise SpecError(f"{where}.role: expected one of {list(ROLES)}, got {s.role!r}")
    if fields_required and not s.fields:
        raise SpecError(f"{where}.fields: map at least one name to a field path")
    return s


def _conditions(items: Any, where: str, names: list[str]) -> tuple[Condition, ...]:
    out = []
    for i, c in enumerate(items or []):
        _check_keys(c, {"field", "op", "value"}, f"{where}[{i}]")
        if c.get("field") not in names:
            raise SpecError(f"{where}[{i}].field: {c.get('field')!r} is not a stream field {names}")
        if c.get("op") not in _OPS:
            raise SpecError(f"{where}[{i}].op: expected one of {list(_OPS)}, got {c.get('op')!r}")
        try:
            out.append(Condition(c["field"], c["op"], float(c.get("value", 0.0))))
        except (TypeError, ValueError):
            raise SpecError(f"{where}[{i}].value: expected a number, got {c.get('value')!r}") from None
    return tuple(out)


def parse_mcap_spec(data: dict[str, Any], text: str = "", where: str = "spec", base_dir: str = ".") -> McapSpec:
    _check_keys(data, {"name", "on_error", "sources", "clock", "episodes", "streams", "action", "cost", "source",
                       "hints"}, where)
    clock = data.get("clock") or {}
    _check_keys(clock, {"topic", "time", "rate_hz", "reorder_window"}, f"{where}.clock")
    if ("topic" in clock) == ("rate_hz" in clock):
        raise SpecError(f"{where}.clock: give either the topic whose messages define the steps (clock.topic) "
                        "or a control rate (clock.rate_hz)")
    streams = tuple(_stream(s, f"{where}.streams[{i}]") for i, s in enumerate(data.get("streams", [])))
    if not any(s.role == "obs" for s in streams):
        raise SpecError(f"{where}.streams: declare at least one observation stream (role = 'obs', the default)")
    names = [n for s in streams for n in s.fields]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise SpecError(f"{where}.streams: field names {dup} are declared more than once")
    a = dict(data.get("action") or {})
    if "topic" not in a or "field" not in a:
        raise SpecError(f"{where}.action: needs 'topic' and 'field'")
    act_field = a.pop("field")
    act_stream = _stream({k: a.pop(k) for k in list(a) if k in _STREAM_KEYS and k != "fields"} | {"fields": {"action": act_field}},
                         f"{where}.action", fields_required=False)
    from offline_adp.ingest.spec import parse_parquet_spec

    action = parse_parquet_spec({"episode": {"id": "e", "step": "k"}, "observations": {"columns": ["x"], "next_columns": ["x"]},
                                 "action": {"column": "action", **a}, "cost": {"column": "c"}}, where=where).action
    cost = data.get("cost") or {}
    _check_keys(cost, {"terms", "terminal_cost", "field", "reward"}, f"{where}.cost")
    terms = tuple(cost.get("terms", []))
    for i, t in enumerate(terms):
        _check_keys(t, {"field", "op", "weight", "at"}, f"{where}.cost.terms[{i}]")
        if t.get("field") not in [*names, "action"]:
            raise SpecError(f"{where}.cost.terms[{i}].field: {t.get('field')!r} is not a stream field {names} or 'action'")
        if t.get("op", "abs") not in ("abs", "square", "identity"):
            raise SpecError(f"{where}.cost.terms[{i}].op: expected 'abs', 'square' or 'identity'")
        if t.get("at", "step") not in ("step", "next"):
            raise SpecError(f"{where}.cost.terms[{i}].at: expected 'step' or 'next'")
    cost_field, reward_field = cost.get("field"), cost.get("reward")
    for role in ("cost", "reward"):
        fs = [n for s in streams if s.role == role for n in s.fields]
        if fs and not terms and cost_field is None and reward_field is None:
            cost_field, reward_field = (fs[0], None) if role == "cost" else (None, fs[0])
    for k, v in (("field", cost_field), ("reward", reward_field)):
        if v is not None and v not in names:
            raise SpecError(f"{where}.cost.{k}: {v!r} is not a stream field {names}")
    if sum(x is not None and x != () for x in (terms or None, cost_field, reward_field)) != 1:
        raise SpecError(f"{where}.cost: declare exactly one of terms (a weighted sum of terms; no expressions are "
                        "evaluated), field (a cost field) or reward (a reward field, negated)")
    ep = dict(data.get("episodes") or {})
    _check_keys(ep, {"topic", "id_field", "event_field", "terminated_field", "source_field", "gap", "restart",
                     "per_file", "end_when", "terminal_when"}, f"{where}.episodes")
    src = data.get("source") or {}
    _check_keys(src, {"value", "by_file"}, f"{where}.source")
    sources = data.get("sources") or {}
    _check_keys(sources, {"files", "split_recordings"}, f"{where}.sources")
    hints = data.get("hints") or {}
    _check_keys(hints, {"gamma", "horizon"}, f"{where}.hints")
    terminal_when = _conditions(ep.get("terminal_when"), f"{where}.episodes.terminal_when", names)
    terminal_when += tuple(Condition(n, "!=", 0.0) for s in streams if s.role == "terminal" for n in s.fields)
    on_error = data.get("on_error", "fail")
    if on_error not in ("fail", "quarantine"):
        raise SpecError(f"{where}.on_error: expected 'fail' or 'quarantine', got {on_error!r}")
    return McapSpec(
        clock_topic=clock.get("topic"), clock_time=clock.get("time", "log_time"), streams=streams, action_stream=act_stream,
        action=action, cost_terms=terms, terminal_cost=cost.get("terminal_cost"), cost_field=cost_field,
        reward_field=reward_field, rate_hz=None if "rate_hz" not in clock else float(clock["rate_hz"]),
        reorder_window=float(clock.get("reorder_window", 2.0)), episode_topic=ep.get("topic"),
        episode_fields={k: ep[k] for k in ("id_field", "event_field", "terminated_field", "source_field") if k in ep},
        gap=float(ep.get("gap", 1.0)), restart=float(ep.get("restart", 1.0)), per_file=bool(ep.get("per_file", False)),
        end_when=_conditions(ep.get("end_when"), f"{where}.episodes.end_when", names), terminal_when=terminal_when,
        source_value=src.get("value", "unknown"), source_by_file=dict(src.get("by_file", {})),
        files=tuple(sources.get("files", [])), split_recordings=bool(sources.get("split_recordings", True)),
        gamma=hints.get("gamma"), horizon=hints.get("horizon"), name=data.get("name", ""), on_error=on_error,
        raw=dict(data), text=text, base_dir=base_dir,
    )


def load_mcap_spec(path: str | PathLike[str]) -> McapSpec:
    path = Path(path)
    try:
        text = path.read_text()
        return parse_mcap_spec(tomllib.loads(text), text, str(path), base_dir=str(path.parent))
    except FileNotFoundError:
        raise SpecError(f"{path}: no such spec file") from None
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{path}: not valid TOML ({exc})") from exc


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


# ----------------------------------------------------------------------------- reading
def _msg_time(which: str, msg: Any, dec: Any) -> int:
    if which == "log_time":
        return int(msg.log_time)
    if which == "publish_time":
        return int(msg.publish_time)
    return to_ns(get_path(dec, which))


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


def _align(ts: np.ndarray, vals: np.ndarray, at: np.ndarray, s: StreamSpec) -> tuple[np.ndarray, np.ndarray]:
    """Values of one field at times ``at``; returns (values, ok mask)."""
    max_age = int(s.max_age * 1e9)
    n = len(ts)
    if n == 0:
        return np.full(len(at), np.nan), np.zeros(len(at), bool)
    i = np.searchsorted(ts, at, side="right")  # ts[i-1] <= at < ts[i]
    prev = np.clip(i - 1, 0, n - 1)
    nxt = np.clip(i, 0, n - 1)
    has_prev = i > 0
    if s.align == "previous":
        ok = has_prev & (at - ts[prev] <= max_age)
        return vals[prev], ok
    if s.align == "nearest":
        use_next = (np.abs(ts[nxt] - at) < np.abs(at - ts[prev])) | ~has_prev
        j = np.where(use_next, nxt, prev)
        return vals[j], np.abs(ts[j] - at) <= max_age
    span = (ts[nxt] - ts[prev]).astype(np.float64)
    w = np.where(span > 0, (at - ts[prev]) / np.where(span > 0, span, 1.0), 0.0)
    ok = has_prev & (i < n) & (at - ts[prev] <= max_age) & (ts[nxt] - at <= max_age) | (ts[prev] == at)
    return vals[prev] + np.clip(w, 0, 1) * (vals[nxt] - vals[prev]), ok


class _Buffer:
    """One key's messages in one epoch: appended in file order, sorted by time on demand
    (each stream on its own: never a global sort of the file)."""

    def __init__(self, names: list[str], dtype: Any = np.float64) -> None:
        self.names, self.dtype = names, dtype
        self.new: dict[str, list] = {"t": [], "file": [], **{n: [] for n in names}}
        self.arr: dict[str, np.ndarray] = {"t": np.zeros(0, np.int64), "file": np.zeros(0, np.int32),
                                           **{n: np.zeros(0, dtype) for n in names}}

    def add(self, t: int, file: int, values: list[Any]) -> None:
        self.new["t"].append(t)
        self.new["file"].append(file)
        for n, v in zip(self.names, values, strict=True):
            self.new[n].append(v)

    def arrays(self) -> dict[str, np.ndarray]:
        if self.new["t"]:
            merged = {k: np.concatenate([self.arr[k], np.asarray(self.new[k], dtype=self.arr[k].dtype)]) for k in self.arr}
            order = np.argsort(merged["t"], kind="stable")
            self.arr = {k: v[order] for k, v in merged.items()}
            self.new = {k: [] for k in self.new}
        return self.arr

    def prune(self, cutoff: int) -> None:
        """Drop messages before ``cutoff`` but keep the last one before it (``previous`` holds it)."""
        a = self.arrays()
        i = max(int(np.searchsorted(a["t"], cutoff, side="left")) - 1, 0)
        if i:
            self.arr = {k: v[i:] for k, v in a.items()}

    def __len__(self) -> int:
        return len(self.arr["t"]) + len(self.new["t"])


@dataclass
class _Episode:
    """The episode being assembled: its steps so far (arrays appended per flush)."""

    key: Any
    ep_id: str
    source: str
    parts: list[dict[str, np.ndarray]] = field(default_factory=list)

    def add(self, steps: dict[str, np.ndarray], sl: slice) -> None:
        if sl.stop > sl.start:
            self.parts.append({k: v[sl] for k, v in steps.items()})


class _Recording:
    """Streams one recording (one file, or the parts of a split recording) into episodes.

    Steps: the clock topic's messages (or ``rate_hz`` ticks over the first observation
    stream). A step is aligned once every stream has moved ``reorder_window`` plus its
    ``max_age`` past it; buffers are then pruned, so memory holds the episode being
    assembled and a few seconds of messages, whatever the file size.
    """

    def __init__(self, files: list[Path], spec: McapSpec, on_error: str, file_index: int) -> None:
        self.files, self.spec, self.on_error, self.file0 = files, spec, on_error, file_index
        self.name = re.sub(r"_\d+$", "", files[0].stem) if len(files) > 1 else files[0].stem
        self.value_keys: dict[Any, StreamSpec] = {("s", i): s for i, s in enumerate(spec.streams)}
        self.value_keys["action"] = spec.action_stream
        self.clock_key: Any = "clock" if spec.clock_topic else ("s", next(i for i, s in enumerate(spec.streams)
                                                                          if s.role == "obs"))
        self.by_topic: dict[str, list[Any]] = {}
        for k, s in self.value_keys.items():
            self.by_topic.setdefault(s.topic, []).append(k)
        if spec.clock_topic:
            self.by_topic.setdefault(spec.clock_topic, []).append("clock")
        if spec.episode_topic:
            self.by_topic.setdefault(spec.episode_topic, []).append("events")
        self.names = {k: list(s.fields) for k, s in self.value_keys.items()}
        self.names["clock"] = []
        self.names["events"] = list(spec.episode_fields)
        self.epoch: dict[Any, int] = {k: 0 for ks in self.by_topic.values() for k in ks}
        self.maxt: dict[Any, int | None] = {k: None for k in self.epoch}
        self.bufs: dict[tuple[Any, int], _Buffer] = {}
        self.clock_first: dict[int, int] = {}
        self.active = 0
        self.flushed_t: int | None = None  # time of the last step handed to the episodes
        self.lag = int((spec.reorder_window + max(s.max_age for s in self.value_keys.values())) * 1e9)
        self.reorder = int(spec.reorder_window * 1e9)
        self.restart = int(spec.restart * 1e9)
        self.next_tick: int | None = None
        self.last_step_t: int | None = None
        self.last_episode_value: np.ndarray | None = None
        self.waiting: Any = None  # key of an episode an end/terminal condition closed, while it still holds
        self.counter = 0
        self.seg = 0
        self.event_info: dict[Any, tuple[str, str | None, bool | None]] = {}
        self.splits: dict[Any, int] = {}
        self.cur: _Episode | None = None
        self.out: list[dict[str, Any]] = []
        self.used = {t: 0 for t in self.by_topic}
        self.late = {t: 0 for t in self.by_topic}
        self.stats = {"dropped_steps": 0, "outside_episode_steps": 0, "condition_steps": 0, "short_episodes": 0,
                      "incomplete_episodes": 0, "episodes_lost_to_damage": 0, "damaged_steps": 0, "restarts": 0,
                      "orphan_messages": 0,
                      "max_buffered_messages": 0}
        self.reports: list[dict[str, Any]] = []
        self.live_reports: list[dict[str, Any]] = []
        obs = spec.obs_names
        aux = spec.aux_names
        self.col = {n: ("obs", obs.index(n)) for n in obs} | {n: ("aux", aux.index(n)) for n in aux}
        self.episode_fields = [n for s in spec.streams if s.role == "episode" for n in s.fields]

    # ------------------------------------------------------------------ reading
    def run(self) -> dict[str, Any]:
        for fi, path in enumerate(self.files):
            if fi and self.spec.per_file:
                self._new_epoch_everywhere()
            self._read(path, self.file0 + fi)
        self._flush(final=True)
        lost = self._lost_ranges()
        if lost:  # episodes that overlap a lost chunk miss messages: leave them out, counted
            kept = [ep for ep in self.out if not any(ep["t"][0] <= b and ep["t_end"] >= a for a, b in lost)]
            self.stats["episodes_lost_to_damage"] += len(self.out) - len(kept)
            self.out = kept
        missing = [t for t, n in self.used.items() if n == 0 and t != self.spec.episode_topic]
        return {"episodes": self.out, "stats": self.stats, "used": self.used, "late": self.late, "files": self.reports,
                "missing_topics": missing}

    def _read(self, path: Path, file_index: int) -> None:
        from collections import Counter

        report: dict[str, Any] = {}
        self.live_reports.append(report)  # lost chunks become known while reading
        before = dict(self.used)
        decoders = _Decoders()
        n_since = 0
        try:
            with open(path, "rb") as f:
                for sch, ch, msg in scan_records(f, set(self.by_topic), report):
                    dec = decoders(sch, ch)
                    if dec is None:
                        raise IngestError(f"{path}: needed topic {ch.topic!r} has message encoding "
                                          f"{ch.message_encoding!r} (schema {getattr(sch, 'name', '')!r}, encoding "
                                          f"{getattr(sch, 'encoding', '')!r}) that no installed decoder reads")
                    self._add(ch.topic, msg, dec(msg.data), file_index, path)
                    n_since += 1
                    if n_since >= 5000:
                        n_since = 0
                        self._flush()
        except IngestError:
            raise
        except (KeyError, AttributeError, IndexError, TypeError, ValueError) as exc:
            raise IngestError(f"{path}: a field path of the spec does not match the messages ({type(exc).__name__}: "
                              f"{exc}); run `offline-adp mcap-info` to list the fields") from exc
        except Exception as exc:  # noqa: BLE001 - any other library error becomes ours, naming the file
            raise IngestError(f"{path}: cannot read as MCAP ({type(exc).__name__}: {exc})") from exc
        text = damage_text(path, report)
        entry = {"path": str(path), "messages_used": {t: n - before[t] for t, n in self.used.items()},
                 "messages_skipped": dict(Counter(report.get("skipped", {}))), **({"empty": True} if report.get("empty") else {})}
        if text:
            entry["recovered"] = {"messages": report["messages"], "lost_chunks": report["lost_chunks"],
                                  **{k: report[k] for k in ("lost_from_offset", "damaged") if k in report}, "text": text}
            if self.on_error == "fail":
                raise IngestError(text + "; re-run with --on-error quarantine to keep what was recovered")
            import warnings

            warnings.warn(text, stacklevel=4)
        self.reports.append(entry)

    def _add(self, topic: str, msg: Any, dec: Any, file_index: int, path: Path) -> None:
        self.used[topic] += 1
        for k in self.by_topic[topic]:
            if k == "events":
                t = int(msg.log_time)
                values = [get_path(dec, p) for p in self.spec.episode_fields.values()]
            elif k == "clock":
                t, values = _msg_time(self.spec.clock_time, msg, dec), []
            else:
                s = self.value_keys[k]
                t = _msg_time(s.time, msg, dec)
                values = [float(get_path(dec, p)) for p in s.fields.values()]
            e = self._epoch_of(k, t)
            if e is None:  # late for an epoch already over (by file order, not by flush points)
                self.late[topic] += 1
                continue
            if e == self.active and self.flushed_t is not None and t < self.flushed_t - self.lag:
                self.late[topic] += 1  # steps before it were aligned without it
            b = self.bufs.get((k, e))
            if b is None:
                b = self.bufs[(k, e)] = _Buffer(self.names[k], object if k == "events" else np.float64)
            b.add(t, file_index, values)

    def _epoch_of(self, k: Any, t: int) -> int | None:
        """The epoch of a message of key ``k`` at time ``t``, from the file order alone
        (never from what has been flushed): see "Epochs" in docs/ingestion-spec.md.

        The clock's epoch advances when its time jumps back more than ``restart``. Any
        other stream is placed against the clock's current epoch ``ce`` and latest time
        ``cm``: a time more than ``restart`` below ``cm`` is the next epoch's (the stream
        restarted before the clock); a stream still in ``ce - 1`` whose time has not
        jumped back and lies more than ``restart`` above ``cm`` is a late message of
        ``ce - 1``; anything else is ``ce``'s. A stream ahead of the clock stays ahead
        until the clock follows (a second jump back while ahead replaces its buffer: the
        clock skipped that epoch). None: the message belongs to an epoch that is over.
        """
        r = self.restart
        m, ek = self.maxt[k], self.epoch[k]
        own_restart = m is not None and r > 0 and t < m - r
        ck = self.clock_key
        if k == ck:
            e = ek + 1 if own_restart else ek
            if own_restart:
                self.stats["restarts"] += 1
            if e not in self.clock_first:
                self.clock_first[e] = t
        else:
            ce, cm = self.epoch[ck], self.maxt[ck]
            ahead = cm is not None and r > 0 and t < cm - r
            if ek == ce + 1 and m is not None:  # ahead of the clock
                e = ek
                if own_restart:  # a second restart before the clock's: the clock has no such epoch
                    b = self.bufs.pop((k, ek), None)
                    self.stats["orphan_messages"] += len(b) if b is not None else 0
            elif ek == ce and m is not None and not own_restart:
                e = ce
            elif ek == ce - 1 and m is not None and not own_restart and cm is not None and r > 0 and t > cm + r:
                e = ek  # a late message of the epoch before the clock's restart
                if cm - self.clock_first.get(ce, cm) >= self.reorder:
                    return None
            else:
                e = ce + 1 if ahead else ce
        if e != ek:
            self.epoch[k], m = e, None
        elif own_restart:
            m = None
        if m is None or t > m:
            self.maxt[k] = t
        if e < self.active:  # defensive: never happens for messages on time (see the rules above)
            return None
        return e

    def _lost_ranges(self) -> list[tuple[int, int]]:
        """Time ranges (widened by the reorder window) of the chunks lost so far."""
        return [(c["start_ns"] - self.reorder, c["end_ns"] + self.reorder) for r in self.live_reports
                for c in r.get("lost_chunks", []) if "start_ns" in c]

    def _damaged(self, t: np.ndarray) -> np.ndarray:
        out = np.zeros(len(t), bool)
        for a, b in self._lost_ranges():
            out |= (t >= a) & (t <= b)
        return out

    def _new_epoch_everywhere(self) -> None:
        e = max(self.epoch.values()) + 1
        for k in self.epoch:
            self.epoch[k], self.maxt[k] = e, None

    # ------------------------------------------------------------------ flushing
    def _watermark(self, e: int) -> float:
        """Steps of epoch ``e`` up to this time have all their data (inf: the epoch is over)."""
        ce = self.epoch[self.clock_key]
        if ce > e:
            now = self.maxt[self.clock_key] or 0
            if (ce > e + 1 or all(v > e for v in self.epoch.values())
                    or now - self.clock_first.get(ce, now) >= self.reorder):  # no message can still join e
                return np.inf
        latest = [self.maxt[k] for k in self.epoch if self.epoch[k] == e and self.maxt[k] is not None]
        if not latest:
            return -np.inf
        top = max(latest)
        span = top - self.clock_first.get(e, top)
        w = np.inf
        for k in self.epoch:
            if k == "events":
                continue
            if self.epoch[k] > e:
                continue
            if self.epoch[k] < e or self.maxt[k] is None:
                if span <= self.reorder:
                    return -np.inf  # this stream may still come (e.g. written topic by topic)
                continue
            if self.maxt[k] < top - self.reorder:
                continue  # an idle stream (event-driven commands): do not wait for it
            w = min(w, self.maxt[k])
        return w - self.lag

    def _flush(self, final: bool = False) -> None:
        held = sum(len(b) for b in self.bufs.values())
        self.stats["max_buffered_messages"] = max(self.stats["max_buffered_messages"], held)
        while True:
            e = self.active
            w = np.inf if final else self._watermark(e)
            if w == -np.inf:
                return
            self._emit_ready(e, w)
            if w != np.inf:
                return
            self._close(None)  # the epoch is over: so is its episode
            for k in list(self.bufs):
                if k[1] == e:
                    del self.bufs[k]
            self.last_step_t, self.last_episode_value, self.next_tick, self.waiting = None, None, None, None
            self.flushed_t = None
            self.active += 1
            if self.active > max(self.epoch.values()):
                return

    def _ticks(self, e: int, w: float) -> tuple[np.ndarray, np.ndarray]:
        """Step times and their files: clock messages, or rate_hz ticks over the reference stream."""
        b = self.bufs.get((self.clock_key, e))
        if b is None:
            return np.zeros(0, np.int64), np.zeros(0, np.int32)
        a = b.arrays()
        start = 0 if self.flushed_t is None else int(np.searchsorted(a["t"], self.flushed_t, side="right"))
        stop = len(a["t"]) if w == np.inf else int(np.searchsorted(a["t"], w, side="right"))
        t, f = a["t"][start:stop], a["file"][start:stop]
        if self.spec.rate_hz is None:
            return t, f
        period = int(round(1e9 / self.spec.rate_hz))
        gap = int(self.spec.gap * 1e9)
        out_t, out_f = [], []
        prev = self.flushed_t
        for ti, fi in zip(t.tolist(), f.tolist(), strict=True):  # per reference message, not per row of data
            if self.next_tick is None or prev is None or ti - prev > gap:
                self.next_tick = ti
            if self.next_tick <= ti:
                k = np.arange(self.next_tick, ti + 1, period, dtype=np.int64)
                out_t.append(k)
                out_f.append(np.full(len(k), fi, np.int32))
                self.next_tick = int(k[-1]) + period
            prev = ti
        if not out_t:
            return np.zeros(0, np.int64), np.zeros(0, np.int32)
        return np.concatenate(out_t), np.concatenate(out_f)

    def _emit_ready(self, e: int, w: float) -> None:
        times, files = self._ticks(e, w)
        if len(times):
            last_clock = self.bufs[(self.clock_key, e)].arrays()["t"]
            upto = int(last_clock[-1]) if w == np.inf else int(last_clock[np.searchsorted(last_clock, w, side="right") - 1])
            self._steps(e, times, files)
            self.flushed_t = upto
            for (k, ek), b in self.bufs.items():
                if ek == e and k != "events":
                    b.prune(upto - self.lag)

    def _steps(self, e: int, times: np.ndarray, files: np.ndarray) -> None:
        spec = self.spec
        n = len(times)
        obs = np.empty((n, len(spec.obs_names)))
        aux = np.empty((n, len(spec.aux_names)))
        keep = np.ones(n, bool)
        damaged = self._damaged(times)  # steps whose messages may be in a lost chunk: their episode is left out
        missing_here = np.zeros(n, bool)
        act, act_ok = np.zeros(n), np.ones(n, bool)
        for k, s in self.value_keys.items():
            b = self.bufs.get((k, e))
            a = b.arrays() if b is not None else {"t": np.zeros(0, np.int64), **{nm: np.zeros(0) for nm in s.fields}}
            for name in s.fields:
                v, good = _align(a["t"], a[name], times, s)
                if s.missing == "fill":
                    v, good = np.where(good, v, s.fill), np.ones(n, bool)
                elif s.missing == "drop_step":
                    keep &= good
                elif k != "action":
                    if not (good | damaged).all():
                        j = int(np.flatnonzero(~(good | damaged))[0])
                        raise IngestError(f"{self.files[files[j] - self.file0]}: step at t = {times[j] / 1e9:.6f} s: no "
                                          f"{s.topic} message within max_age = {s.max_age} s for {name!r} (use missing = "
                                          "'fill' or 'drop_step')")
                    missing_here |= ~good
                if k == "action":
                    act, act_ok = v, good
                else:
                    where, j = self.col[name]
                    (obs if where == "obs" else aux)[:, j] = v
        hit = damaged & (missing_here | ~act_ok)
        self.stats["damaged_steps"] += int(hit.sum())
        keep &= ~hit
        self.stats["dropped_steps"] += int((~keep & ~hit).sum())
        steps = {"t": times, "file": files, "obs": obs, "aux": aux, "act": act, "act_ok": act_ok}
        if not keep.all():
            steps = {k: v[keep] for k, v in steps.items()}
        self._segment(e, steps)

    def _segment(self, e: int, st: dict[str, np.ndarray]) -> None:
        """Cut the steps into episodes: events (or gaps), episode fields, end/terminal conditions."""
        spec = self.spec
        t = st["t"]
        n = len(t)
        if not n:
            return
        if spec.episode_topic:
            key = self._event_membership(e, t)
        else:
            prev = np.r_[self.last_step_t if self.last_step_t is not None else t[0], t[:-1]]
            gap = (t - prev) > spec.gap * 1e9
            if self.last_step_t is None:
                gap[0] = True
            key = (self.seg + np.cumsum(gap)).astype(object)  # a new key at every gap
            self.seg = int(key[-1])
        brk = np.zeros(n, bool)
        if self.episode_fields:
            vals = np.column_stack([st["aux"][:, self.col[f][1]] for f in self.episode_fields])
            prev_v = np.vstack([vals[:1] if self.last_episode_value is None else self.last_episode_value, vals[:-1]])
            brk |= (vals != prev_v).any(axis=1)
            self.last_episode_value = vals[-1:]
        term = np.zeros(n, bool)
        for c in spec.terminal_when:
            term |= c.holds(self._field(st, c.field))
        end = term.copy()
        for c in spec.end_when:
            end |= c.holds(self._field(st, c.field))
        self.last_step_t = int(t[-1])
        # walk the change points only (not every step): key changes, breaks, condition steps and the step after one
        pts = np.flatnonzero(brk | end | np.r_[True, key[1:] != key[:-1]] | np.r_[False, end[:-1]])
        for i, j in zip(pts.tolist(), [*pts[1:].tolist(), n], strict=True):
            self._run(st, key[i], bool(brk[i]), bool(end[i]), bool(term[i]), i, j)

    def _run(self, st: dict[str, np.ndarray], k: Any, brk: bool, end: bool, term: bool, i: int, j: int) -> None:
        """Steps i..j-1: one key, no break inside; an ``end`` run is a single step."""
        if k is None:
            self._close(None)
            self.waiting = None
            self.stats["outside_episode_steps"] += j - i
            return
        if self.cur is not None and (self.cur.key != k or brk):
            self._close(None)
        if self.waiting is not None and self.waiting != k:
            self.waiting = None
        if self.waiting is not None:
            if end:  # the condition still holds: this step belongs to no episode
                self.stats["condition_steps"] += j - i
                return
            self.waiting = None
        if self.cur is None:
            self._open(k, st, i)
        self.cur.add(st, slice(i, j))  # type: ignore[union-attr]
        if end:  # an end or terminal condition: the episode ends at this step
            self._close(term)
            self.waiting = k

    def _open(self, k: Any, st: dict[str, np.ndarray], i: int) -> None:
        if self.spec.episode_topic:
            ep_id, source, _ = self.event_info[k]
            n_before = self.splits.get(k, 0)
            self.splits[k] = n_before + 1
            if n_before:
                ep_id = f"{ep_id}/{n_before}"
        else:
            ep_id, source = f"{self.name}-{self.counter:05d}", None
            self.counter += 1
        if source is None:
            source = self._source_of(self.files[int(st["file"][i]) - self.file0])
        self.cur = _Episode(k, ep_id, source)

    def _source_of(self, path: Path) -> str:
        import fnmatch

        for pat, label in self.spec.source_by_file.items():
            if fnmatch.fnmatch(path.name, pat) or fnmatch.fnmatch(str(path), pat):
                return str(label)
        return self.spec.source_value

    def _field(self, st: dict[str, np.ndarray], name: str) -> np.ndarray:
        where, j = self.col[name]
        return st[where][:, j]

    def _event_membership(self, e: int, t: np.ndarray) -> np.ndarray:
        """Per step, the key of the event-delimited episode it belongs to (None: outside)."""
        b = self.bufs.get(("events", e))
        out = np.full(len(t), None, dtype=object)
        if b is None:
            return out
        a = b.arrays()
        names = list(self.spec.episode_fields)
        kind = np.asarray([str(x) for x in a["event_field"]]) if "event_field" in a else np.full(len(a["t"]), "start")
        et = a["t"]
        is_start = kind == "start"
        idx = np.searchsorted(et, t, side="right") - 1  # the last event at or before each step
        for j in np.unique(idx[idx >= 0]):
            steps = idx == j
            if is_start[j]:
                s = j
                end_t = end_i = None
                after = np.arange(len(kind)) > j
                later_end = np.flatnonzero(after & (kind == "end"))
                later_start = np.flatnonzero(after & is_start)
                if len(later_end) and (not len(later_start) or later_end[0] < later_start[0]):
                    end_i = int(later_end[0])
                    end_t = et[end_i]
            elif kind[j] == "end":
                steps &= t == et[j]  # a step exactly at the end event still belongs to the episode
                starts = np.flatnonzero(is_start[:j])
                if not len(starts):
                    continue
                s, end_t, end_i = starts[-1], et[j], j
            else:
                continue
            k = f"{e}:{int(et[s])}"  # a scalar key (numpy would unpack a tuple)
            if k not in self.event_info:
                ep_id = str(a["id_field"][s]) if "id_field" in names else f"{self.name}-{e}-{int(et[s])}"
                src = str(a["source_field"][s]) if "source_field" in names else None
                self.event_info[k] = (ep_id, src, None)
            if end_t is not None:
                terminated = bool(a["terminated_field"][end_i]) if "terminated_field" in names else False
                self.event_info[k] = (*self.event_info[k][:2], terminated)
            out[steps] = [k] * int(steps.sum())
        return out

    def _close(self, terminated: bool | None) -> None:
        ep, self.cur = self.cur, None
        if ep is None or not ep.parts:
            return
        st = {k: np.concatenate([p[k] for p in ep.parts]) for k in ep.parts[0]}
        if self.spec.episode_topic:
            info = self.event_info.get(ep.key)
            ended = info is not None and info[2] is not None
            if not ended and terminated is None:  # the log stops inside this episode (cut or crashed recording)
                self.stats["incomplete_episodes"] += 1
                return
            if terminated is None:
                terminated = bool(info[2])  # type: ignore[index]
        n = len(st["t"]) - 1
        if n < 1:
            self.stats["short_episodes"] += 1
            return
        if not st["act_ok"][:n].all():
            k = int(np.flatnonzero(~st["act_ok"][:n])[0])
            raise IngestError(f"{self.files[int(st['file'][k]) - self.file0]}: episode {ep.ep_id}, step {k}: no "
                              f"{self.spec.action_stream.topic} command within max_age = {self.spec.action_stream.max_age} s")
        self.out.append({"ep": ep.ep_id, "src": ep.source, "t": st["t"][:n], "file": st["file"][:n],
                         "obs": st["obs"][:-1], "next": st["obs"][1:], "aux": st["aux"][:-1], "aux_next": st["aux"][1:],
                         "act": st["act"][:n], "terminated": bool(terminated), "t_end": int(st["t"][-1])})


def _run_recording(files: list[Path], spec: McapSpec, on_error: str, file_index: int) -> dict[str, Any]:
    return _Recording(files, spec, on_error, file_index).run()


def ingest_mcap(
    files: Sequence[str | PathLike[str]],
    spec: McapSpec | str | PathLike[str],
    out: str | PathLike[str] | None = None,
    *,
    on_error: str | None = None,
    overwrite: bool = False,
    jobs: int = 1,
    progress: Any = None,
) -> tuple[TransitionDataset, dict[str, Any]]:
    """Ingest MCAP files into a dataset (written atomically to ``out`` when given).

    ``files`` may hold globs; empty means the spec's ``[sources] files``. Recordings (a
    file, or the parts of a split recording) are assembled independently — in a process
    pool with ``jobs > 1`` — and concatenated in input order, so the result does not
    depend on ``jobs``. Returns the dataset and a summary: per file its sha256, messages
    read and skipped per topic, damage recovered; per topic the messages used; steps
    dropped, outside any episode or under an end condition; episodes, transitions and
    per-source counts. ``progress(done, total)`` is called after each recording.
    """
    if not isinstance(spec, McapSpec):
        spec = load_mcap_spec(spec)
    if out is not None and Path(out).exists() and not overwrite:
        raise IngestError(f"{out} already exists; pass overwrite=True (CLI: --overwrite) to replace it")
    on_error = on_error or spec.on_error
    recordings = resolve_sources(files, spec)
    starts = np.cumsum([0] + [len(r) for r in recordings])[:-1].tolist()
    args = [(r, spec, on_error, s) for r, s in zip(recordings, starts, strict=True)]
    results: list[dict[str, Any]] = []
    if jobs > 1 and len(recordings) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(max_workers=min(jobs, len(recordings)), mp_context=mp.get_context("spawn")) as pool:
            for k, res in enumerate(pool.map(_run_recording, *zip(*args, strict=True))):  # input order
                results.append(res)
                if progress:
                    progress(k + 1, len(recordings))
    else:
        for k, a in enumerate(args):
            results.append(_run_recording(*a))
            if progress:
                progress(k + 1, len(recordings))
    paths = [p for r in recordings for p in r]
    summary: dict[str, Any] = {"files": [], "recordings": [[str(p) for p in r] for r in recordings],
                               "messages_used": {}, "messages_skipped": {}, "late_messages": {}}
    for res, rec in zip(results, recordings, strict=True):
        for k, v in res["stats"].items():
            summary[k] = max(summary.get(k, 0), v) if k == "max_buffered_messages" else summary.get(k, 0) + v
        for name in ("used", "late"):
            tgt = summary["messages_used" if name == "used" else "late_messages"]
            for t, v in res[name].items():
                tgt[t] = tgt.get(t, 0) + v
        for f in res["files"]:
            for t, v in f["messages_skipped"].items():
                summary["messages_skipped"][t] = summary["messages_skipped"].get(t, 0) + v
            summary["files"].append({**f, "sha256": sha256_file(f["path"])})
        if res["missing_topics"]:
            needed = [s for s in (*spec.streams, spec.action_stream) if s.topic in res["missing_topics"]]
            clock_missing = (spec.clock_topic or "") in res["missing_topics"]
            if clock_missing or any(s.missing == "error" for s in needed):
                msg = (f"{', '.join(map(str, rec))}: no decodable messages on needed topic(s) {res['missing_topics']} "
                       "(present in other recordings? set missing = 'fill' or 'drop_step' on that stream)")
                if on_error == "fail" or not any(len(r["episodes"]) for r in results):
                    raise IngestError(msg)
                import warnings

                warnings.warn(msg, stacklevel=2)
    summary["late_messages"] = {t: v for t, v in summary["late_messages"].items() if v}
    if summary["late_messages"]:
        import warnings

        warnings.warn(f"{sum(summary['late_messages'].values())} messages arrived more than clock.reorder_window = "
                      f"{spec.reorder_window} s after later ones in the file ({summary['late_messages']}); steps before "
                      "them were aligned without them. Raise reorder_window.", stacklevel=2)
    eps = [ep for r in results for ep in r["episodes"]]
    if not eps:
        raise IngestError(f"no episode with at least one transition in {[str(p) for p in paths]}")
    ds = _dataset(eps, spec, paths, summary)
    report = validate(ds)
    summary["doctor"] = report.summary()
    if not report.ok:
        if on_error == "fail":
            raise ValidationError(report.to_text(), report)
        ds, q = split_quarantine(ds, report)
        summary["quarantined_rows"] = q.num_rows
    if out is not None:
        write_dataset(ds, out, overwrite=overwrite, extra_meta={"ingest": _jsonable(summary)})
    summary.update(episodes=ds.n_episodes, transitions=len(ds), per_source=ds.source_counts())
    return ds, summary


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _dataset(eps: list[dict[str, Any]], spec: McapSpec, paths: list[Path], summary: dict[str, Any]) -> TransitionDataset:
    """Episodes -> dataset: action table, costs, provenance (``src_file`` per row)."""
    import pyarrow as pa

    cat = lambda k: np.concatenate([e[k] for e in eps])  # noqa: E731
    obs, nxt, aux, aux_next = cat("obs"), cat("next"), cat("aux"), cat("aux_next")
    lengths = np.array([len(e["t"]) for e in eps])
    raw_action = cat("act")
    if spec.action.type == "discrete":
        action, atable = map_discrete(raw_action, spec.action)
    else:
        action, atable = bin_continuous(raw_action, spec.action)
    term = np.zeros(len(obs), bool)
    ends = np.cumsum(lengths) - 1
    term[ends] = [e["terminated"] for e in eps]
    trunc = np.zeros(len(obs), bool)
    trunc[ends] = ~term[ends]
    obs_names, aux_names = spec.obs_names, spec.aux_names

    def column(name: str, at: str = "step") -> np.ndarray:
        if name == "action":
            return atable.values[action, 0]
        if name in obs_names:
            return (nxt if at == "next" else obs)[:, obs_names.index(name)]
        return (aux_next if at == "next" else aux)[:, aux_names.index(name)]

    if spec.cost_field is not None:
        cost = column(spec.cost_field).copy()
    elif spec.reward_field is not None:
        cost = -column(spec.reward_field)
    else:
        cost = np.zeros(len(obs))
        for t in spec.cost_terms:
            x = column(t["field"], t.get("at", "step"))
            op, w = t.get("op", "abs"), float(t.get("weight", 1.0))
            cost += w * (np.abs(x) if op == "abs" else x * x if op == "square" else x)
    if spec.terminal_cost is not None:
        cost = np.where(term, spec.terminal_cost, cost)
    cost = cost + 0.0  # no -0.0
    info = DatasetInfo(
        features=tuple(Feature(n) for n in obs_names), action_table=atable, gamma=spec.gamma, horizon=spec.horizon,
        propensity_source="unknown", name=spec.name,
        provenance={"inputs": summary["files"], "spec": spec.raw, "package_version": __version__,
                    "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"), "generator": "offline-adp ingest mcap"},
    )
    ds = TransitionDataset.from_arrays(
        info, episode_id=np.repeat([e["ep"] for e in eps], lengths), step=np.concatenate([np.arange(n) for n in lengths]),
        obs=obs, action=action, cost=cost, next_obs=nxt, terminated=term, truncated=trunc,
        source=np.repeat([e["src"] for e in eps], lengths), t_ns=cat("t"),
        extra={"src_file": pa.DictionaryArray.from_arrays(pa.array(cat("file").astype(np.int32)),
                                                          pa.array([str(p) for p in paths]))},
    )
    return ds
