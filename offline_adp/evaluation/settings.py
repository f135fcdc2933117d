"""The evaluation's settings: one typed model, the single source of every setting's name,
default, bounds and check.

:class:`EvaluationSettings` serves

- the command line: ``offline-adp evaluate`` and ``offline-adp compare`` make one flag per
  field (``--fqe-bootstrap`` for ``fqe_bootstrap``), each value checked by the model as it
  is parsed (:func:`parse_flag`);
- a pipeline's ``[evaluate]`` table: :class:`EvaluationOptions`, the same fields but the
  seed (a pipeline has one seed, its top-level ``seed``, bounded by :data:`MAX_SEED` too);
- the JSON Schema (``offline-adp schema pipeline``): the model's own;
- the Python API: :func:`offline_adp.evaluation.run.evaluate_run`,
  :func:`~offline_adp.evaluation.run.evaluation_metrics` and
  :func:`~offline_adp.evaluation.offpolicy.off_policy` take a settings object (or its
  fields as keywords, checked by :meth:`EvaluationSettings.resolve`; the former keyword
  names ``n_episodes``, ``n_boot`` and ``n_boot_fqe`` are still read).

Every bound is far above any useful value, so a typo (``--bootstrap 1000000000000``) is
one error naming the setting before any work, not hours of work or an allocation that
fails half-way through. Nothing here imports numpy.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from pydantic import ConfigDict, Field, field_validator
from pydantic import ValidationError as _PydanticValidationError

from offline_adp.config import ConfigModel, format_validation_error, parse_json_object
from offline_adp.errors import MAX_JSON_DEPTH, InvalidArgumentError, SpecError, json_depth
from offline_adp.evaluation import (
    FQE_BOOTSTRAP_DEFAULT,
    MAX_MODEL_PARTICLES,
    MODEL_PARTICLES_DEFAULT,
    particle_count_error,
)

#: Rollout episodes per policy: at most this many.
MAX_EPISODES = 1_000_000
#: Bootstrap replicates of IS/DR/MIS: at most this many.
MAX_REPLICATES = 1_000_000
#: FQE bootstrap replicates (each a re-weighting or a refit of FQE, with its own episode
#: weights in memory): at most this many.
MAX_FQE_REPLICATES = 100_000
#: The evaluation horizon (steps of every rollout): at most this many.
MAX_HORIZON = 1_000_000
#: Seeds: 0 .. 2**31 - 1. The estimators seed scikit-learn and numpy with ``seed + t`` per
#: step (t < :data:`MAX_HORIZON`), which must stay below 2**32.
MAX_SEED = 2**31 - 1
#: The former Python keyword names of three settings (still read by the Python API).
LEGACY_NAMES = {"n_episodes": "episodes", "n_boot": "bootstrap", "n_boot_fqe": "fqe_bootstrap"}
#: Settings that are 0 (none) or at least 2 (a Monte-Carlo interval needs two draws).
ZERO_OR_TWO = ("bootstrap", "fqe_bootstrap", "model_particles")

_NOT_ONE = {"not": {"const": 1}}


def check_simulator_name(name: str | None) -> None:
    """A simulator setting: ``None``/``"none"``, a reference problem's name or ``gym:ENV_ID``
    (a registered gymnasium environment: checked when the evaluation makes it)."""
    from offline_adp.envs import PROBLEM_NAMES

    if name is not None and name != "none" and name not in PROBLEM_NAMES and not (
            name.startswith("gym:") and len(name) > 4):
        raise ValueError(f"simulator = {name!r}: known simulators are {list(PROBLEM_NAMES)}, gym:ENV_ID or 'none'")


class EvaluationOptions(ConfigModel):
    """A pipeline's ``[evaluate]`` table: the evaluation's settings but the seed (the
    pipeline's own ``seed``). Strict: whole numbers only, no strings for numbers."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, validate_default=True)

    simulator: str | None = Field(
        None, description="reference problem to roll out in, gym:ENV_ID (a registered gymnasium environment; features "
        "by declared order, actions by the action table's values), or 'none' (default: the dataset's problem)")
    episodes: int = Field(500, ge=2, le=MAX_EPISODES,
                          description="rollout episodes in the simulator (at least 2: their mean's interval needs two)")
    bootstrap: int = Field(200, ge=0, le=MAX_REPLICATES, json_schema_extra=_NOT_ONE,
                           description="bootstrap replicates for IS/DR/MIS (0: no interval; not 1)")
    fqe_bootstrap: int | None = Field(
        FQE_BOOTSTRAP_DEFAULT, ge=0, le=MAX_FQE_REPLICATES, json_schema_extra=_NOT_ONE,
        description="FQE bootstrap replicates; omitted: 200 when replicates are cheap, else 50; 0: no interval; not 1")
    fqe_params: dict[str, Any] | None = Field(
        None, description='FittedQEvaluation parameters, e.g. {"mode": "refit"} (checked as `fit --algorithm fqe` '
        "checks its table)")
    horizon: int | None = Field(None, ge=1, le=MAX_HORIZON, description="the evaluation horizon (default: the data's "
                                "longest episode; with gym:ENV_ID the environment's own time limit)")
    estimand: Literal["finite", "infinite"] = Field(
        "finite", description="the value to estimate: over the logged horizon (finite) or infinite-horizon discounted "
        "(FQE only)")
    model_particles: int = Field(
        MODEL_PARTICLES_DEFAULT, ge=0, le=MAX_MODEL_PARTICLES, json_schema_extra=_NOT_ONE,
        description="particles of the model rollouts of the logs, a second reading of the value and a logs-only drift "
        "measure (0: none; not 1; below 200 they do not count as showing that the policy stays in the data)")

    @field_validator("episodes", "bootstrap", "fqe_bootstrap", "horizon", "model_particles", mode="before")
    @classmethod
    def _whole_numbers(cls, value: Any) -> Any:
        """A numpy integer (e.g. a horizon computed from arrays) or a whole float (``1e13`` in
        TOML or ``--set``: then refused by its bound, not by its type) is read as the int it is;
        strings, bools and fractions are refused."""
        if type(value).__module__ == "numpy" and hasattr(value, "__index__") and not isinstance(value, bool | int):
            return int(value)
        if isinstance(value, float) and value.is_integer():
            return int(value)
        return value

    @field_validator("bootstrap", "fqe_bootstrap")
    @classmethod
    def _zero_or_two(cls, value: int | None) -> int | None:
        if value == 1:
            raise ValueError("must be 0 (no interval) or at least 2 (a percentile interval needs two replicates)")
        return value

    @field_validator("model_particles")
    @classmethod
    def _particles(cls, value: int) -> int:
        why = particle_count_error(value)
        if why:
            raise ValueError(why)
        return value

    @field_validator("simulator")
    @classmethod
    def _simulator(cls, value: str | None) -> str | None:
        check_simulator_name(value)
        return value

    @field_validator("fqe_params")
    @classmethod
    def _fqe_params(cls, value: dict[str, Any] | None) -> dict[str, Any] | None:
        """Nested at most :data:`MAX_JSON_DEPTH` deep; then checked by the fit's own check of
        an FQE table (the registry's), numbers as validated."""
        if value is None:
            return None
        if json_depth(value) > MAX_JSON_DEPTH:
            raise ValueError(f"nested deeper than {MAX_JSON_DEPTH} levels")
        from offline_adp.algorithms.registry import get_algorithm

        try:
            return get_algorithm("fqe").check_params(value, "", "fqe_params")
        except SpecError as exc:
            raise ValueError(str(exc)) from None


class EvaluationSettings(EvaluationOptions):
    """Every setting of an evaluation (see the module docstring)."""

    seed: int = Field(0, ge=0, le=MAX_SEED, description="seed of the rollouts, bootstraps and fits")

    _seed_whole = field_validator("seed", mode="before")(EvaluationOptions._whole_numbers.__func__)

    @classmethod
    def resolve(cls, settings: EvaluationSettings | Mapping[str, Any] | None = None,
                options: Mapping[str, Any] | None = None, where: str = "") -> EvaluationSettings:
        """``settings`` (a settings object or a mapping of its fields) with ``options`` (fields
        by name, or by their former names :data:`LEGACY_NAMES`) set over it, checked; an
        unknown name or a refused value is an :class:`InvalidArgumentError` naming the key."""
        if isinstance(settings, EvaluationSettings) and not options:
            return settings
        base: dict[str, Any] = {}
        if isinstance(settings, EvaluationSettings):
            base = settings.model_dump(exclude_unset=True)
        elif settings is not None:
            base = dict(_renamed(dict(settings), where))
        base.update(_renamed(dict(options or {}), where))
        try:
            return cls.model_validate(base)
        except _PydanticValidationError as exc:
            raise InvalidArgumentError(format_validation_error(exc, cls, where)) from None

    @classmethod
    def of_arguments(cls, args: Any) -> EvaluationSettings:
        """The settings of parsed command-line arguments (an ``argparse.Namespace`` whose
        attributes of the settings' names hold values already checked by :func:`parse_flag`)."""
        return cls.resolve(None, {n: getattr(args, n) for n in cls.model_fields if hasattr(args, n)})


def _renamed(given: dict[str, Any], where: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in given.items():
        name = LEGACY_NAMES.get(key, key)
        if name not in EvaluationSettings.model_fields:
            head = f"{where}: " if where else ""
            raise InvalidArgumentError(f"{head}{key}: not an evaluation setting; settings are "
                                       f"{', '.join(EvaluationSettings.model_fields)}")
        if name in out:
            raise InvalidArgumentError(f"{key}: given twice (as {name} and {key})")
        out[name] = value
    return out


def flag(name: str) -> str:
    """The command-line flag of a setting: ``fqe_bootstrap`` -> ``--fqe-bootstrap``."""
    return "--" + name.replace("_", "-")


def _bound(name: str, which: str) -> Any:
    """A numeric setting's ``ge`` or ``le`` bound (None: none, or not numeric)."""
    return next((getattr(m, which) for m in EvaluationSettings.model_fields[name].metadata if hasattr(m, which)), None)


def describe(name: str) -> str:
    """What a numeric setting takes, from its bounds: ``a positive integer up to 1,000,000``."""
    lo, hi = _bound(name, "ge"), _bound(name, "le")
    if name in ZERO_OR_TWO:
        text = "0 or an integer from 2"
    else:
        text = {0: "a non-negative integer", 1: "a positive integer"}.get(lo, f"an integer from {lo}")
    return text + (f" up to {hi:,}" if hi is not None else "")


def parse_flag(name: str, text: str) -> Any:
    """The value of setting ``name`` given on the command line as ``text``, checked by the
    model; an :class:`InvalidArgumentError` ``--flag: ...`` otherwise (one line)."""
    opt = flag(name)
    if name == "fqe_params":
        value: Any = parse_json_object(text, opt, '{"mode": "refit"}')
    elif _bound(name, "ge") is not None:
        try:
            value = int(text.strip().replace("_", ""), 10) if len(text) <= 64 else None
        except ValueError:
            value = None
        if value is None:
            raise InvalidArgumentError(f"{opt}: expected {describe(name)}, got {text[:40]!r}")
    else:
        value = text
    try:
        return getattr(EvaluationSettings.model_validate({name: value}), name)
    except _PydanticValidationError as exc:
        if isinstance(value, int):
            raise InvalidArgumentError(f"{opt}: expected {describe(name)}, got {value:,}") from None
        said = format_validation_error(exc, EvaluationSettings, "").removeprefix(f"{name}: ")
        raise InvalidArgumentError(f"{opt}: {said}") from None
