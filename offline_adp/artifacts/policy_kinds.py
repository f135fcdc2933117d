"""Policies in artifacts: each kind's writer and checked reader (greedy, greedy_command,
uniform, tabular, mixture, non-stationary, classifier, distilled_command),
:func:`save_policy` and :func:`load_index_policy` (see :mod:`offline_adp.artifacts`)."""

from __future__ import annotations

from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.artifacts import checks as C
from offline_adp.artifacts.estimators import Arrays, _export_estimator, _guard, _import_estimator
from offline_adp.artifacts.kinds import _Kinds
from offline_adp.artifacts.q_kinds import _export_q, _import_q, _probe, load_q
from offline_adp.artifacts.storage import _read, _write
from offline_adp.errors import ArtifactError


def _write_tabular(pi: Any, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
    arrays[f"{key}.table"] = pi.table
    return {"table": f"{key}.table"}


def _read_tabular(spec: dict[str, Any], arrays: Any, where: str) -> Any:
    from offline_adp.policies import TabularPolicy

    table = C.array(arrays, spec.get("table"), where, kinds="biuf")  # type: ignore[arg-type]
    if table.ndim not in (2, 3) or 0 in table.shape or not np.all(np.isfinite(table)) or np.any(table < 0):
        raise ArtifactError(f"{where}: {spec.get('table')}: a policy table needs finite probabilities >= 0 of shape "
                            f"(states, actions) or (steps, states, actions), got {table.shape}")
    return TabularPolicy(table)


def _read_parts(spec: dict[str, Any], arrays: Any, where: str, field: str, kind: str) -> list[Any]:
    parts = spec.get(field)
    if not isinstance(parts, list) or not parts:
        raise ArtifactError(f"{where}: {kind} policy needs a non-empty list of policies")
    pols = [_import_policy(c, arrays, where) for c in parts]
    if len({p.n_actions for p in pols}) != 1:
        raise ArtifactError(f"{where}: {kind} policy mixes action counts")
    return pols


def _read_mixture(spec: dict[str, Any], arrays: Any, where: str) -> Any:
    from offline_adp.policies import MixturePolicy

    pols = _read_parts(spec, arrays, where, "components", "mixture")
    w = spec.get("weights")
    if not isinstance(w,
                      list) or len(w) != len(pols) or not all(isinstance(x, int | float)
                                                              and not isinstance(x, bool) for x in w):
        raise ArtifactError(f"{where}: mixture needs one numeric weight per component")
    try:
        return MixturePolicy(pols, w)
    except ValueError as exc:
        raise ArtifactError(f"{where}: {exc}") from None


def _write_classifier(pi: Any, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
    fmap = None if pi.feature_map is None else _export_estimator(pi.feature_map, arrays, f"{key}.phi")
    clf = None if pi.classifier is None else _export_estimator(pi.classifier, arrays, f"{key}.clf")
    return {"n_actions": pi.n_actions, "constant": pi.constant, "classifier": clf, "feature_map": fmap}


def _read_classifier(spec: dict[str, Any], arrays: Any, where: str) -> Any:
    from offline_adp.policies import ClassifierPolicy

    n_actions = C.check_int(spec.get("n_actions"), where, "n_actions", 1, 1_000_000)
    constant = spec.get("constant")
    if constant is not None:
        C.check_int(constant, where, "constant", 0, n_actions - 1)
    clf = None if spec.get("classifier") is None else _guard(_import_estimator(spec["classifier"], arrays, where),
                                                             where, "classifier")
    if clf is None and constant is None:
        raise ArtifactError(f"{where}: classifier policy with neither a classifier nor a constant action")
    classes = getattr(clf, "classes_", None)
    if classes is not None:
        c = np.asarray(classes)
        if c.dtype.kind not in "iu" or (len(c) and (c.min() < 0 or c.max() >= n_actions)):
            raise ArtifactError(f"{where}: classifier classes {c[:10].tolist()} are not action indices in [0, "
                                f"{n_actions})")
    fmap = None if spec.get("feature_map") is None else _guard(_import_estimator(spec["feature_map"], arrays, where),
                                                               where, "feature_map")
    return ClassifierPolicy(clf, n_actions, constant, fmap)


def _read_greedy_command(spec: dict[str, Any], arrays: Any, where: str) -> Any:
    from offline_adp.policies import GreedyCommandPolicy
    from offline_adp.qfunctions import command_encoder

    q = _import_q(spec.get("q"), arrays, where)
    if command_encoder(q) is None:
        raise ArtifactError(f"{where}: a greedy_command policy needs a Q-function over continuous commands")
    return GreedyCommandPolicy(q)


def _write_distilled(pi: Any, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
    arrays[f"{key}.low"], arrays[f"{key}.high"] = pi.low, pi.high
    out: dict[str, Any] = {"models": [_export_estimator(m, arrays, f"{key}.u{c}") for c, m in enumerate(pi.models)],
                           "low": f"{key}.low", "high": f"{key}.high", "max_rate": None, "n_features": pi.n_features,
                           "report": pi.report}
    if pi.max_rate is not None:
        arrays[f"{key}.max_rate"] = pi.max_rate
        out["max_rate"] = f"{key}.max_rate"
    return out


def _read_distilled(spec: dict[str, Any], arrays: Any, where: str) -> Any:
    """A :class:`~offline_adp.distill.DistilledCommandPolicy`: tree ensembles only (checked
    arrays), bounds and rate limit of one length per component, then one probe."""
    from offline_adp.distill import DistilledCommandPolicy

    models = spec.get("models")
    if not isinstance(models, list) or not 1 <= len(models) <= 1024:
        raise ArtifactError(f"{where}: a distilled_command policy needs a list of 1 to 1024 models (one per component)")
    if not all(isinstance(m, dict) and m.get("kind") == "tree_ensemble" for m in models):
        raise ArtifactError(f"{where}: a distilled_command policy's models must be tree ensembles")
    d = C.check_int(spec.get("n_features"), where, "n_features", 1, C.MAX_WIDTH)
    ens = [_import_estimator(m, arrays, where) for m in models]
    m = len(ens)
    low, high = (np.asarray(C.array(arrays, spec.get(k), where, kinds="f", ndim=1),
                            np.float64) for k in ("low", "high"))
    rate = None if spec.get("max_rate") is None else \
        np.asarray(C.array(arrays, spec.get("max_rate"), where, kinds="f", ndim=1), np.float64)
    if low.shape != (m,) or high.shape != (m,) or (rate is not None and rate.shape != (m,)):
        raise ArtifactError(f"{where}: low {low.shape}, high {high.shape}, max_rate "
                            f"{None if rate is None else rate.shape}: one value per component ({m}) required")
    if np.isnan(low).any() or np.isnan(high).any() or (low > high).any() or \
            (rate is not None and (not np.isfinite(rate).all() or (rate <= 0).any())):
        raise ArtifactError(f"{where}: bounds must satisfy low <= high (no NaN) and max_rate be finite and > 0")
    for c, e in enumerate(ens):
        w = getattr(e, "n_features_in_", None)
        if w is not None and w != d:
            raise ArtifactError(f"{where}: model {c} reads {w} features, the policy {d}")
    report = spec.get("report")
    pi = DistilledCommandPolicy(ens, low, high, rate, n_features=d, report=report if isinstance(report, dict) else None)
    _probe(where, "the distilled policy", lambda: pi.raw_commands(np.zeros((2, d))), (2, m))
    return pi


def _read_uniform(spec: dict[str, Any], arrays: Any, where: str) -> Any:
    """A stored uniform policy: ``n_actions`` and, for one over some actions, their indices
    (checked: distinct, in range)."""
    from offline_adp.policies import UniformPolicy

    n = C.check_int(spec.get("n_actions"), where, "n_actions", 1, 1_000_000)
    acts = spec.get("actions")
    if acts is None:
        return UniformPolicy(n)
    if not isinstance(acts, list) or not acts or len(acts) > n:
        raise C.fail(where, "actions", f"expected a list of 1 to {n} action indices, found {acts!r}")
    got = [C.check_int(a, where, "actions[]", 0, n - 1) for a in acts]
    if len(set(got)) != len(got):
        raise C.fail(where, "actions", f"expected distinct action indices, found {acts!r}")
    return UniformPolicy(n, got)


def _register_policies() -> None:
    """Register the package's policy kinds (on first use: policies import lazily to keep this module light)."""
    from offline_adp.policies import (
        ClassifierPolicy,
        GreedyCommandPolicy,
        GreedyPolicy,
        MixturePolicy,
        NonStationaryPolicy,
        TabularPolicy,
        UniformPolicy,
    )

    register_policy_kind("greedy", GreedyPolicy, lambda pi, arrays, key: {"q": _export_q(pi.q, arrays, f"{key}.q")},
                         lambda spec, arrays, where: GreedyPolicy(_import_q(spec.get("q"), arrays, where)))  # type: ignore[arg-type]
    register_policy_kind("greedy_command", GreedyCommandPolicy,
                         lambda pi, arrays, key: {"q": _export_q(pi.q, arrays, f"{key}.q")}, _read_greedy_command)
    register_policy_kind("uniform", UniformPolicy, lambda pi, arrays, key: {
        "n_actions": pi.n_actions, **({"actions": pi.actions} if getattr(pi, "actions", None) is not None else {})},
        _read_uniform)
    register_policy_kind("tabular", TabularPolicy, _write_tabular, _read_tabular)
    register_policy_kind("mixture", MixturePolicy,
                         lambda pi, arrays, key: {"weights": pi.weights.tolist(), "components": [
                             _export_policy(c, arrays, f"{key}.c{i}") for i, c in enumerate(pi.components)]},
                         _read_mixture)
    register_policy_kind("non_stationary", NonStationaryPolicy,
                         lambda pi, arrays, key: {"steps": [_export_policy(c, arrays, f"{key}.t{i}")
                                                            for i, c in enumerate(pi.steps)]},
                         lambda spec, arrays, where: NonStationaryPolicy(
                             _read_parts(spec, arrays, where, "steps", "non_stationary")))
    register_policy_kind("classifier", ClassifierPolicy, _write_classifier, _read_classifier)
    from offline_adp.distill import DistilledCommandPolicy

    register_policy_kind("distilled_command", DistilledCommandPolicy, _write_distilled, _read_distilled)


_POLICY_KINDS = _Kinds("policy", load=_register_policies)
#: ``register_policy_kind(kind, cls, write, read)``: see :meth:`_Kinds.register`
register_policy_kind = _POLICY_KINDS.register
_export_policy, _import_policy = _POLICY_KINDS.export, _POLICY_KINDS.read


def save_policy(policy: Any, directory: str | PathLike[str], extra: dict[str, Any] | None = None) -> None:
    """Write a policy (greedy, greedy_command, distilled_command, uniform, tabular, mixture,
    non-stationary, classifier) as
    ``policy.json`` + ``policy.npz``."""
    arrays = Arrays()
    _write(directory, "policy", {"policy": _export_policy(policy, arrays, "p")}, arrays, extra)


def load_index_policy(directory: str | PathLike[str]) -> Any:
    """Read a policy written by :func:`save_policy` (or the greedy policy of a saved Q)
    *without* a signature: it knows no feature names nor action values, so its ``act``
    takes arrays in the fitted column order and returns action **indices**.

    This is what algorithms use (``act_index``). To deploy a policy, use
    :func:`offline_adp.load_policy` (:func:`offline_adp.deploy.load_policy`), which
    attaches the run's signature: ``act`` then returns action values and checks the
    observation's names and width.
    """
    d = Path(directory)
    if not (d / "policy.json").exists() and (d / "q.json").exists():
        from offline_adp.policies import greedy_policy

        return greedy_policy(load_q(d)[0])
    return _read(d, "policy", "policy", _import_policy, "policy")[0]

