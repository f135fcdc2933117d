"""The MCAP ingestion spec (TOML) as frozen dataclasses, checked on load."""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.errors import SpecError
from offline_adp.ingest.spec import ActionSpec, _check_keys

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
    fields: dict[str, Any]  # name -> a field path, or a derived field ({ yaw_of = path })
    time: str = "log_time"
    align: str = "nearest"
    max_age: float = 0.1
    missing: str = "error"
    fill: float = 0.0
    role: str = "obs"
    units: dict[str, str] = field(default_factory=dict)  # unit per field name (features keep it)


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
    action_bins: dict[str, Any] = field(default_factory=dict)  # vector continuous actions: per component
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
_STREAM_KEYS = {"topic", "fields", "time", "align", "max_age", "missing", "fill", "role", "units"}
_ACTION_KEYS = {"topic", "field", "fields", "time", "align", "max_age", "missing", "fill", "type", "values", "names",
                "edges", "n_bins", "bin_value", "dim", "dims", "unit", "units", "vectors", "low", "high"}


def _stream(d: dict[str, Any], where: str, fields_required: bool = True) -> StreamSpec:
    _check_keys(d, _STREAM_KEYS | ({"field"} if not fields_required else set()), where)
    if "topic" not in d:
        raise SpecError(f"{where}: missing required key 'topic'")
    s = StreamSpec(topic=d["topic"], fields=dict(d.get("fields", {})), time=d.get("time", "log_time"),
                   align=d.get("align", "nearest"), max_age=float(d.get("max_age", 0.1)),
                   missing=d.get("missing", "error"), fill=float(d.get("fill", 0.0)), role=d.get("role", "obs"),
                   units=dict(d.get("units", {})))
    if not set(s.units) <= set(s.fields):
        raise SpecError(f"{where}.units: {sorted(set(s.units) - set(s.fields))} are not fields of this stream "
                        f"{sorted(s.fields)}")
    if s.align not in _ALIGN:
        raise SpecError(f"{where}.align: expected one of {list(_ALIGN)}, got {s.align!r}")
    if s.missing not in ("fill", "drop_step", "error"):
        raise SpecError(f"{where}.missing: expected 'fill', 'drop_step' or 'error', got {s.missing!r}")
    if s.role not in ROLES:
        raise SpecError(f"{where}.role: expected one of {list(ROLES)}, got {s.role!r}")
    if fields_required and not s.fields:
        raise SpecError(f"{where}.fields: map at least one name to a field path")
    for n, p in s.fields.items():
        if isinstance(p, dict):  # a derived field: { yaw_of = "pose.pose.orientation" }
            if len(p) != 1 or next(iter(p)) not in ("yaw_of",) or not isinstance(next(iter(p.values())), str):
                raise SpecError(f"{where}.fields.{n}: expected a field path or {{ yaw_of = \"path\" }} (the heading of "
                                f"the quaternion there, in rad), got {p!r}")
            if s.units.setdefault(n, "rad") != "rad":
                raise SpecError(f"{where}.units.{n}: a heading from {{ yaw_of = ... }} is in rad, not "
                                f"{s.units[n]!r} (the unit labels the values; it does not convert them)")
    _check_paths({**{f"fields.{n}": next(iter(p.values())) if isinstance(p, dict) else p
                     for n, p in s.fields.items()}, "time": s.time}, where)
    return s


def _check_paths(paths: dict[str, Any], where: str) -> None:
    """Each field path is one (names, list indices, selectors), checked before any file is read."""
    from offline_adp.ingest.mcap.decode import check_path

    for key, path in paths.items():
        if path in ("log_time", "publish_time"):
            continue
        if (why := check_path(path)) is not None:
            raise SpecError(f"{where}.{key}: {path!r} is no field path: {why}")


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


def _vector_action(a: dict[str, Any], dims: list[str], where: str) -> tuple[ActionSpec, dict[str, Any]]:
    """A vector action (several fields): ``discrete`` with ``vectors`` (the table's value
    vectors, matched component-wise), or ``continuous``: kept as logged (no ``edges`` /
    ``n_bins``; bounds ``low``/``high`` declared or logged) or binned per component into a
    product table (``edges`` / ``n_bins``: one value for every component, or a table per
    component name). ``low``/``high``: one number for every component, a list in the
    order of ``fields``, or a table per component name; ``units`` likewise (or ``unit``)."""
    typ = a.get("type", "discrete")
    if typ not in ("discrete", "continuous"):
        raise SpecError(f"{where}.type: expected 'discrete' or 'continuous', got {typ!r}")
    if "values" in a:
        raise SpecError(f"{where}.values: a vector action lists its actions as vectors = [[...], ...] "
                        f"(one component per field {dims})")
    bins: dict[str, Any] = {}
    if typ == "discrete":
        for key in ("low", "high", "units"):
            if key in a:
                raise SpecError(f"{where}.{key}: only for continuous commands (type = 'continuous')")
        vec = a.get("vectors")
        if not vec or any(not isinstance(v, list) or len(v) != len(dims) for v in vec):
            raise SpecError(f"{where}.vectors: a discrete vector action needs vectors = [[...], ...], each with "
                            f"{len(dims)} components ({dims})")
        try:
            vectors = tuple(tuple(float(x) for x in v) for v in vec)
        except (TypeError, ValueError):
            raise SpecError(f"{where}.vectors: expected numbers, got {vec!r}") from None
    else:
        vectors = None
        if "edges" in a and "n_bins" in a:
            raise SpecError(f"{where}: a continuous vector action takes at most one of edges or n_bins (one for all "
                            f"components, or a table per component {dims}); neither keeps the commands as logged")
        if "names" in a and "edges" not in a and "n_bins" not in a:
            raise SpecError(f"{where}.names: the components of a command kept as logged are named by the keys of "
                            f"fields {dims}")
        for key in ("edges", "n_bins"):
            if key in a:
                v = a[key]
                per = v if isinstance(v, dict) else {d: v for d in dims}
                if set(per) != set(dims):
                    raise SpecError(f"{where}.{key}: give one for each component {dims}, got {sorted(per)}")
                for d, x in per.items():
                    if key == "edges" and (not isinstance(x, list) or len(x) < 2):
                        raise SpecError(f"{where}.edges.{d}: expected at least two bin edges, got {x!r}")
                    if key == "n_bins" and (not isinstance(x, int) or x < 1):
                        raise SpecError(f"{where}.n_bins.{d}: expected a positive integer, got {x!r}")
                bins = {d: {key: per[d]} for d in dims}
    low, high = (_per_component(a.get(k), dims, f"{where}.{k}", number=True) for k in ("low", "high"))
    if low is not None and high is not None and any(lo > hi for lo, hi in zip(low, high, strict=True)):
        raise SpecError(f"{where}: low {list(low)} exceeds high {list(high)}")
    units = _per_component(a.get("units"), dims, f"{where}.units", number=False)
    if units is not None and a.get("unit"):
        raise SpecError(f"{where}: give either 'unit' (one for every component) or 'units' (one per component)")
    names = a.get("names")
    spec = ActionSpec(column="action", type=typ, names=tuple(names) if names else None, vectors=vectors,
                      dims=tuple(dims), unit=str(a.get("unit", "")), bin_value=a.get("bin_value", "mean"),
                      components=tuple(dims), low=low, high=high, units=units)
    return spec, bins


def _per_component(v: Any, dims: list[str], where: str, *, number: bool) -> tuple[Any, ...] | None:
    """One value for every component, a list in component order, or a table per component."""
    if v is None:
        return None
    if isinstance(v, dict):
        if set(v) != set(dims):
            raise SpecError(f"{where}: give one for each component {dims}, got {sorted(v)}")
        v = [v[d] for d in dims]
    elif not isinstance(v, list):
        v = [v] * len(dims)
    if len(v) != len(dims):
        raise SpecError(f"{where}: {len(v)} entries for the {len(dims)} components {dims}")
    ok = (lambda x: isinstance(x, int | float) and not isinstance(x, bool) and np.isfinite(x)) if number else (
        lambda x: isinstance(x, str))
    bad = [x for x in v if not ok(x)]
    if bad:
        raise SpecError(f"{where}: expected {'finite numbers' if number else 'strings'}, got {bad[0]!r}")
    return tuple(float(x) for x in v) if number else tuple(v)


def parse_mcap_spec(data: dict[str, Any], text: str = "", where: str = "spec", base_dir: str = ".") -> McapSpec:
    if isinstance(data, dict) and {"observations", "episode"} & set(data) and not {"clock", "streams"} & set(data):
        raise SpecError(f"{where}: this is a Parquet/CSV ingestion spec ([episode], [observations] ...), not an MCAP "
                        "one ([clock], [[streams]] ...): `offline-adp ingest parquet` reads it (both kinds: "
                        "docs/ingestion-spec.md)")
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
    _check_keys(a, _ACTION_KEYS, f"{where}.action")
    if "topic" not in a or ("field" in a) == ("fields" in a):
        raise SpecError(f"{where}.action: needs 'topic' and either 'field' (one field path) or 'fields' (a vector "
                        "action: {name = path, ...}); valid keys are " + str(sorted(_ACTION_KEYS)))
    if "field" in a:
        act_fields = {"action": a.pop("field")}
    else:
        act_fields = a.pop("fields")
        if isinstance(act_fields, list):
            if not all(isinstance(p, str) for p in act_fields):
                raise SpecError(f"{where}.action.fields: a list names field paths (strings); for a derived "
                                "field give a table: { name = { yaw_of = 'path' } }")
            act_fields = {p: p for p in act_fields}
        if not isinstance(act_fields, dict) or not act_fields:
            raise SpecError(f"{where}.action.fields: map each component name to a field path, e.g. "
                            "{ v = 'linear.x', w = 'angular.z' }")
    act_stream = _stream({k: a.pop(k) for k in list(a) if k in _STREAM_KEYS - {"units"}} | {"fields": act_fields},
                         f"{where}.action", fields_required=False)
    action_bins: dict[str, Any] = {}
    if len(act_fields) == 1:
        from offline_adp.ingest.spec import parse_parquet_spec

        if a.get("type") == "continuous" and "edges" not in a and "n_bins" not in a and "names" not in a:
            a.setdefault("dim", "a")  # the component of a command kept as logged: action_value.a
        action = parse_parquet_spec({"episode": {"id": "e", "step": "k"},
                                     "observations": {"columns": ["x"], "next_columns": ["x"]},
                                     "action": {"column": "action", **a}, "cost": {"column": "c"}}, where=where).action
    else:
        action, action_bins = _vector_action(a, list(act_fields), f"{where}.action")
    cost = data.get("cost") or {}
    _check_keys(cost, {"terms", "terminal_cost", "field", "reward"}, f"{where}.cost")
    terms = tuple(cost.get("terms", []))
    for i, t in enumerate(terms):
        _check_keys(t, {"field", "op", "weight", "at"}, f"{where}.cost.terms[{i}]")
        act_names = ["action"] + ([f"action.{n}" for n in act_fields] if len(act_fields) > 1 else [])
        if t.get("field") not in [*names, *act_names]:
            raise SpecError(f"{where}.cost.terms[{i}].field: {t.get('field')!r} is not a stream field {names} or "
                            f"one of {act_names}")
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
    _check_paths({"time": clock.get("time", "log_time")}, f"{where}.clock")
    _check_paths({k: ep[k] for k in ("id_field", "event_field", "terminated_field", "source_field") if k in ep},
                 f"{where}.episodes")
    terminal_when = _conditions(ep.get("terminal_when"), f"{where}.episodes.terminal_when", names)
    terminal_when += tuple(Condition(n, "!=", 0.0) for s in streams if s.role == "terminal" for n in s.fields)
    on_error = data.get("on_error", "fail")
    if on_error not in ("fail", "quarantine"):
        raise SpecError(f"{where}.on_error: expected 'fail' or 'quarantine', got {on_error!r}")
    return McapSpec(
        clock_topic=clock.get("topic"), clock_time=clock.get("time", "log_time"), streams=streams,
        action_stream=act_stream,
        action=action, action_bins=action_bins, cost_terms=terms, terminal_cost=cost.get("terminal_cost"),
        cost_field=cost_field,
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
    """Read and check an MCAP ingestion spec (a regular file of bounded size, read by the
    one configuration reader, :func:`offline_adp.config.read_config_bytes`)."""
    from offline_adp.config import read_config_bytes

    path = Path(path)
    try:
        raw = read_config_bytes(path, "ingestion spec")
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise SpecError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
        return parse_mcap_spec(tomllib.loads(text), text, str(path), base_dir=str(path.parent))
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{path}: not valid TOML ({exc})") from exc
