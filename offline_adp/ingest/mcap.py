"""MCAP logs -> dataset (the only module that imports ``mcap``).

Status: first version (issue 3 in progress). Works: ``mcap_info``; reading in file order
with a streaming reader (unindexed files and files without a summary; a truncated or
corrupt file keeps every complete chunk before the damage and reports "recovered N
messages of file X, lost from offset Y", failing or continuing per ``on_error``); JSON and ROS 2 CDR
decoding (protobuf through ``mcap_protobuf`` when installed); a clock topic defining the
steps; per-stream field extraction with dotted paths and list indices; ``nearest``,
``previous`` and ``linear`` alignment with ``max_age`` and ``fill``/``drop_step``/
``error`` for missing values; episodes from an event topic or from time gaps; discrete
or binned actions; declarative costs (weighted abs/square terms, terminal cost); the
dataset doctor at the end. Not yet: resuming after a corrupt chunk (the chunks after it
are lost), bounded memory for very large files (a file is read whole), parallel files.

Spec (TOML), see ``docs/ingestion-spec.md``::

    [clock]   topic, time            # messages of `topic` are the steps
    [episodes] topic, id_field, event_field, terminated_field, source_field, gap
    [[streams]] topic, time, align, max_age, missing, fill, fields = {name = "path"}
    [action]  topic, field, time, align, max_age, + the Parquet spec's action keys
    [cost]    terms = [{field, op, weight, at}], terminal_cost
    [source]  value
    [hints]   gamma, horizon
"""

from __future__ import annotations

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
    schema, encoding, count, rate and the field paths of the first decodable message."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            reader = _open_reader(f)
            header = reader.get_header()
            summary = reader.get_summary()
            info: dict[str, Any] = {"file": str(path), "profile": header.profile, "library": header.library,
                                    "summary": summary is not None, "topics": {}}
            if summary is not None:
                st = summary.statistics
                info["indexed"] = bool(summary.chunk_indexes)
                info["compression"] = sorted({c.compression or "none" for c in summary.chunk_indexes})
                if st is not None:
                    info["time_range_ns"] = [st.message_start_time, st.message_end_time]
                    dur = max((st.message_end_time - st.message_start_time) / 1e9, 1e-9)
                    for cid, ch in summary.channels.items():
                        sch = summary.schemas.get(ch.schema_id)
                        n = st.channel_message_counts.get(cid, 0)
                        info["topics"][ch.topic] = {"schema": sch.name if sch else "", "encoding": ch.message_encoding,
                                                    "messages": n, "rate_hz": round(n / dur, 3), "fields": None}
        with open(path, "rb") as f:
            reader = _open_reader(f)
            pending = set(info["topics"]) if info["topics"] else None
            for sch, ch, _msg, dec in _safe_decoded(reader, None):
                t = info["topics"].setdefault(ch.topic, {"schema": sch.name if sch else "", "encoding": ch.message_encoding,
                                                         "messages": None, "rate_hz": None, "fields": None})
                if t["fields"] is None:
                    t["fields"] = field_paths(dec)
                    if pending is not None:
                        pending.discard(ch.topic)
                        if not pending:
                            break
    except IngestError:
        raise
    except Exception as exc:  # noqa: BLE001 - any library error becomes ours, naming the file
        raise IngestError(f"{path}: cannot read as MCAP ({type(exc).__name__}: {exc})") from exc
    return info


def _decoded(messages: Any):
    """Decode (schema, channel, message) triples; channels no decoder understands are
    skipped (a needed topic that yields nothing is reported by the caller, by name)."""
    cache: dict[tuple[str, int | None], Any] = {}
    factories = decoder_factories()
    for sch, ch, msg in messages:
        key = (ch.message_encoding, None if sch is None else sch.id)
        if key not in cache:
            cache[key] = next((d for fac in factories if (d := fac.decoder_for(ch.message_encoding, sch)) is not None), None)
        if cache[key] is not None:
            yield sch, ch, msg, cache[key](msg.data)


def _safe_decoded(reader: Any, topics: Sequence[str] | None):
    """Decoded messages of an indexed reader, in file order."""
    return _decoded(reader.iter_messages(topics=topics, log_time_order=False))


# ----------------------------------------------------------------------------- spec
@dataclass(frozen=True)
class StreamSpec:
    topic: str
    fields: dict[str, str]
    time: str = "log_time"
    align: str = "nearest"
    max_age: float = 0.1
    missing: str = "error"
    fill: float = 0.0


@dataclass(frozen=True)
class McapSpec:
    clock_topic: str
    clock_time: str
    streams: tuple[StreamSpec, ...]
    action_stream: StreamSpec
    action: ActionSpec
    cost_terms: tuple[dict[str, Any], ...]
    terminal_cost: float | None = None
    episode_topic: str | None = None
    episode_fields: dict[str, str] = field(default_factory=dict)
    gap: float = 1.0
    source_value: str = "unknown"
    gamma: float | None = None
    horizon: int | None = None
    name: str = ""
    on_error: str = "fail"
    raw: dict[str, Any] = field(default_factory=dict, compare=False)
    text: str = field(default="", compare=False)


_ALIGN = ("nearest", "previous", "linear")
_STREAM_KEYS = {"topic", "fields", "time", "align", "max_age", "missing", "fill"}


def _stream(d: dict[str, Any], where: str, fields_required: bool = True) -> StreamSpec:
    _check_keys(d, _STREAM_KEYS | ({"field"} if not fields_required else set()), where)
    if "topic" not in d:
        raise SpecError(f"{where}: missing required key 'topic'")
    s = StreamSpec(topic=d["topic"], fields=dict(d.get("fields", {})), time=d.get("time", "log_time"),
                   align=d.get("align", "nearest"), max_age=float(d.get("max_age", 0.1)),
                   missing=d.get("missing", "error"), fill=float(d.get("fill", 0.0)))
    if s.align not in _ALIGN:
        raise SpecError(f"{where}.align: expected one of {list(_ALIGN)}, got {s.align!r}")
    if s.missing not in ("fill", "drop_step", "error"):
        raise SpecError(f"{where}.missing: expected 'fill', 'drop_step' or 'error', got {s.missing!r}")
    if fields_required and not s.fields:
        raise SpecError(f"{where}.fields: map at least one observation name to a field path")
    return s


def parse_mcap_spec(data: dict[str, Any], text: str = "", where: str = "spec") -> McapSpec:
    _check_keys(data, {"name", "on_error", "clock", "episodes", "streams", "action", "cost", "source", "hints"}, where)
    clock = data.get("clock") or {}
    _check_keys(clock, {"topic", "time"}, f"{where}.clock")
    if "topic" not in clock:
        raise SpecError(f"{where}.clock: give the topic whose messages define the steps (clock.topic)")
    streams = tuple(_stream(s, f"{where}.streams[{i}]") for i, s in enumerate(data.get("streams", [])))
    if not streams:
        raise SpecError(f"{where}.streams: declare at least one observation stream")
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
    _check_keys(cost, {"terms", "terminal_cost"}, f"{where}.cost")
    terms = tuple(cost.get("terms", []))
    for i, t in enumerate(terms):
        _check_keys(t, {"field", "op", "weight", "at"}, f"{where}.cost.terms[{i}]")
        if t.get("op", "abs") not in ("abs", "square", "identity"):
            raise SpecError(f"{where}.cost.terms[{i}].op: expected 'abs', 'square' or 'identity'")
        if t.get("at", "step") not in ("step", "next"):
            raise SpecError(f"{where}.cost.terms[{i}].at: expected 'step' or 'next'")
    if not terms:
        raise SpecError(f"{where}.cost.terms: declare the cost as a weighted sum of terms (no expressions are evaluated)")
    ep = dict(data.get("episodes") or {})
    _check_keys(ep, {"topic", "id_field", "event_field", "terminated_field", "source_field", "gap"}, f"{where}.episodes")
    src = data.get("source") or {}
    _check_keys(src, {"value"}, f"{where}.source")
    hints = data.get("hints") or {}
    _check_keys(hints, {"gamma", "horizon"}, f"{where}.hints")
    return McapSpec(
        clock_topic=clock["topic"], clock_time=clock.get("time", "log_time"), streams=streams, action_stream=act_stream,
        action=action, cost_terms=terms, terminal_cost=cost.get("terminal_cost"), episode_topic=ep.pop("topic", None),
        episode_fields={k: v for k, v in ep.items() if k != "gap"}, gap=float(ep.get("gap", 1.0)),
        source_value=src.get("value", "unknown"), gamma=hints.get("gamma"), horizon=hints.get("horizon"),
        name=data.get("name", ""), on_error=data.get("on_error", "fail"), raw=dict(data), text=text,
    )


def load_mcap_spec(path: str | PathLike[str]) -> McapSpec:
    path = Path(path)
    try:
        text = path.read_text()
        return parse_mcap_spec(tomllib.loads(text), text, str(path))
    except FileNotFoundError:
        raise SpecError(f"{path}: no such spec file") from None
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{path}: not valid TOML ({exc})") from exc


# ----------------------------------------------------------------------------- reading
def _msg_time(which: str, msg: Any, dec: Any) -> int:
    if which == "log_time":
        return int(msg.log_time)
    if which == "publish_time":
        return int(msg.publish_time)
    return to_ns(get_path(dec, which))


def _records_in_file_order(f: Any, topics: set[str], report: dict[str, Any]):
    """Messages of ``topics`` in file order with a streaming reader (no index or summary
    needed). A truncated or corrupt file stops the stream at the damaged record: every
    complete chunk before it is kept and ``report`` says how much was recovered and from
    which byte offset the rest was lost."""
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    reader = StreamReader(f, validate_crcs=True)
    report["messages"] = 0
    try:
        for rec in reader.records:
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
            elif isinstance(rec, Message):
                ch = channels.get(rec.channel_id)
                if ch is not None and ch.topic in topics:
                    report["messages"] += 1
                    yield schemas.get(ch.schema_id), ch, rec
    except Exception as exc:  # noqa: BLE001 - truncation/corruption surfaces as many library types
        report["damaged"] = f"{type(exc).__name__}: {exc}"
        report["lost_from_offset"] = int(f.tell())


def _decoded_in_file_order(f: Any, topics: set[str], report: dict[str, Any]):
    return _decoded(_records_in_file_order(f, topics, report))


def _read_file(path: Path, spec: McapSpec, on_error: str = "fail") -> dict[str, Any]:
    """Per stream (observation streams by index, ``"action"``, ``"clock"``, ``"episodes"``):
    times and field values, each sorted by its own time."""
    streams = {i: s for i, s in enumerate(spec.streams)}
    streams["action"] = spec.action_stream
    by_topic: dict[str, list[Any]] = {}
    for key, s in streams.items():
        by_topic.setdefault(s.topic, []).append(key)
    by_topic.setdefault(spec.clock_topic, []).append("clock")
    if spec.episode_topic:
        by_topic.setdefault(spec.episode_topic, []).append("episodes")
    data: dict[Any, dict[str, list]] = {k: {"t": []} for ks in by_topic.values() for k in ks}
    counts = {t: 0 for t in by_topic}
    report: dict[str, Any] = {}
    try:
        with open(path, "rb") as f:
            for _sch, ch, msg, dec in _decoded_in_file_order(f, set(by_topic), report):
                counts[ch.topic] += 1
                for key in by_topic[ch.topic]:
                    d = data[key]
                    if key == "episodes":
                        d["t"].append(int(msg.log_time))
                        for k, p in spec.episode_fields.items():
                            d.setdefault(k, []).append(get_path(dec, p))
                    elif key == "clock":
                        d["t"].append(_msg_time(spec.clock_time, msg, dec))
                    else:
                        s = streams[key]
                        d["t"].append(_msg_time(s.time, msg, dec))
                        for name, p in s.fields.items():
                            d.setdefault(name, []).append(float(get_path(dec, p)))
    except (KeyError, AttributeError, IndexError, TypeError, ValueError) as exc:
        raise IngestError(f"{path}: a field path of the spec does not match the messages ({type(exc).__name__}: {exc}); "
                          "run `offline-adp mcap-info` to list the fields") from exc
    except IngestError:
        raise
    except Exception as exc:  # noqa: BLE001 - library errors become ours, naming the file
        raise IngestError(f"{path}: cannot read as MCAP ({type(exc).__name__}: {exc})") from exc
    if "damaged" in report:
        msg = (f"recovered {report['messages']} messages of file {path}, lost from offset {report['lost_from_offset']} "
               f"({report['damaged']})")
        if on_error == "fail":
            raise IngestError(msg + "; re-run with --on-error quarantine to keep what was recovered")
        import warnings

        warnings.warn(msg, stacklevel=3)
    missing = [t for t in by_topic if counts[t] == 0 and t != spec.episode_topic]
    if missing:
        raise IngestError(f"{path}: no decodable messages on needed topic(s) {missing}")
    out: dict[Any, Any] = {}
    for key, d in data.items():
        order = np.argsort(np.asarray(d["t"], dtype=np.int64), kind="stable")  # sort per stream, not the whole file
        out[key] = {k: np.asarray(v)[order] for k, v in d.items()}
    out["__counts"] = counts
    out["__report"] = report
    return out


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


def ingest_mcap(
    files: Sequence[str | PathLike[str]],
    spec: McapSpec | str | PathLike[str],
    out: str | PathLike[str] | None = None,
    *,
    on_error: str | None = None,
    overwrite: bool = False,
) -> tuple[TransitionDataset, dict[str, Any]]:
    """Ingest MCAP files into a dataset (written to ``out`` when given); returns it and a summary."""
    if not isinstance(spec, McapSpec):
        spec = load_mcap_spec(spec)
    if out is not None and Path(out).exists() and not overwrite:
        raise IngestError(f"{out} already exists; pass overwrite=True (CLI: --overwrite) to replace it")
    on_error = on_error or spec.on_error
    obs_names = [n for s in spec.streams for n in s.fields]
    rows: dict[str, list] = {k: [] for k in ("ep", "src", "step", "t", "obs", "act", "next", "term", "trunc", "file", "row")}
    summary: dict[str, Any] = {"files": [], "dropped_steps": 0}
    paths = [Path(p) for p in files]
    if not paths:
        raise IngestError("no MCAP files given")
    for fi, path in enumerate(paths):
        if not path.is_file():
            raise IngestError(f"{path}: no such file")
        d = _read_file(path, spec, on_error)
        summary["files"].append({"path": str(path), "sha256": sha256_file(path), "messages_used": d["__counts"],
                                 **({"recovered": d["__report"]} if "damaged" in d["__report"] else {})})
        tclk = d["clock"]["t"]
        # episodes: between start/end events, else split on gaps of the clock
        if spec.episode_topic:
            ev = d["episodes"]
            kind = ev.get("event_field", np.array([]))
            starts = np.flatnonzero(kind == "start")
            bounds = []
            for k in starts:
                ends = np.flatnonzero((kind == "end") & (np.arange(len(kind)) > k))
                if not len(ends):  # the log stops inside this episode (cut or crashed recording)
                    summary["incomplete_episodes"] = summary.get("incomplete_episodes", 0) + 1
                    continue
                e = ends[0]
                bounds.append((ev["t"][k], ev["t"][e], str(ev.get("id_field", [f"{path.stem}-{k}"] * len(kind))[k]),
                               bool(ev["terminated_field"][e]) if "terminated_field" in ev else False,
                               str(ev["source_field"][k]) if "source_field" in ev else spec.source_value))
        else:
            gaps = np.flatnonzero(np.diff(tclk) > spec.gap * 1e9)
            edges = np.r_[0, gaps + 1, len(tclk)]
            bounds = [(tclk[a], tclk[b - 1], f"{path.stem}-{i:05d}", False, spec.source_value) for i, (a, b) in enumerate(zip(edges[:-1], edges[1:], strict=True))]
        for t0, t1, ep_id, terminated, source in bounds:
            sel = (tclk >= t0) & (tclk <= t1)
            times = tclk[sel]
            if len(times) < 2:
                continue
            cols, ok = [], np.ones(len(times), bool)
            for si, s in enumerate(spec.streams):
                st = d[si]
                for name in s.fields:
                    v, good = _align(st["t"], st[name], times, s)
                    if s.missing == "fill":
                        v = np.where(good, v, s.fill)
                    elif s.missing == "error" and not good.all():
                        k = int(np.flatnonzero(~good)[0])
                        raise IngestError(f"{path}: episode {ep_id}, step {k}: no {s.topic} message within max_age = {s.max_age} s "
                                          f"for {name!r} (use missing = 'fill' or 'drop_step')")
                    else:
                        ok &= good
                    cols.append(v)
            a_st = d["action"]
            av, agood = _align(a_st["t"], a_st["action"], times, spec.action_stream)
            obs = np.column_stack(cols)
            keep = ok.copy()
            keep[-1] = ok[-1]
            summary["dropped_steps"] += int((~keep).sum())
            obs, av, agood, times_k = obs[keep], av[keep], agood[keep], times[keep]
            n = len(obs) - 1
            if n < 1:
                continue
            if not agood[:n].all():
                k = int(np.flatnonzero(~agood[:n])[0])
                raise IngestError(f"{path}: episode {ep_id}, step {k}: no {spec.action_stream.topic} command within max_age = "
                                  f"{spec.action_stream.max_age} s")
            rows["ep"] += [ep_id] * n
            rows["src"] += [source] * n
            rows["step"].append(np.arange(n))
            rows["t"].append(times_k[:n])
            rows["obs"].append(obs[:-1])
            rows["next"].append(obs[1:])
            rows["act"].append(av[:n])
            term = np.zeros(n, bool)
            term[-1] = terminated
            rows["term"].append(term)
            tr = np.zeros(n, bool)
            tr[-1] = not terminated
            rows["trunc"].append(tr)
            rows["file"] += [fi] * n
    if not rows["obs"]:
        raise IngestError(f"no episode with at least one transition in {[str(p) for p in paths]}")
    obs = np.vstack(rows["obs"])
    nxt = np.vstack(rows["next"])
    raw_action = np.concatenate(rows["act"])
    if spec.action.type == "discrete":
        action, atable = map_discrete(raw_action, spec.action)
    else:
        action, atable = bin_continuous(raw_action, spec.action)
    term = np.concatenate(rows["term"])
    cost = np.zeros(len(obs))
    for t in spec.cost_terms:
        name, op, w = t["field"], t.get("op", "abs"), float(t.get("weight", 1.0))
        if name == "action":
            x = atable.values[action, 0]
        else:
            if name not in obs_names:
                raise SpecError(f"cost term field {name!r} is not an observation name {obs_names} or 'action'")
            x = (nxt if t.get("at", "step") == "next" else obs)[:, obs_names.index(name)]
        cost += w * (np.abs(x) if op == "abs" else x * x if op == "square" else x)
    if spec.terminal_cost is not None:
        cost = np.where(term, spec.terminal_cost, cost)
    info = DatasetInfo(
        features=tuple(Feature(n) for n in obs_names), action_table=atable, gamma=spec.gamma, horizon=spec.horizon,
        propensity_source="unknown", name=spec.name,
        provenance={"inputs": summary["files"], "spec": spec.raw, "package_version": __version__,
                    "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"), "generator": "offline-adp ingest mcap"},
    )
    ds = TransitionDataset.from_arrays(
        info, episode_id=np.asarray(rows["ep"]), step=np.concatenate(rows["step"]), obs=obs, action=action, cost=cost,
        next_obs=nxt, terminated=term, truncated=np.concatenate(rows["trunc"]), source=np.asarray(rows["src"]),
        t_ns=np.concatenate(rows["t"]),
    )
    report = validate(ds)
    summary["doctor"] = report.summary()
    if not report.ok:
        if on_error == "fail":
            raise ValidationError(report.to_text(), report)
        ds, q = split_quarantine(ds, report)
        summary["quarantined_rows"] = q.num_rows
    if out is not None:
        write_dataset(ds, out, overwrite=overwrite, extra_meta={"ingest": summary})
    summary.update(episodes=ds.n_episodes, transitions=len(ds), per_source=ds.source_counts())
    return ds, summary
