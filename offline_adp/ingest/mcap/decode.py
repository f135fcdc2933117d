"""Message decoding (JSON, ROS 2 CDR, protobuf), field paths and message times."""

from __future__ import annotations

import functools
import json
import math
import re
from typing import Any

import numpy as np

from offline_adp.errors import IngestError


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
        self.errors: dict[tuple[str, int | None], str] = {}

    def __call__(self, sch: Any, ch: Any) -> Any:
        """The decoder, None if no installed decoder reads the encoding; a schema a decoder
        cannot parse (e.g. a ROS 2 service definition with ``---``) is an IngestError
        naming the topic and schema."""
        key = (ch.message_encoding, None if sch is None else sch.id)
        try:
            return self.cache[key]
        except KeyError:
            pass
        if key in self.errors:
            raise IngestError(self.errors[key])
        try:
            d = self.cache[key] = next((d for fac in self.factories
                                        if (d := fac.decoder_for(ch.message_encoding, sch)) is not None), None)
        except Exception as exc:  # noqa: BLE001 - schema parse errors of many library types
            self.errors[key] = (f"topic {ch.topic!r}: its schema {getattr(sch, 'name', '')!r} "
                                f"({getattr(sch, 'encoding', '')}) cannot be parsed ({type(exc).__name__}: {exc})")
            raise IngestError(self.errors[key]) from None
        return d


_TOKEN = re.compile(r"([^.\[\]]+)|\[(\d+)\]|\[([^=\[\]]+)=([^\[\]]*)\]")
#: A whole field path: names joined by dots, list indices ``[2]`` and selectors ``[key=value]``.
_PATH = re.compile(r"(?:[^.\[\]]+|\[\d+\]|\[[^=\[\]]+=[^\[\]]*\])(?:\.[^.\[\]]+|\[\d+\]|\[[^=\[\]]+=[^\[\]]*\])*")


class NoElement(Exception):
    """A selector ``[key=value]`` of a field path matched no element of the message's list:
    the message is not the stream's (e.g. a /tf message of another frame pair). ``seen``:
    the values of ``key`` the list held."""

    def __init__(self, text: str, seen: tuple[str, ...] = ()) -> None:
        super().__init__(text)
        self.seen = seen


def check_path(path: str) -> str | None:
    """Why ``path`` is no field path (None: it is one). A path is names joined by dots, with
    list indices (``transforms[0]``) and selectors (``transforms[child_frame_id=base_link]``:
    the one element whose field ``child_frame_id`` is ``base_link``; the key may be a dotted
    path itself: ``transforms[header.frame_id=odom]``)."""
    if not isinstance(path, str):
        return f"expected a string, got {type(path).__name__}"
    rule = ("names joined by dots, with list indices [0] or selectors [key=value], e.g. "
            "'transforms[child_frame_id=base_link].transform.translation.x'")
    if not _PATH.fullmatch(path):
        at = next((i for i in range(len(path), -1, -1) if _PATH.fullmatch(path[:i])), 0)
        return f"not {rule}: it goes wrong at character {at + 1} ({path[at:at + 12]!r})"
    for key, _ in _SELECTOR.findall(path):
        if any(not part.strip() for part in key.split(".")):
            return f"the selector key {key!r} is not names joined by dots ({rule})"
    return None


#: A selector's key and value in a path.
_SELECTOR = re.compile(r"\[([^=\[\]]+)=([^\[\]]*)\]")


@functools.lru_cache(maxsize=4096)
def _steps_of(path: str) -> tuple[tuple[str, int | None, str | None], ...]:
    out = []
    for name, index, key, value in _TOKEN.findall(path):
        if key:
            v = value.strip()
            if len(v) >= 2 and v[0] == v[-1] and v[0] in "'\"":
                v = v[1:-1]  # a quoted value: [child_frame_id="base_link"]
            out.append((".".join(part.strip() for part in key.split(".")), None, v))
        else:
            out.append((name, int(index) if index else None, None))
    return tuple(out)


def _child(cur: Any, name: str) -> Any:
    return cur[name] if isinstance(cur, dict) else getattr(cur, name)


_ABSENT = object()


def _key_of(el: Any, key: str) -> Any:
    """An element's value at ``key`` (a dotted path), or _ABSENT where it has no such field."""
    cur = el
    for name in key.split("."):
        try:
            cur = _child(cur, name)
        except (KeyError, AttributeError, TypeError):
            return _ABSENT
    return cur


def _matches(v: Any, value: str) -> bool:
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, str):
        return v == value
    if isinstance(v, bool):  # true/false only: "1" is a number, and a list may hold both
        return value.lower() == ("true" if v else "false")
    if isinstance(v, int | float):
        try:
            return float(v) == float(value)
        except ValueError:
            return False
    return False


def _select(cur: Any, key: str, value: str, path: str) -> Any:
    """The one element of list ``cur`` whose field ``key`` is ``value`` (an element without
    that field is not it)."""
    if isinstance(cur, str | bytes | bytearray | dict):
        raise TypeError(f"[{key}={value}] selects from a list, and this is {type(cur).__name__}")
    try:
        seq = list(cur)  # lists, tuples, numpy arrays, protobuf repeated fields (sequence protocol)
    except TypeError:
        raise TypeError(f"[{key}={value}] selects from a list, and this is {type(cur).__name__}") from None
    keys = [_key_of(el, key) for el in seq]
    hits = [el for el, v in zip(seq, keys, strict=True) if v is not _ABSENT and _matches(v, value)]
    if not hits:
        raise NoElement(f"no element with {key} = {value!r} in {path!r}",
                        tuple(str(v.item() if isinstance(v, np.generic) else v) for v in keys if v is not _ABSENT))
    if len(hits) > 1:
        raise ValueError(f"{len(hits)} elements have {key} = {value!r} (a selector must pick one)")
    return hits[0]


def get_path(msg: Any, path: str) -> Any:
    """Value at a dotted path with list indices (``transforms[0].transform.translation.x``)
    and selectors (``transforms[child_frame_id=base_link].transform.translation.x``: the one
    element whose ``child_frame_id`` is ``base_link``; none: :class:`NoElement`, several: a
    ValueError)."""
    cur = msg
    for name, index, value in _steps_of(path):
        if value is not None:
            cur = _select(cur, name, value, path)
        elif index is not None:
            cur = cur[index]
        else:
            cur = _child(cur, name)
    return cur


def to_ns(value: Any) -> int:
    """A time value in ns: ``{sec, nanosec}`` (ROS 2 ``builtin_interfaces/Time``),
    ``{sec, nsec}`` / ``{secs, nsecs}`` (ROS 1), ``{seconds, nanos}``
    (``google.protobuf.Timestamp``), or float seconds."""
    for s, n in (("sec", "nanosec"), ("sec", "nsec"), ("secs", "nsecs"), ("seconds", "nanos")):
        if isinstance(value, dict) and s in value:
            return int(value[s]) * 1_000_000_000 + int(value.get(n, 0))
        if hasattr(value, s):
            return int(getattr(value, s)) * 1_000_000_000 + int(getattr(value, n, 0))
    return int(round(float(value) * 1e9))


def _is_proto(msg: Any) -> bool:
    return hasattr(msg, "DESCRIPTOR") and hasattr(msg, "ListFields") and hasattr(msg.DESCRIPTOR, "fields")


def field_values(msg: Any, prefix: str = "", depth: int = 0) -> list[tuple[str, Any]]:
    """(leaf field path, value) of a decoded message: dicts (JSON), ROS 2 objects,
    protobuf messages (by their real field names); lists by their first element."""
    if depth > 8:
        return [(prefix, msg)]
    if isinstance(msg, dict):
        items = list(msg.items())
    elif _is_proto(msg):
        items = []
        for f in msg.DESCRIPTOR.fields:
            v = getattr(msg, f.name)
            if not _is_proto(v) and hasattr(v, "__len__") and not isinstance(v, str | bytes):
                v = list(v)  # a repeated field: its first element, or an empty list
            items.append((f.name, v))
    elif isinstance(msg, list | tuple) or (hasattr(msg, "__len__") and hasattr(msg, "__getitem__")
                                           and not isinstance(msg,
                                                              str | bytes | bytearray)
                                                              and not hasattr(msg, "__slots__")):
        seq = list(msg)
        if not seq:
            return [(f"{prefix}[0]", None)]
        return field_values(seq[0], f"{prefix}[0]", depth + 1)
    elif hasattr(msg, "__slots__") or (hasattr(msg, "__dict__") and not isinstance(msg, type)):
        names = getattr(msg, "__slots__", None) or [k for k in vars(msg) if not k.startswith("_")]
        items = [(k, getattr(msg, k)) for k in names]
    else:
        return [(prefix, msg)]
    out: list[tuple[str, Any]] = []
    for k, v in items:
        out += field_values(v, f"{prefix}.{k}" if prefix else str(k), depth + 1)
    return out


def field_paths(msg: Any, prefix: str = "", depth: int = 0) -> list[str]:
    """Leaf field paths of a decoded message (for ``mcap-info``)."""
    return [p for p, _ in field_values(msg, prefix, depth)]


def _msg_time(which: str, log_time: int, publish_time: int, dec: Any) -> int:
    if which == "log_time":
        return int(log_time)
    if which == "publish_time":
        return int(publish_time)
    return to_ns(get_path(dec, which))


def yaw_of(q: Any) -> float:
    """The heading (rad, in [-pi, pi]) of the quaternion ``q`` (fields x, y, z, w): the
    rotation about z of its z-y'-x'' (yaw, pitch, roll) angles,
    ``atan2(2 (w z + x y), w^2 + x^2 - y^2 - z^2)``. The same for ``q`` and ``-q`` (one
    rotation, two quaternions) and for any positive scale of ``q``; NaN (a missing value)
    for a zero or non-finite quaternion."""
    parts = [_child(q, n) for n in "xyzw"]
    if any(v is None for v in parts):  # a JSON null: a missing value, as for a plain field
        return float("nan")
    x, y, z, w = (float(v.item() if isinstance(v, np.generic) else v) for v in parts)
    big = max(abs(x), abs(y), abs(z), abs(w))
    if not np.isfinite(big) or big == 0.0:
        return float("nan")
    x, y, z, w = x / big, y / big, z / big, w / big  # any scale: no underflow or overflow in the squares
    return math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)


#: Derived fields: ``{ yaw_of = "pose.pose.orientation" }`` in place of a field path.
DERIVED = {"yaw_of": yaw_of}


def field_value(dec: Any, path: str | dict[str, str]) -> Any:
    """The value of a spec field: at a field path, or derived (``{ yaw_of = path }``)."""
    if isinstance(path, dict):
        (how, inner), = path.items()
        return DERIVED[how](get_path(dec, inner))
    return get_path(dec, path)


def numeric_fields(dec: Any, fields: dict[str, Any], topic: str, log_time: int, command: bool = False) -> list[float]:
    """The float value of each field path in a decoded message; a null (JSON ``null``) is a
    missing value, NaN (the doctor reports it, naming the row; quarantine sets that episode
    aside); a path the message lacks, a value that is no number, an integer that float64
    cannot hold exactly (beyond 2^53) and, for a continuous ``command``, a boolean (as the
    tables refuse them; a discrete one may be a flag) are errors naming the topic, the
    message's log_time and the field."""
    out = []
    for name, path in fields.items():
        try:
            v = field_value(dec, path)
            if isinstance(v, np.generic):
                v = v.item()
            if command and isinstance(v, bool):
                raise TypeError(f"{v!r} is a boolean, not a continuous command (a flag is a discrete action)")
            if isinstance(v, int) and not isinstance(v, bool) and abs(v) > 2**53:
                raise ValueError(f"the integer {v} is beyond 2^53, where float64 would round it")
            out.append(float("nan") if v is None else float(v))
        except (KeyError, AttributeError, IndexError, TypeError, ValueError, OverflowError) as exc:
            raise IngestError(f"topic {topic!r}, message at log_time {int(log_time)}: field {name!r} (path {path!r}) "
                              f"cannot be read as a number ({type(exc).__name__}: {exc}); run `offline-adp "
                              "mcap-info` to list the fields") from None
    return out
