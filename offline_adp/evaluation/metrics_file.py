"""The structure of ``metrics.json`` that ``report``, ``compare`` and ``run`` read
(:class:`MetricsFile`), and :func:`read_metrics`, which holds a file to it.

``metrics.json`` is untrusted like every file we read: a hand-edited or damaged one
(``"level": "0.95"``, an interval of one number, a stored headline whose ranking entries
lack a name) is an :class:`~offline_adp.errors.ArtifactError` naming the file and the key,
before anything formats or indexes into it. The keys the readers use are typed strictly
(a number is a JSON number, never a string or ``true``; ints fill floats); keys they do not
read pass as they are.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

#: An interval as stored: two numbers, either null where none was computed.
Pair = Annotated[list[float | None], Field(min_length=2, max_length=2)]
#: An interval that is quoted: two numbers.
Bounds = Annotated[list[float], Field(min_length=2, max_length=2)]
Outcome = Literal["better", "worse", "cannot tell", "not converged"]


class _Open(BaseModel):
    """A part of ``metrics.json``: the keys read are typed, others pass."""

    model_config = ConfigDict(extra="allow", strict=True)


class _ModelRollouts(_Open):
    estimate: float | None = None
    interval: Pair | None = None
    exit_mass: float | None = None
    n_particles: int | None = None


class _WeightDiagnostics(_Open):
    ess_fraction: float | None = None


class _Estimate(_Open):
    estimate: float | None = None
    interval: Pair | None = None
    level: float | None = None
    nominal_level: float | None = None
    level_note: str | None = None
    interval_method: str | None = None
    plugin_estimate: float | None = None
    degenerate: bool | None = None
    comparable: bool | None = None
    ess: float | None = None
    warnings: list[Any] | None = []
    model_rollouts: _ModelRollouts | None = None
    vs_logged: Pair | None = None
    weight_diagnostics: _WeightDiagnostics | None = None


class _Estimand(_Open):
    form: str | None = None
    quantity: str | None = None
    horizon: int | None = None
    gamma: float | None = None
    possible_range: Bounds | None = None


class _Rollout(_Open):
    mean_discounted_cost: float
    interval: Pair | None = None
    n_episodes: int | None = None
    failures: int | float | None = None


class _Rollouts(_Open):
    policy: _Rollout
    demonstrator: _Rollout | None = None
    note: str | None = None


class _ShiftStep(_Open):
    step: int
    ess_fraction: float | None
    auc: float | None = None
    uncovered: float | None = None
    q90: float | None = None
    q99: float | None = None
    max: float | None = None
    supported_sup: float | None = None
    sup_ucb: float | None = None


class _ShiftBlock(_Open):
    per_step: list[_ShiftStep]
    warnings: list[Any] | None = []


class _Pooled(_Open):
    ess_fraction: float
    q99: float
    warnings: list[Any] | None = []


class _WorstStep(_Open):
    step: int
    ess_fraction: float


class _SupportViolations(_Open):
    fraction: float | None = None
    threshold: float | None = None


class _Behaviour(_Open):
    support_violations: _SupportViolations = _SupportViolations()
    source: str | None = None
    clip: float | None = None
    n_clipped: int | None = None
    warnings: list[Any] | None = []


class _BehaviourValue(_Open):
    mean: float
    interval: Pair | None = None
    episodes: int | None = None
    comparable: bool | None = None  # False: not the behaviour's T-step value (truncated episodes)
    not_comparable: str | None = None


class _Quantiles(_Open):
    levels: list[float]
    values: list[float]

    @model_validator(mode="after")
    def _same_length(self) -> _Quantiles:
        if len(self.levels) != len(self.values):
            raise ValueError(f"levels ({len(self.levels)}) and values ({len(self.values)}) differ in length")
        return self


class _Distribution(_Open):
    usable: bool | None = None
    reason: str | None = None
    method: str | None = None
    mean: float | None = None
    cvar: float | None = None
    alpha: float | None = None
    n_episodes: int | None = None
    ess: float | None = None
    quantiles: _Quantiles | None = None

    @model_validator(mode="after")
    def _numbers_when_usable(self) -> _Distribution:
        if self.usable is not False and (self.mean is None or self.cvar is None):
            raise ValueError("a usable distribution needs its mean and cvar")
        if self.usable is not False and self.ess is not None and self.n_episodes is None:
            raise ValueError("an effective sample size needs n_episodes")
        return self


class _CostDistribution(_Open):
    alpha: float | None = None
    behaviour_logged: _Distribution | None = None
    policy_logs: _Distribution | None = None
    policy_rollouts: _Distribution | None = None
    demonstrator_rollouts: _Distribution | None = None


class _Source(_Open):
    data_mass: float
    policy_mass: float


class _PsdpReference(_Open):
    ratio_ucb_max: float | None = None
    ratio_ucb_step: int | None = None
    eps_sum: float | None = None
    pooled_ratio_ucb: float | None = None
    per_step: float | None = None
    averaged: float | None = None
    method: str | None = None


class _Psdp(_Open):
    label: str
    eps: list[float | None] | None = None
    eps_method: str | None = None
    references: dict[str, _PsdpReference]


class _Commands(_Open):
    dims: list[str]
    units: list[str] = []


class _Dataset(_Open):
    path: str | None = None
    fingerprint: str | None = None
    sources: dict[str, int | float] | None = None


class _Logs(_Open):
    """Which logs were read (:mod:`offline_adp.evaluation.logs`)."""

    kind: Literal["held_out", "fit", "other"] | None = None
    in_sample: bool | None = None
    episodes: int | None = None
    of: int | None = None
    description: str | None = None


class _Discount(_Open):
    fit: float | None = None
    evaluation: float | None = None
    evaluation_source: str | None = None


class _Ranked(_Open):
    """An entry of the stored headline's ranking (:func:`~offline_adp.evaluation.summary.rank_estimators`)."""

    name: str
    label: str
    tier: Literal[0, 1, 2]
    reason: str = ""
    estimate: float | None
    interval: Bounds | None = None
    shown_interval: Bounds | None = None
    level: float | None = None
    level_note: str | None = None
    plugin_estimate: float | None = None

    @model_validator(mode="after")
    def _as_ranked(self) -> _Ranked:
        if self.tier < 2 and self.estimate is None:
            raise ValueError(f"tier {self.tier} needs an estimate")
        if self.tier == 0 and self.interval is None:
            raise ValueError("tier 0 needs an interval")
        return self


class _Text(_Open):
    text: str


class _Convergence(_Text):
    verdict: str | None = None


class _Verdict(_Text):
    outcome: Outcome | None = None
    performance: str | None = None
    support_left: bool | None = None


class _Headline(_Open):
    best: _Ranked | None
    ranking: list[_Ranked]
    shift: _Text
    convergence: _Convergence
    verdict: _Verdict
    n_warnings: int
    outcome: Outcome | None = None
    discount_note: str | None = None
    logs_note: str | None = None


class MetricsFile(_Open):
    """The structure of ``metrics.json`` that ``report``, ``compare`` and ``run`` read: a
    file without it (``"ope": "nonsense"``) is an :class:`~offline_adp.errors.ArtifactError`
    naming the file and key before anything indexes into it."""

    ope: dict[str, _Estimate]
    estimand: _Estimand = _Estimand()
    dataset: _Dataset = _Dataset()
    algorithm: str | None = None
    simulator: str | None = None
    simulator_note: str | None = None
    warnings: list[Any] = []
    rollout: _Rollouts | None = None
    shift: dict[str, _ShiftBlock] = {}
    pooled_shift: _Pooled | None = None
    psdp_bound: _Psdp | None = None
    per_source: dict[str, _Source] | None = None
    behaviour: _Behaviour | None = None
    behaviour_value: _BehaviourValue | None = None
    cost_distribution: _CostDistribution | None = None
    discount: _Discount | None = None
    logs: _Logs | None = None
    headline: _Headline | None = None
    worst_step: _WorstStep | None = None
    per_step_counts: list[int] | None = None
    min_states_per_step: int | None = None
    commands: _Commands | None = None
    not_usable: dict[str, str] | None = None


class ReportMetricsFile(MetricsFile):
    """:class:`MetricsFile` with what the report shows unconditionally: the behaviour model
    and the policy's support violations (and, for a discrete policy, the clipping)."""

    @model_validator(mode="after")
    def _shown(self) -> ReportMetricsFile:
        beh = self.behaviour
        need = {"behaviour": beh, "behaviour.support_violations.fraction": beh and beh.support_violations.fraction}
        if self.commands is None and beh is not None:
            need.update({"behaviour.source": beh.source, "behaviour.clip": beh.clip,
                         "behaviour.n_clipped": beh.n_clipped,
                         "behaviour.support_violations.threshold": beh.support_violations.threshold})
        missing = [k for k, v in need.items() if v is None]
        if missing:
            raise ValueError(f"missing {', '.join(missing)} (the report shows them)")
        return self


def frame_records(df: Any) -> list[dict[str, Any]]:
    """A table's rows as ``metrics.json`` stores them: numbers exact (pandas' ``to_json``
    rounds to 10 digits: a step's classifier AUC of 0.950000000004 read 0.95 and fell out
    of the count of steps above 0.95 that the warnings made), NaN and infinities null."""
    import math

    def cell(v: Any) -> Any:
        v = v.item() if hasattr(v, "item") else v
        return None if isinstance(v, float) and not math.isfinite(v) else v

    return [{str(k): cell(v) for k, v in r.items()} for r in df.to_dict(orient="records")]


def read_metrics(path: str | Path, structure: type[MetricsFile] = MetricsFile) -> dict[str, Any]:
    """``metrics.json`` through the gates of every file we read: a regular file of bounded
    size and nesting (:func:`~offline_adp.data.files.read_json_file`), then the structure
    of :class:`MetricsFile` (or ``structure``, e.g. :class:`ReportMetricsFile`); returns the
    file's keys as validated (ints where floats are read become floats)."""
    from pydantic import ValidationError as PydanticValidationError

    from offline_adp.config import format_validation_error
    from offline_adp.data.files import read_json_file
    from offline_adp.errors import ArtifactError

    m = read_json_file(path)
    try:
        return structure.model_validate(m).model_dump(exclude_unset=True)
    except PydanticValidationError as exc:
        raise ArtifactError(format_validation_error(exc, structure, str(path)).replace("\n", " ")
                            + "; not a metrics.json this version reads (run `offline-adp evaluate` again)") from None
