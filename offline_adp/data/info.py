"""Dataset metadata (``meta/info.json``) as frozen dataclasses, checked on load."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from offline_adp.data.schema import FORMAT_VERSION, PROPENSITY_SOURCES
from offline_adp.errors import InvalidTypeError, SchemaError

#: Action table kinds (:class:`ActionTable`).
ACTION_KINDS = ("discrete", "binned", "continuous")
#: Prefix of the columns that keep each row's exact command (``action_value.<dim>``).
ACTION_VALUE_PREFIX = "action_value."


@dataclass(frozen=True)
class Feature:
    """One observation feature: column ``obs.<name>`` (and ``next_obs.<name>``)."""

    name: str
    unit: str = ""
    description: str = ""


@dataclass(frozen=True)
class Action:
    """One entry of the action table: a name and the value vector sent to the system."""

    name: str
    value: tuple[float, ...]


@dataclass(frozen=True)
class ActionTable:
    """The declared, finite action set; the ``action`` column indexes into it.

    Parameters
    ----------
    actions : tuple of Action
        Entry ``i`` is action index ``i``.
    dims : tuple of str
        Names of the components of each action's value vector (e.g. ``("steering",)``).
    kind : {"discrete", "binned", "continuous"}
        ``"binned"`` when a continuous command was quantised at ingestion (the explicit
        choice); then ``bin_edges`` holds the edges (one dimension) and each value is the
        bin's representative command. ``"continuous"``: the exact command of every row is
        stored in the ``action_value.<dim>`` columns and is what algorithms learn from;
        the ``action`` column then holds a coarse bin of each command (its entry's value is
        the bin's representative), kept for the discrete views (counts, behaviour models).
    units : tuple of str
        Unit of each value component.
    bin_edges : tuple of float, optional
        Bin edges (length ``n_actions + 1``) for binned one-dimensional commands.
    low, high : tuple of float, optional
        Bounds of each command component (continuous and binned commands): declared in
        the ingestion spec, else the logged range. Commands outside are refused by the doctor.
    """

    actions: tuple[Action, ...]
    dims: tuple[str, ...] = ("a",)
    kind: str = "discrete"
    units: tuple[str, ...] = ()
    bin_edges: tuple[float, ...] | None = None
    low: tuple[float, ...] | None = None
    high: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if not self.actions:
            raise SchemaError("action table is empty: declare at least one action")
        if self.kind not in ACTION_KINDS:
            raise SchemaError(f"action table kind must be one of {list(ACTION_KINDS)}, got {self.kind!r}")
        for key, b in (("low", self.low), ("high", self.high)):
            if b is not None and (len(b) != len(self.dims) or not all(np.isfinite(x) for x in b)):
                raise SchemaError(f"action table {key}: {list(b)} must hold one finite number per dim "
                                  f"{list(self.dims)}")
        if (
            self.low is not None
            and self.high is not None
            and any(lo > hi for lo, hi in zip(self.low, self.high, strict=True))
        ):
            raise SchemaError(f"action table bounds: low {list(self.low)} exceeds high {list(self.high)}")
        for i, a in enumerate(self.actions):
            if len(a.value) != len(self.dims):
                raise SchemaError(
                    f"action {i} ({a.name!r}) has {len(a.value)} value components, "
                    f"the table declares {len(self.dims)} dims {list(self.dims)}"
                )
        names = [a.name for a in self.actions]
        if len(set(names)) != len(names):
            seen: set[str] = set()
            dup = sorted({x for x in names if x in seen or seen.add(x)})  # type: ignore[func-returns-value]
            raise SchemaError(f"action names must be unique; {len(dup)} repeated, e.g. {dup[:5]} "
                              f"({len(names)} actions)")

    def __len__(self) -> int:
        return len(self.actions)

    @property
    def names(self) -> list[str]:
        """Action names in index order."""
        return [a.name for a in self.actions]

    @property
    def values(self) -> np.ndarray:
        """``(n_actions, n_dims)`` float64 array of action value vectors."""
        return np.array([a.value for a in self.actions], dtype=np.float64).reshape(
            len(self.actions), len(self.dims)
        )

    @classmethod
    def from_values(
        cls,
        values: Sequence[float] | Sequence[Sequence[float]],
        names: Sequence[str] | None = None,
        dims: Sequence[str] = ("a",),
        units: Sequence[str] = (),
    ) -> ActionTable:
        """Build a discrete table from value vectors (scalars allowed for one dim)."""
        vals = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
        if names is None:
            names = [f"{dims[0]}={v[0]:g}" if vals.shape[1] == 1 else f"a{i}" for i, v in enumerate(vals)]
        actions = tuple(Action(str(n), tuple(float(x) for x in v)) for n, v in zip(names, vals, strict=True))
        return cls(actions=actions, dims=tuple(dims), units=tuple(units))

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "kind": self.kind,
            "dims": list(self.dims),
            "units": list(self.units),
            "actions": [{"index": i, "name": a.name, "value": list(a.value)} for i, a in enumerate(self.actions)],
        }
        if self.bin_edges is not None:
            d["bin_edges"] = list(self.bin_edges)
        if self.low is not None:
            d["low"] = list(self.low)
        if self.high is not None:
            d["high"] = list(self.high)
        return d

    @property
    def continuous(self) -> bool:
        """Whether the exact commands (``action_value.<dim>`` columns) are the actions."""
        return self.kind == "continuous"

    @property
    def command_columns(self) -> list[str]:
        """The columns holding the exact command of each row, one per dim."""
        return [ACTION_VALUE_PREFIX + d for d in self.dims]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` per component as float64 (``-inf``/``inf`` where not declared)."""
        k = len(self.dims)
        lo = np.full(k, -np.inf) if self.low is None else np.asarray(self.low, np.float64)
        hi = np.full(k, np.inf) if self.high is None else np.asarray(self.high, np.float64)
        return lo, hi

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str = "action_table") -> ActionTable:
        try:
            actions = tuple(Action(str(a["name"]), tuple(float(v) for v in a["value"])) for a in d["actions"])
            edges = d.get("bin_edges")
            low, high = d.get("low"), d.get("high")
            return cls(
                low=None if low is None else tuple(float(v) for v in low),
                high=None if high is None else tuple(float(v) for v in high),
                actions=actions,
                dims=_strings(d.get("dims", ("a",)), f"{where}: dims"),
                kind=d.get("kind", "discrete"),
                units=_strings(d.get("units", ()), f"{where}: units"),
                bin_edges=None if edges is None else tuple(float(e) for e in edges),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise SchemaError(f"{where}: malformed action table ({exc!r})") from exc


@dataclass(frozen=True)
class DatasetInfo:
    """Everything in ``meta/info.json`` except derived counts.

    Parameters
    ----------
    features : tuple of Feature
        Observation features in column order.
    action_table : ActionTable
        The declared action set.
    gamma, horizon : optional
        Hints for algorithms (discount factor; episode horizon T).
    propensity_source : {"logged", "estimated", "unknown"}
        Where ``behavior_prob`` came from, if present.
    provenance : dict
        Input files with sha256, ingestion spec and its hash, package version, creation
        time, generating command.
    name : str
        Human-readable dataset name.
    problem : str, optional
        Reference problem that generated the data (``simulate``), if any.
    format_version : str
        Format version the dataset was written with.
    """

    features: tuple[Feature, ...]
    action_table: ActionTable
    gamma: float | None = None
    horizon: int | None = None
    propensity_source: str = "unknown"
    provenance: Mapping[str, Any] = field(default_factory=dict)
    name: str = ""
    problem: str | None = None
    format_version: str = FORMAT_VERSION

    def __post_init__(self) -> None:
        if not self.features:
            raise SchemaError("a dataset needs at least one observation feature")
        names = [f.name for f in self.features]
        if len(set(names)) != len(names):
            seen: set[str] = set()
            dup = sorted({x for x in names if x in seen or seen.add(x)})  # type: ignore[func-returns-value]
            raise SchemaError(f"feature names must be unique; {len(dup)} repeated, e.g. {dup[:5]} "
                              f"({len(names)} features)")
        if self.propensity_source not in PROPENSITY_SOURCES:
            raise SchemaError(
                f"propensity_source must be one of {list(PROPENSITY_SOURCES)}, got {self.propensity_source!r}"
            )
        if self.gamma is not None and not 0.0 <= self.gamma <= 1.0:
            raise SchemaError(f"gamma hint must be in [0, 1], got {self.gamma}")
        if self.horizon is not None and self.horizon <= 0:
            raise SchemaError(f"horizon hint must be positive, got {self.horizon}")

    @property
    def feature_names(self) -> list[str]:
        return [f.name for f in self.features]

    @property
    def n_actions(self) -> int:
        return len(self.action_table)

    def replace(self, **changes: Any) -> DatasetInfo:
        """Copy with some fields changed (dataclasses.replace)."""
        import dataclasses

        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return {
            "format_version": self.format_version,
            "name": self.name,
            "problem": self.problem,
            "features": [{"name": f.name, "unit": f.unit, "description": f.description} for f in self.features],
            "action_table": self.action_table.to_dict(),
            "gamma": self.gamma,
            "horizon": self.horizon,
            "propensity_source": self.propensity_source,
            "provenance": dict(self.provenance),
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=False, default=json_numpy)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str = "info.json") -> DatasetInfo:
        try:
            features = tuple(
                Feature(str(f["name"]), str(f.get("unit", "")), str(f.get("description", "")))
                for f in d["features"]
            )
            return cls(
                features=features,
                action_table=ActionTable.from_dict(d["action_table"], where=f"{where}: action_table"),
                gamma=_hint(d.get("gamma"), f"{where}: gamma", whole=False),
                horizon=_hint(d.get("horizon"), f"{where}: horizon", whole=True),
                propensity_source=d.get("propensity_source", "unknown"),
                provenance=d.get("provenance", {}),
                name=d.get("name", ""),
                problem=d.get("problem"),
                format_version=str(d.get("format_version", "")),
            )
        except KeyError as exc:
            raise SchemaError(f"{where}: missing key {exc.args[0]!r}") from exc
        except (TypeError, ValueError) as exc:
            raise SchemaError(f"{where}: malformed ({exc})") from exc


def _strings(value: Any, where: str) -> tuple[str, ...]:
    """A list of names read from ``info.json`` (action dims, units): strings only (a number
    there would fail later as a column name ``action_value.`` + 5)."""
    if isinstance(value, str) or not isinstance(value, list | tuple) or not all(isinstance(x, str) for x in value):
        raise SchemaError(f"{where} must be a list of strings, found {value!r:.80}")
    return tuple(value)


def _hint(value: Any, where: str, whole: bool) -> Any:
    """``gamma`` or ``horizon`` as read from ``info.json``: None, or a number (not a bool; a
    horizon a whole number: NaN or 2.5 steps would reach ``int()`` deep in an evaluation);
    the ranges are :class:`DatasetInfo`'s own checks."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or (whole and not float(value).is_integer()):
        raise SchemaError(f"{where} must be null or {'a whole number' if whole else 'a number'}, found {value!r:.60}")
    return int(value) if whole else value


def json_numpy(o: Any) -> Any:
    """``json.dumps``'s ``default`` for numpy scalars and arrays (their Python values);
    anything else is a ``TypeError``, as without it."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise InvalidTypeError(f"not JSON serialisable: {type(o).__name__}")
