"""Message decoding (JSON, ROS 2 CDR, protobuf), field paths and message times."""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from typing import Any


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



def _msg_time(which: str, msg: Any, dec: Any) -> int:
    if which == "log_time":
        return int(msg.log_time)
    if which == "publish_time":
        return int(msg.publish_time)
    return to_ns(get_path(dec, which))
