"""Ingestion spec for Parquet/CSV tables (TOML) as frozen dataclasses, checked on load.

Every table of the spec accepts only its documented keys; an unknown key fails with
the list of valid ones. ``docs/ingestion-spec.md`` documents each key with examples.
"""

from __future__ import annotations

import hashlib
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path
from typing import Any

from offline_adp.errors import SpecError

TIME_UNITS = {"s": 1_000_000_000, "ms": 1_000_000, "us": 1_000, "ns": 1}


def _check_keys(table: Mapping[str, Any], allowed: set[str], where: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise SpecError(f"{where}: unknown key(s) {unknown}; valid keys are {sorted(allowed)}")


def _get(table: Mapping[str, Any], key: str, typ: type | tuple[type, ...], where: str, default: Any = None, required: bool = False) -> Any:
    if key not in table:
        if required:
            raise SpecError(f"{where}: missing required key {key!r}")
        return default
    v = table[key]
    if typ is float and isinstance(v, int) and not isinstance(v, bool):
        v = float(v)
    if not isinstance(v, typ) or (isinstance(v, bool) and typ is not bool):
        tn = typ.__name__ if isinstance(typ, type) else " or ".join(t.__name__ for t in typ)
        raise SpecError(f"{where}.{key}: expected {tn}, got {type(v).__name__} {v!r}")
    return v


def _str_list(table: Mapping[str, Any], key: str, where: str, required: bool = False) -> tuple[str, ...]:
    v = _get(table, key, list, where, default=[], required=required)
    if not all(isinstance(x, str) for x in v):
        raise SpecError(f"{where}.{key}: expected a list of column names (strings), got {v!r}")
    return tuple(v)


@dataclass(frozen=True)
class EpisodeSpec:
    id: str
    step: str | None = None
    step_base: int = 0
    order: str | None = None
    time: str | None = None
    time_unit: str = "ns"


@dataclass(frozen=True)
class ObservationSpec:
    columns: tuple[str, ...]
    next_columns: tuple[str, ...] = ()
    names: tuple[str, ...] = ()
    units: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class ActionSpec:
    column: str
    type: str = "discrete"
    values: tuple[Any, ...] | None = None
    names: tuple[str, ...] | None = None
    edges: tuple[float, ...] | None = None
    n_bins: int | None = None
    bin_value: str = "mean"
    dim: str = "a"
    unit: str = ""
    vectors: tuple[tuple[float, ...], ...] | None = None
    dims: tuple[str, ...] | None = None


@dataclass(frozen=True)
class ParquetSpec:
    """A parsed Parquet/CSV ingestion spec (see ``docs/ingestion-spec.md``)."""

    kind: str
    episode: EpisodeSpec
    observations: ObservationSpec
    action: ActionSpec
    cost_column: str | None = None
    reward_column: str | None = None
    terminated_column: str | None = None
    truncated_column: str | None = None
    source_column: str | None = None
    source_value: str = "unknown"
    propensity_column: str | None = None
    gamma: float | None = None
    horizon: int | None = None
    format: str = "auto"
    name: str = ""
    on_error: str = "fail"
    csv_delimiter: str = ","
    raw: Mapping[str, Any] = field(default_factory=dict, compare=False)
    text: str = field(default="", compare=False)

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.text.encode()).hexdigest()

    def needed_columns(self) -> list[str]:
        cols = [self.episode.id, *self.observations.columns, *self.observations.next_columns, self.action.column]
        for c in (
            self.episode.step,
            self.episode.order,
            self.episode.time,
            self.cost_column,
            self.reward_column,
            self.terminated_column,
            self.truncated_column,
            self.source_column,
            self.propensity_column,
        ):
            if c:
                cols.append(c)
        return list(dict.fromkeys(cols))


_TOP = {"kind", "format", "name", "on_error", "episode", "observations", "action", "cost", "end", "source", "propensity", "hints", "csv"}


def parse_parquet_spec(data: Mapping[str, Any], text: str = "", where: str = "spec") -> ParquetSpec:
    """Check and convert a spec mapping (from TOML) into a :class:`ParquetSpec`."""
    _check_keys(data, _TOP, where)
    kind = _get(data, "kind", str, where, "transitions")
    if kind not in ("transitions", "steps"):
        raise SpecError(f"{where}.kind: expected 'transitions' or 'steps', got {kind!r}")
    fmt = _get(data, "format", str, where, "auto")
    if fmt not in ("auto", "parquet", "csv"):
        raise SpecError(f"{where}.format: expected 'auto', 'parquet' or 'csv', got {fmt!r}")
    on_error = _get(data, "on_error", str, where, "fail")
    if on_error not in ("fail", "quarantine"):
        raise SpecError(f"{where}.on_error: expected 'fail' or 'quarantine', got {on_error!r}")

    e = _get(data, "episode", dict, where, required=True)
    w = f"{where}.episode"
    _check_keys(e, {"id", "step", "step_base", "order", "time", "time_unit"}, w)
    ep = EpisodeSpec(
        id=_get(e, "id", str, w, required=True),
        step=_get(e, "step", str, w),
        step_base=_get(e, "step_base", int, w, 0),
        order=_get(e, "order", str, w),
        time=_get(e, "time", str, w),
        time_unit=_get(e, "time_unit", str, w, "ns"),
    )
    if ep.time_unit not in TIME_UNITS:
        raise SpecError(f"{w}.time_unit: expected one of {list(TIME_UNITS)}, got {ep.time_unit!r}")
    if ep.step and ep.order:
        raise SpecError(f"{w}: give either 'step' (an integer step column) or 'order' (any sortable column), not both")
    if not (ep.step or ep.order or ep.time):
        raise SpecError(f"{w}: rows need an ordering within episodes: give 'step', 'order' or 'time'")

    o = _get(data, "observations", dict, where, required=True)
    w = f"{where}.observations"
    _check_keys(o, {"columns", "next_columns", "names", "units"}, w)
    obs = ObservationSpec(
        columns=_str_list(o, "columns", w, required=True),
        next_columns=_str_list(o, "next_columns", w),
        names=_str_list(o, "names", w),
        units=_get(o, "units", dict, w, {}),
    )
    if not obs.columns:
        raise SpecError(f"{w}.columns: list at least one observation column")
    if obs.next_columns and len(obs.next_columns) != len(obs.columns):
        raise SpecError(f"{w}: next_columns has {len(obs.next_columns)} entries, columns has {len(obs.columns)}")
    if obs.names and len(obs.names) != len(obs.columns):
        raise SpecError(f"{w}: names has {len(obs.names)} entries, columns has {len(obs.columns)}")
    if kind == "transitions" and not obs.next_columns:
        raise SpecError(f"{w}.next_columns: required for kind = 'transitions' (or use kind = 'steps')")
    unknown_units = set(obs.units) - set(obs.names or obs.columns)
    if unknown_units:
        raise SpecError(f"{w}.units: keys {sorted(unknown_units)} are not observation names {list(obs.names or obs.columns)}")

    a = _get(data, "action", dict, where, required=True)
    w = f"{where}.action"
    _check_keys(a, {"column", "type", "values", "names", "edges", "n_bins", "bin_value", "dim", "unit", "vectors", "dims"}, w)
    vectors = _get(a, "vectors", list, w)
    dims = _get(a, "dims", list, w)
    values = _get(a, "values", list, w)
    names = _get(a, "names", list, w)
    edges = _get(a, "edges", list, w)
    act = ActionSpec(
        column=_get(a, "column", str, w, required=True),
        type=_get(a, "type", str, w, "discrete"),
        values=tuple(values) if values is not None else None,
        names=tuple(str(n) for n in names) if names is not None else None,
        edges=tuple(float(x) for x in edges) if edges is not None else None,
        n_bins=_get(a, "n_bins", int, w),
        bin_value=_get(a, "bin_value", str, w, "mean"),
        dim=_get(a, "dim", str, w, "a"),
        unit=_get(a, "unit", str, w, ""),
        vectors=tuple(tuple(float(x) for x in (v if isinstance(v, list) else [v])) for v in vectors) if vectors is not None else None,
        dims=tuple(str(d) for d in dims) if dims is not None else None,
    )
    if act.vectors is not None:
        if act.values is None or len(act.vectors) != len(act.values):
            raise SpecError(f"{w}.vectors: give one value vector per entry of 'values'")
        if len({len(v) for v in act.vectors}) != 1 or (act.dims is not None and len(act.dims) != len(act.vectors[0])):
            raise SpecError(f"{w}.vectors: all vectors need the same length, matching 'dims'")
    if act.type not in ("discrete", "continuous"):
        raise SpecError(f"{w}.type: expected 'discrete' or 'continuous', got {act.type!r}")
    if act.type == "continuous":
        if (act.edges is None) == (act.n_bins is None):
            raise SpecError(f"{w}: a continuous action needs exactly one of 'edges' or 'n_bins'")
        if act.edges is not None and (len(act.edges) < 2 or list(act.edges) != sorted(act.edges)):
            raise SpecError(f"{w}.edges: need at least two increasing edges, got {list(act.edges)}")
        if act.n_bins is not None and act.n_bins < 1:
            raise SpecError(f"{w}.n_bins: must be >= 1, got {act.n_bins}")
        if act.bin_value not in ("mean", "center"):
            raise SpecError(f"{w}.bin_value: expected 'mean' or 'center', got {act.bin_value!r}")
        if act.values is not None:
            raise SpecError(f"{w}.values: only for discrete actions (continuous ones are binned)")
    elif act.edges is not None or act.n_bins is not None:
        raise SpecError(f"{w}: 'edges'/'n_bins' bin continuous actions; set type = 'continuous'")
    if act.names is not None and act.values is not None and len(act.names) != len(act.values):
        raise SpecError(f"{w}: names has {len(act.names)} entries, values has {len(act.values)}")

    c = _get(data, "cost", dict, where, required=True)
    w = f"{where}.cost"
    _check_keys(c, {"column", "reward"}, w)
    cost_col, reward_col = _get(c, "column", str, w), _get(c, "reward", str, w)
    if (cost_col is None) == (reward_col is None):
        raise SpecError(f"{w}: give exactly one of 'column' (a cost, lower is better) or 'reward' (negated)")

    end = _get(data, "end", dict, where, {})
    w = f"{where}.end"
    _check_keys(end, {"terminated", "truncated"}, w)
    src = _get(data, "source", dict, where, {})
    w = f"{where}.source"
    _check_keys(src, {"column", "value"}, w)
    if "column" in src and "value" in src:
        raise SpecError(f"{w}: give either 'column' or 'value', not both")
    prop = _get(data, "propensity", dict, where, {})
    _check_keys(prop, {"column"}, f"{where}.propensity")
    hints = _get(data, "hints", dict, where, {})
    _check_keys(hints, {"gamma", "horizon"}, f"{where}.hints")
    csv = _get(data, "csv", dict, where, {})
    _check_keys(csv, {"delimiter"}, f"{where}.csv")
    return ParquetSpec(
        kind=kind,
        episode=ep,
        observations=obs,
        action=act,
        cost_column=cost_col,
        reward_column=reward_col,
        terminated_column=_get(end, "terminated", str, f"{where}.end"),
        truncated_column=_get(end, "truncated", str, f"{where}.end"),
        source_column=_get(src, "column", str, f"{where}.source"),
        source_value=_get(src, "value", str, f"{where}.source", "unknown"),
        propensity_column=_get(prop, "column", str, f"{where}.propensity"),
        gamma=_get(hints, "gamma", float, f"{where}.hints"),
        horizon=_get(hints, "horizon", int, f"{where}.hints"),
        format=fmt,
        name=_get(data, "name", str, where, ""),
        on_error=on_error,
        csv_delimiter=_get(csv, "delimiter", str, f"{where}.csv", ","),
        raw=dict(data),
        text=text,
    )


def load_parquet_spec(path: str | PathLike[str]) -> ParquetSpec:
    """Read and check a TOML spec file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise SpecError(f"{path}: cannot read spec ({exc.strerror})") from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{path}: not valid TOML ({exc})") from exc
    return parse_parquet_spec(data, text=text, where=str(path))


__all__ = ["ParquetSpec", "EpisodeSpec", "ObservationSpec", "ActionSpec", "parse_parquet_spec", "load_parquet_spec"]
