"""Ingestion spec for Parquet/CSV tables (TOML): a typed model on the configuration layer.

The file is read with :func:`offline_adp.config.load_toml` (missing file, non-UTF-8 bytes
and TOML syntax errors name the file and line) and validated against
:class:`ParquetSpecModel` with :func:`offline_adp.config.validate_config`: unknown keys
(listing the valid ones), wrong types and bad values (``csv.delimiter = ";;"``,
``action.type = "discret"``, ``hints.gamma = 2``) are one :class:`SpecError` naming the file
and the dotted key. Rules across keys (``step`` or ``order``, ``next_columns`` for
transition tables, one of ``cost.column``/``cost.reward``...) are checked next, with the
same naming. The result is converted to the frozen dataclasses the readers use
(:class:`ParquetSpec`). ``docs/ingestion-spec.md`` documents each key;
``docs/schemas/ingest-spec.schema.json`` is the JSON Schema (:func:`parquet_spec_schema`)
for editors.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from os import PathLike
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, field_validator

from offline_adp.config import (
    ConfigModel,
    did_you_mean,
    json_schema,
    load_toml,
    read_config_bytes,
    validate_config,
)
from offline_adp.errors import SpecError

TIME_UNITS = {"s": 1_000_000_000, "ms": 1_000_000, "us": 1_000, "ns": 1}


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
    """The ``[action]`` table: where the logged command is and how it becomes actions.

    ``column`` is one column (a scalar, or for a continuous command a list column whose
    lists hold the components); ``columns`` several scalar columns forming one vector
    command (then ``column`` is ``""``). For continuous commands ``components`` names the
    components (``None``: from the columns, see :meth:`component_names`), ``units`` their
    units and ``low``/``high`` their declared bounds (``None``: the logged range).
    ``type_declared`` is whether the spec gave ``type`` (a list column without it is a
    continuous command).
    """

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
    columns: tuple[str, ...] = ()
    components: tuple[str, ...] | None = None
    units: tuple[str, ...] | None = None
    low: tuple[float, ...] | None = None
    high: tuple[float, ...] | None = None
    type_declared: bool = True
    dim_declared: bool = True

    @property
    def source_columns(self) -> tuple[str, ...]:
        """The input columns holding the command."""
        return self.columns or (self.column,)

    @property
    def exact(self) -> bool:
        """A continuous command kept as logged (kind ``"continuous"``): no edges, no n_bins."""
        return self.type == "continuous" and self.edges is None and self.n_bins is None

    def component_names(self, width: int, *, list_column: bool = False) -> tuple[str, ...]:
        """Names of the ``width`` components: ``components`` if given, else the columns
        (``columns``), ``<column>.0``, ``<column>.1``... (a list column), ``dim`` if given, or
        the column's name (a scalar command kept as logged; binned ones keep ``dim = "a"``)."""
        if self.components is not None:
            return self.components
        if self.columns:
            return self.columns
        if list_column:
            return tuple(f"{self.column}.{j}" for j in range(width))
        return (self.column,) if self.exact and not self.dim_declared else (self.dim,)


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

    def text_columns(self) -> list[str]:
        """The columns compared as text, which a CSV reader must not convert to numbers:
        the episode ids, the source labels, and a discrete action column whose
        ``values`` are all strings."""
        cols = [self.episode.id, self.source_column]
        a = self.action
        if a.type == "discrete" and a.column and a.values and all(isinstance(v, str) for v in a.values):
            cols.append(a.column)
        return list(dict.fromkeys(c for c in cols if c))

    def needed_columns(self) -> list[str]:
        cols = [self.episode.id, *self.observations.columns, *self.observations.next_columns,
                *self.action.source_columns]
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


# ----------------------------------------------------------------------------- the TOML model
Str = Annotated[str, Field(strict=True)]
Column = Annotated[str, Field(strict=True, min_length=1, max_length=1000)]
#: A name that becomes part of a column name (``action_value.<name>``) or an action's name.
Name = Annotated[str, Field(strict=True, min_length=1, max_length=1000)]
Int = Annotated[int, Field(strict=True)]
Number = Annotated[float, Field(strict=True)]
Label = Annotated[int, Field(strict=True)] | Annotated[float, Field(strict=True)] | Annotated[str, Field(strict=True)]


def _unique(v: tuple[str, ...] | None) -> tuple[str, ...] | None:
    if v is not None and len(set(v)) != len(v):
        raise ValueError("entries must be unique")
    return v


class EpisodeModel(ConfigModel):
    """``[episode]``: which column identifies episodes and which orders rows within them."""

    id: Column = Field(description="episode id column (any type; compared as strings)")
    step: Column | None = Field(None, description="integer step column, used as is (minus step_base)")
    step_base: Annotated[int, Field(strict=True, ge=-(2**31),
                                    le=2**31 - 1)] = Field(0, description="first step value (e.g. 1)")
    order: Column | None = Field(None, description="any sortable column: steps are its dense rank within the episode")
    time: Column | None = Field(None, description="optional timestamp column -> t_ns")
    time_unit: Literal["s", "ms", "us", "ns"] = Field("ns", description="unit of a numeric time column")


class ObservationsModel(ConfigModel):
    """``[observations]``: feature columns, their next-state columns, names and units."""

    columns: tuple[Column, ...] = Field(min_length=1, description="feature columns, in order")
    next_columns: tuple[Column, ...] = Field((), description="next-state columns (required for kind = 'transitions')")
    names: tuple[Column, ...] = Field((), description="feature names (default: the column names)")
    units: dict[Str, Str] = Field(default_factory=dict, description="unit per feature name")

    _u = field_validator("columns", "names")(_unique)


Bounds = Number | tuple[Number, ...]


class ActionModel(ConfigModel):
    """``[action]``: the logged command (one column, a list column or several columns) and
    how it becomes actions: discrete labels, binned, or continuous commands kept as logged."""

    column: Column | None = Field(None,
                                  description="the action column (a scalar, or a list column: one command "
                                  "vector per row)")
    columns: tuple[Column, ...] | None = Field(None, min_length=1,
                                               description="several columns forming one vector command (continuous)")
    type: Literal["discrete", "continuous"] | None = Field(
        None, description="default: 'continuous' for 'columns' or a list column, else 'discrete'")
    values: tuple[Label, ...] | None = Field(None, min_length=1,
                                             description="discrete: the action table in index order")
    names: tuple[Name, ...] | None = Field(
        None, min_length=1,
        description="vector or unbinned continuous commands: component names (default: the columns, "
        "or <column>.0, <column>.1... for a list column); otherwise the action (bin) names")
    edges: tuple[Number, ...] | None = Field(None,
                                             description="continuous: bin edges (-inf/inf allowed); the exact commands "
                                             "are kept too")
    n_bins: Annotated[int, Field(strict=True, ge=1,
                                 le=100_000)] | None = Field(None, description="continuous: that many quantile bins")
    bin_value: Literal["mean", "center"] = "mean"
    dim: Name = "a"
    unit: Str = ""
    units: tuple[Str, ...] | None = Field(None, min_length=1, description="unit of each command component")
    low: Bounds | None = Field(None,
                               description="continuous: lower bound of each component (default: the logged minimum)")
    high: Bounds | None = Field(None,
                                description="continuous: upper bound of each component (default: the logged maximum)")
    vectors: tuple[Number | tuple[Number, ...], ...] | None = Field(None,
                                                                    description="each discrete action's value vector")
    dims: tuple[Name, ...] | None = Field(None, description="names of the components of the value vectors")

    _u = field_validator("names", "dims", "columns")(_unique)

    @field_validator("edges")
    @classmethod
    def _edges(cls, v: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if v is not None and (len(v) < 2 or any(math.isnan(x) for x in v)
                              or any(b <= a for a, b in zip(v, v[1:], strict=False))):
            raise ValueError(f"need at least two strictly increasing edges, got {list(v)}")
        return v

    @field_validator("low", "high")
    @classmethod
    def _bounds(cls, v: float | tuple[float, ...] | None) -> float | tuple[float, ...] | None:
        if v is not None and not all(math.isfinite(x) for x in (v if isinstance(v, tuple) else (v,))):
            raise ValueError(f"bounds must be finite numbers, got {v!r}")
        return v


class CostModel(ConfigModel):
    """``[cost]``: a cost column (lower is better) or a reward column (negated)."""

    column: Column | None = None
    reward: Column | None = None


class EndModel(ConfigModel):
    """``[end]``: optional flag columns (bool or 0/1)."""

    terminated: Column | None = None
    truncated: Column | None = None


class SourceModel(ConfigModel):
    """``[source]``: a label column, or one label for every row."""

    column: Column | None = None
    value: Str | None = None


class PropensityModel(ConfigModel):
    """``[propensity]``: probability of the logged action under the behaviour policy."""

    column: Column | None = None


class HintsModel(ConfigModel):
    """``[hints]``: problem hints stored in info.json."""

    gamma: Annotated[float, Field(strict=True, gt=0.0, le=1.0)] | None = None
    horizon: Annotated[int, Field(strict=True, ge=1, le=2**31 - 1)] | None = None


class CsvModel(ConfigModel):
    """``[csv]``: how CSV files are parsed."""

    delimiter: Annotated[str, Field(strict=True, min_length=1, max_length=1)] = ","

    @field_validator("delimiter")
    @classmethod
    def _delim(cls, v: str) -> str:
        if v in ('"', "\n", "\r"):
            raise ValueError(f"{v!r} cannot separate fields")
        return v


class ParquetSpecModel(ConfigModel):
    """An ingestion spec for Parquet/CSV tables (``offline-adp ingest parquet --spec``)."""

    kind: Literal["transitions", "steps"] = Field("transitions",
                                                  description="rows with next-state columns, or one row per step")
    format: Literal["auto", "parquet", "csv"] = "auto"
    name: Str = ""
    on_error: Literal["fail", "quarantine"] = "fail"
    episode: EpisodeModel
    observations: ObservationsModel
    action: ActionModel
    cost: CostModel
    end: EndModel = EndModel()
    source: SourceModel = SourceModel()
    propensity: PropensityModel = PropensityModel()
    hints: HintsModel = HintsModel()
    csv: CsvModel = CsvModel()


def parquet_spec_schema() -> dict[str, Any]:
    """The JSON Schema of a Parquet/CSV ingestion spec (``docs/schemas/ingest-spec.schema.json``)."""
    return json_schema(ParquetSpecModel)


def _check_keys(table: Mapping[str, Any], allowed: set[str], where: str) -> None:
    """Unknown keys of a plain TOML table (used by the MCAP spec reader)."""
    if not isinstance(table, Mapping):
        raise SpecError(f"{where}: expected a table, got {type(table).__name__} {table!r}")
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise SpecError(f"{where}: unknown key(s) {unknown}{did_you_mean(unknown, sorted(allowed))}; valid keys are "
                        f"{sorted(allowed)}")


def _action(a: ActionModel, w: str) -> ActionSpec:
    if (a.column is None) == (a.columns is None):
        raise SpecError(f"{w}: give either 'column' (one column, or a list column holding the command vector) or "
                        "'columns' (several columns forming one vector command)")
    typ = a.type or ("continuous" if a.columns is not None else "discrete")
    vectors = None if a.vectors is None else tuple(tuple(v) if isinstance(v, tuple) else (float(v),) for v in a.vectors)
    binned = a.edges is not None or a.n_bins is not None
    vector = a.columns is not None
    # names are component names for a vector command or an unbinned continuous one
    components = a.names if (vector or (typ == "continuous" and not binned)) else None
    act = ActionSpec(column=a.column or "", type=typ, values=a.values,
                     names=None if components is not None else a.names,
                     edges=a.edges, n_bins=a.n_bins, bin_value=a.bin_value, dim=a.dim, unit=a.unit, vectors=vectors,
                     dims=a.dims, columns=a.columns or (), components=components, units=a.units,
                     low=_bound(a.low), high=_bound(a.high), type_declared=a.type is not None,
                     dim_declared="dim" in a.model_fields_set)
    if act.type == "continuous" and act.column and not vector and components is not None and len(components) == 1:
        if "dim" in a.model_fields_set and a.dim != components[0]:
            raise SpecError(f"{w}: dim {a.dim!r} and names {list(components)} name the component differently; give one")
    if vector:
        if act.type == "discrete":
            raise SpecError(f"{w}.columns: several columns form a continuous command vector; set type = 'continuous' "
                            "(or map one column of labels with 'column')")
        if a.dims is not None or vectors is not None:
            raise SpecError(f"{w}: 'dims'/'vectors' describe discrete value vectors; name the components of "
                            "'columns' with 'names'")
        if components is not None and len(components) != len(act.columns):
            raise SpecError(f"{w}.names: {len(components)} names for {len(act.columns)} columns {list(act.columns)}")
    if act.units is not None and act.unit:
        raise SpecError(f"{w}: give either 'unit' (one for every component) or 'units' (one per component)")
    if a.type == "discrete" or vectors is not None:  # undeclared: a list column is a continuous command
        for key in ("low", "high", "units"):
            if getattr(a, key) is not None:
                raise SpecError(f"{w}.{key}: only for continuous commands (type = 'continuous')")
    k = len(act.columns) if vector else (len(components) if components is not None else None)
    for key in ("units", "low", "high"):
        v = getattr(act, key)
        if v is None:
            continue
        if key != "units" and not isinstance(getattr(a, key), tuple):  # one number for every component
            if k is not None:
                act = replace(act, **{key: v * k})
            continue
        if k is not None and len(v) != k:
            raise SpecError(f"{w}.{key}: {len(v)} entries for a command of {k} components")
    if act.low is not None and act.high is not None and len(act.low) == len(act.high):
        bad = [j for j, (lo, hi) in enumerate(zip(act.low, act.high, strict=True)) if lo > hi]
        if bad:
            raise SpecError(f"{w}: low {list(act.low)} exceeds high {list(act.high)} (component {bad[0]})")
    if act.vectors is not None:
        if act.values is None or len(act.vectors) != len(act.values):
            raise SpecError(f"{w}.vectors: give one value vector per entry of 'values'")
        if len({len(v) for v in act.vectors}) != 1 or (act.dims is not None and len(act.dims) != len(act.vectors[0])):
            raise SpecError(f"{w}.vectors: all vectors need the same length, matching 'dims'")
        if not all(math.isfinite(x) for v in act.vectors for x in v):
            raise SpecError(f"{w}.vectors: values must be finite")
    if act.type == "continuous":
        if act.edges is not None and act.n_bins is not None:
            raise SpecError(f"{w}: a continuous action takes at most one of 'edges' or 'n_bins' (neither: the "
                            "commands are kept as logged)")
        if act.values is not None:
            raise SpecError(f"{w}.values: only for discrete actions (continuous ones are binned or kept as logged)")
    elif act.edges is not None or act.n_bins is not None:
        raise SpecError(f"{w}: 'edges'/'n_bins' bin continuous actions; set type = 'continuous'")
    if act.values is not None:
        if len({(type(v) is str, v) for v in act.values}) != len(act.values):
            raise SpecError(f"{w}.values: entries must be unique, got {list(act.values)}")
        if any(isinstance(v, float) and not math.isfinite(v) for v in act.values):
            raise SpecError(f"{w}.values: numbers must be finite")
    if act.names is not None and act.values is not None and len(act.names) != len(act.values):
        raise SpecError(f"{w}: names has {len(act.names)} entries, values has {len(act.values)}")
    return act


def _bound(v: float | tuple[float, ...] | None) -> tuple[float, ...] | None:
    """A bound as a tuple (one number: for every component, resolved by :func:`resolve_bounds`)."""
    if v is None:
        return None
    return tuple(float(x) for x in v) if isinstance(v, tuple) else (float(v),)


def parse_parquet_spec(data: Mapping[str, Any], text: str = "", where: str = "spec") -> ParquetSpec:
    """Check and convert a spec mapping (from TOML) into a :class:`ParquetSpec`.

    Raises
    ------
    SpecError
        Naming ``where`` (the file), the dotted key, what was expected and what was found.
    """
    if not isinstance(data, Mapping):
        raise SpecError(f"{where}: expected a table of keys, got {type(data).__name__}")
    if {"clock", "streams"} & set(data) and not {"observations", "episode"} & set(data):
        raise SpecError(f"{where}: this is an MCAP ingestion spec ([clock], [[streams]] ...), not a Parquet/CSV one: "
                        "`offline-adp ingest mcap` reads it (both kinds: docs/ingestion-spec.md)")
    m = validate_config(ParquetSpecModel, data, source=where)
    w = f"{where}: episode"
    ep = EpisodeSpec(id=m.episode.id, step=m.episode.step, step_base=m.episode.step_base, order=m.episode.order,
                     time=m.episode.time, time_unit=m.episode.time_unit)
    if ep.step and ep.order:
        raise SpecError(f"{w}: give either 'step' (an integer step column) or 'order' (any sortable column), not both")
    if not (ep.step or ep.order or ep.time):
        raise SpecError(f"{w}: rows need an ordering within episodes: give 'step', 'order' or 'time'")
    o = m.observations
    w = f"{where}: observations"
    obs = ObservationSpec(columns=o.columns, next_columns=o.next_columns, names=o.names, units=dict(o.units))
    if obs.next_columns and len(obs.next_columns) != len(obs.columns):
        raise SpecError(f"{w}: next_columns has {len(obs.next_columns)} entries, columns has {len(obs.columns)}")
    if obs.names and len(obs.names) != len(obs.columns):
        raise SpecError(f"{w}: names has {len(obs.names)} entries, columns has {len(obs.columns)}")
    if m.kind == "transitions" and not obs.next_columns:
        raise SpecError(f"{w}.next_columns: required for kind = 'transitions' (or use kind = 'steps')")
    unknown_units = set(obs.units) - set(obs.names or obs.columns)
    if unknown_units:
        raise SpecError(f"{w}.units: keys {sorted(unknown_units)} are not observation names "
                        f"{list(obs.names or obs.columns)}")
    act = _action(m.action, f"{where}: action")
    if (m.cost.column is None) == (m.cost.reward is None):
        raise SpecError(f"{where}: cost: give exactly one of 'column' (a cost, lower is better) or 'reward' (negated)")
    if m.source.column is not None and m.source.value is not None:
        raise SpecError(f"{where}: source: give either 'column' or 'value', not both")
    return ParquetSpec(
        kind=m.kind,
        episode=ep,
        observations=obs,
        action=act,
        cost_column=m.cost.column,
        reward_column=m.cost.reward,
        terminated_column=m.end.terminated,
        truncated_column=m.end.truncated,
        source_column=m.source.column,
        source_value=m.source.value if m.source.value is not None else "unknown",
        propensity_column=m.propensity.column,
        gamma=m.hints.gamma,
        horizon=m.hints.horizon,
        format=m.format,
        name=m.name,
        on_error=m.on_error,
        csv_delimiter=m.csv.delimiter,
        raw=dict(data),
        text=text,
    )


def load_parquet_spec(path: str | PathLike[str]) -> ParquetSpec:
    """Read and check a TOML spec file (see :func:`parse_parquet_spec`)."""
    path = Path(path)
    data = load_toml(path, "ingestion spec")
    text = read_config_bytes(path, "ingestion spec").decode("utf-8", errors="replace")
    return parse_parquet_spec(data, text=text, where=str(path))


__all__ = ["ParquetSpec", "ParquetSpecModel", "EpisodeSpec", "ObservationSpec", "ActionSpec", "parse_parquet_spec",
           "load_parquet_spec", "parquet_spec_schema"]
