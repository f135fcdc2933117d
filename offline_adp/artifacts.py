"""Saving and loading fitted Q-functions without executing code from the files.

Everything is JSON, ``.npz`` arrays (loaded with ``allow_pickle=False``) or LightGBM's
text model format. scikit-learn forests are exported to :class:`TreeEnsemble` arrays;
other scikit-learn estimators go through an explicit allow-list: their constructor
parameters (JSON) and fitted array attributes are stored, and loading rebuilds the
estimator from the allow-listed class and sets those attributes. Anything else raises
:class:`ArtifactError` naming the type, rather than falling back to pickle.
"""

from __future__ import annotations

import importlib
import json
import warnings
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp._version import __version__
from offline_adp.errors import FormatVersionWarning, OfflineADPError
from offline_adp.learners import BoostedSumQ
from offline_adp.qfunctions import (
    QEncoder,
    QFunction,
    RegressorQ,
    TimeIndexedQ,
    TreeEnsemble,
    TreeQ,
)

ARTIFACT_VERSION = "1"

#: Estimators that may be rebuilt from stored parameters and arrays (module, class).
ALLOWED = {
    "LinearRegression": "sklearn.linear_model",
    "Ridge": "sklearn.linear_model",
    "PolynomialFeatures": "sklearn.preprocessing",
    "StandardScaler": "sklearn.preprocessing",
    "MinMaxScaler": "sklearn.preprocessing",
    "OneHotEncoder": "sklearn.preprocessing",
    "Pipeline": "sklearn.pipeline",
    "KNeighborsRegressor": "sklearn.neighbors",
    "MLPRegressor": "sklearn.neural_network",
    "TabularRegressor": "offline_adp.regressors",
    "TabularClassifier": "offline_adp.regressors",
    "SelectColumns": "offline_adp.features",
}


class ArtifactError(OfflineADPError):
    """An artifact cannot be written or read safely."""


def versions() -> dict[str, str]:
    """Versions of the package and the libraries whose models we store."""
    import lightgbm
    import sklearn

    return {"offline_adp": __version__, "numpy": np.__version__, "scikit-learn": sklearn.__version__, "lightgbm": lightgbm.__version__}


# ----------------------------------------------------------------------------- estimators
def _jsonable(v: Any) -> bool:
    try:
        json.dumps(v)
        return True
    except TypeError:
        return False


def _export_estimator(est: Any, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
    name = type(est).__name__
    if hasattr(est, "classes_") and hasattr(est, "estimators_") and hasattr(est.estimators_[0], "tree_"):
        ens = TreeEnsemble.from_sklearn(est)
        arrays.update(ens.to_arrays(f"{key}."))
        probs = np.concatenate([e.tree_.value[:, 0, :] for e in est.estimators_])
        arrays[f"{key}.class_values"] = probs / np.maximum(probs.sum(axis=1, keepdims=True), 1e-300)
        arrays[f"{key}.classes"] = np.asarray(est.classes_)
        return {"kind": "tree_classifier", "key": key}
    if hasattr(est, "estimators_") and hasattr(est.estimators_[0], "tree_"):
        arrays.update(TreeEnsemble.from_sklearn(est).to_arrays(f"{key}."))
        return {"kind": "tree_ensemble", "key": key}
    if isinstance(est, TreeEnsemble):
        arrays.update(est.to_arrays(f"{key}."))
        return {"kind": "tree_ensemble", "key": key}
    booster = getattr(est, "booster_", None) if name == "LGBMRegressor" else (est if name == "Booster" else None)
    if booster is not None:
        return {"kind": "lightgbm", "model": booster.model_to_string()}
    if name not in ALLOWED:
        raise ArtifactError(f"cannot save a {name} safely; allowed: scikit-learn forests, LightGBM, {sorted(ALLOWED)}")
    if name == "Pipeline":
        return {"kind": "pipeline", "steps": [[n, _export_estimator(s, arrays, f"{key}.{i}")] for i, (n, s) in enumerate(est.steps)]}
    params = {k: v for k, v in est.get_params(deep=False).items() if _jsonable(v)}
    attrs: dict[str, Any] = {}
    for k, v in vars(est).items():
        if k in ("_fit_X", "_y"):  # k-NN training data: refitted on load
            arrays[f"{key}.{k}"] = np.asarray(v)
            attrs[k] = {"array": f"{key}.{k}"}
            continue
        fitted = k.endswith("_") or (k.startswith("_") and not k.startswith("__"))
        if not fitted or k.startswith("_oadp") or k in params:
            continue
        if isinstance(v, np.ndarray) and v.dtype != object:
            arrays[f"{key}.{k}"] = v
            attrs[k] = {"array": f"{key}.{k}"}
        elif isinstance(v, list) and all(isinstance(x, np.ndarray) and x.dtype != object for x in v):
            for i, x in enumerate(v):
                arrays[f"{key}.{k}.{i}"] = x
            attrs[k] = {"arrays": [f"{key}.{k}.{i}" for i in range(len(v))]}
        elif isinstance(v, np.generic):
            attrs[k] = {"value": v.item()}
        elif _jsonable(v):
            attrs[k] = {"value": v}
        elif isinstance(v, list) and all(isinstance(x, np.ndarray) for x in v):  # e.g. OneHotEncoder.categories_
            for i, x in enumerate(v):
                arrays[f"{key}.{k}.{i}"] = np.asarray(x.tolist())
            attrs[k] = {"arrays": [f"{key}.{k}.{i}" for i in range(len(v))]}
    return {"kind": "sklearn", "class": name, "params": params, "attrs": attrs}


class _Booster:
    def __init__(self, model: str) -> None:
        import lightgbm as lgb

        self.booster = lgb.Booster(model_str=model)

    def predict(self, X: np.ndarray, raw_score: bool = False) -> np.ndarray:
        return self.booster.predict(X, raw_score=raw_score)


class _TreeClassifier:
    """A saved forest classifier: mean over trees of the leaves' class fractions."""

    def __init__(self, ensemble: TreeEnsemble, class_values: np.ndarray, classes: np.ndarray) -> None:
        self.ensemble, self.class_values, self.classes_ = ensemble, class_values, classes

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        leaves = self.ensemble.apply(X)
        return np.ascontiguousarray(self.class_values[leaves]).mean(axis=1)

    def predict(self, X: np.ndarray) -> np.ndarray:
        return self.classes_[self.predict_proba(X).argmax(axis=1)]


def _import_estimator(spec: dict[str, Any], arrays: Any) -> Any:
    kind = spec["kind"]
    if kind == "tree_ensemble":
        return TreeEnsemble.from_arrays(arrays, f"{spec['key']}.")
    if kind == "lightgbm":
        return _Booster(spec["model"])
    if kind == "tree_classifier":
        return _TreeClassifier(TreeEnsemble.from_arrays(arrays, f"{spec['key']}."), np.asarray(arrays[f"{spec['key']}.class_values"]),
                               np.asarray(arrays[f"{spec['key']}.classes"]))
    if kind == "pipeline":
        from sklearn.pipeline import Pipeline

        return Pipeline([(n, _import_estimator(s, arrays)) for n, s in spec["steps"]])
    if kind != "sklearn" or spec["class"] not in ALLOWED:
        raise ArtifactError(f"refusing to load estimator {spec.get('class', kind)!r}: not in the allow-list")
    cls = getattr(importlib.import_module(ALLOWED[spec["class"]]), spec["class"])
    est = cls(**spec["params"])
    fit_data = {}
    for k, a in spec["attrs"].items():
        if "array" in a:
            val: Any = np.asarray(arrays[a["array"]])
        elif "arrays" in a:
            val = [np.asarray(arrays[x]) for x in a["arrays"]]
        else:
            val = a["value"]
        if k in ("_fit_X", "_y"):
            fit_data[k] = val
        else:
            setattr(est, k, val)
    if fit_data:  # k-NN: rebuild the search structure from the stored training data
        est.fit(fit_data["_fit_X"], fit_data["_y"])
    return est


# ----------------------------------------------------------------------------- Q-functions
def _export_q(q: QFunction, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
    if isinstance(q, TimeIndexedQ):
        return {"kind": "time_indexed", "qs": [_export_q(x, arrays, f"{key}.t{t}") for t, x in enumerate(q.qs)]}
    enc = q.encoder  # type: ignore[attr-defined]
    arrays[f"{key}.action_features"] = enc.action_features
    e = {
        "n_actions": enc.n_actions,
        "per_action": enc.per_action,
        "action_features": f"{key}.action_features",
        "feature_map": None if enc.feature_map is None else _export_estimator(enc.feature_map, arrays, f"{key}.phi"),
    }
    if isinstance(q, BoostedSumQ):
        return {"kind": "boosted_sum", "encoder": e, "boosters": [b.model_to_string() if hasattr(b, "model_to_string") else b.booster.model_to_string() for b in q.boosters]}
    if isinstance(q, RegressorQ | TreeQ):
        models = [_export_estimator(m, arrays, f"{key}.m{i}") for i, m in enumerate(q.models)]
        return {"kind": "regressor", "encoder": e, "models": models}
    raise ArtifactError(f"cannot save a {type(q).__name__}")


def _import_q(spec: dict[str, Any], arrays: Any) -> QFunction:
    if spec["kind"] == "time_indexed":
        return TimeIndexedQ([_import_q(x, arrays) for x in spec["qs"]])
    e = spec["encoder"]
    fmap = None if e["feature_map"] is None else _import_estimator(e["feature_map"], arrays)
    enc = QEncoder(e["n_actions"], np.asarray(arrays[e["action_features"]]), e["per_action"], fmap)
    if spec["kind"] == "boosted_sum":
        return BoostedSumQ([_Booster(m) for m in spec["boosters"]], enc)
    if spec["kind"] == "regressor":
        return RegressorQ([_import_estimator(m, arrays) for m in spec["models"]], enc)
    raise ArtifactError(f"unknown Q-function kind {spec['kind']!r}")


def _write(directory: str | PathLike[str], stem: str, payload: dict[str, Any], arrays: dict[str, np.ndarray],
           extra: dict[str, Any] | None) -> None:
    """``<stem>.json`` (payload, versions, extra) + ``<stem>.npz`` (arrays) in ``directory``."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    np.savez(d / f"{stem}.npz", **arrays)
    spec = {"artifact_version": ARTIFACT_VERSION, "versions": versions(), **payload, **(extra or {})}
    (d / f"{stem}.json").write_text(json.dumps(spec, indent=1))


def _read(directory: str | PathLike[str], stem: str, key: str, build: Any, what: str) -> tuple[Any, dict[str, Any]]:
    """Read what :func:`_write` wrote (arrays without pickle); warns on other versions."""
    d = Path(directory)
    try:
        spec = json.loads((d / f"{stem}.json").read_text())
        arrays = np.load(d / f"{stem}.npz", allow_pickle=False)
    except FileNotFoundError as exc:
        raise ArtifactError(f"{d}: no saved {what} ({exc.filename} missing)") from exc
    except (json.JSONDecodeError, ValueError) as exc:
        raise ArtifactError(f"{d}: unreadable {what} artifact ({exc})") from exc
    now = versions()
    diff = {k: (v, now.get(k)) for k, v in spec.get("versions", {}).items() if now.get(k) != v}
    if diff:
        warnings.warn(f"{d}: written with other versions {diff} (saved, current)", FormatVersionWarning, stacklevel=3)
    with arrays:
        return build(spec[key], arrays), spec


def save_q(q: QFunction, directory: str | PathLike[str], extra: dict[str, Any] | None = None) -> None:
    """Write ``q`` into ``directory`` (``q.json`` + ``q.npz``)."""
    arrays: dict[str, np.ndarray] = {}
    _write(directory, "q", {"q": _export_q(q, arrays, "q")}, arrays, extra)


def load_q(directory: str | PathLike[str]) -> tuple[QFunction, dict[str, Any]]:
    """Read a Q-function written by :func:`save_q`; returns it and the JSON metadata.

    Warns (``FormatVersionWarning``) when the package or library versions differ.
    """
    return _read(directory, "q", "q", _import_q, "Q-function")


# ----------------------------------------------------------------------------- policies
def _export_policy(pi: Any, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
    from offline_adp.policies import (
        ClassifierPolicy,
        GreedyPolicy,
        MixturePolicy,
        NonStationaryPolicy,
        TabularPolicy,
        UniformPolicy,
    )

    if isinstance(pi, GreedyPolicy):
        return {"kind": "greedy", "q": _export_q(pi.q, arrays, f"{key}.q")}
    if isinstance(pi, UniformPolicy):
        return {"kind": "uniform", "n_actions": pi.n_actions}
    if isinstance(pi, TabularPolicy):
        arrays[f"{key}.table"] = pi.table
        return {"kind": "tabular", "table": f"{key}.table"}
    if isinstance(pi, MixturePolicy):
        return {"kind": "mixture", "weights": pi.weights.tolist(),
                "components": [_export_policy(c, arrays, f"{key}.c{i}") for i, c in enumerate(pi.components)]}
    if isinstance(pi, NonStationaryPolicy):
        return {"kind": "non_stationary", "steps": [_export_policy(c, arrays, f"{key}.t{i}") for i, c in enumerate(pi.steps)]}
    if isinstance(pi, ClassifierPolicy):
        fmap = None if pi.feature_map is None else _export_estimator(pi.feature_map, arrays, f"{key}.phi")
        clf = None if pi.classifier is None else _export_estimator(pi.classifier, arrays, f"{key}.clf")
        return {"kind": "classifier", "n_actions": pi.n_actions, "constant": pi.constant, "classifier": clf, "feature_map": fmap}
    raise ArtifactError(f"cannot save a {type(pi).__name__} policy safely")


def _import_policy(spec: dict[str, Any], arrays: Any) -> Any:
    from offline_adp.policies import (
        ClassifierPolicy,
        GreedyPolicy,
        MixturePolicy,
        NonStationaryPolicy,
        TabularPolicy,
        UniformPolicy,
    )

    kind = spec["kind"]
    if kind == "greedy":
        return GreedyPolicy(_import_q(spec["q"], arrays))
    if kind == "uniform":
        return UniformPolicy(spec["n_actions"])
    if kind == "tabular":
        return TabularPolicy(np.asarray(arrays[spec["table"]]))
    if kind == "mixture":
        return MixturePolicy([_import_policy(c, arrays) for c in spec["components"]], spec["weights"])
    if kind == "non_stationary":
        return NonStationaryPolicy([_import_policy(c, arrays) for c in spec["steps"]])
    if kind == "classifier":
        clf = None if spec["classifier"] is None else _import_estimator(spec["classifier"], arrays)
        fmap = None if spec["feature_map"] is None else _import_estimator(spec["feature_map"], arrays)
        return ClassifierPolicy(clf, spec["n_actions"], spec["constant"], fmap)
    raise ArtifactError(f"unknown policy kind {kind!r}")


def save_policy(policy: Any, directory: str | PathLike[str], extra: dict[str, Any] | None = None) -> None:
    """Write a policy (greedy, uniform, tabular, mixture, non-stationary, classifier) as
    ``policy.json`` + ``policy.npz``."""
    arrays: dict[str, np.ndarray] = {}
    _write(directory, "policy", {"policy": _export_policy(policy, arrays, "p")}, arrays, extra)


def load_policy(directory: str | PathLike[str]) -> Any:
    """Read a policy written by :func:`save_policy` (or the greedy policy of a saved Q)."""
    d = Path(directory)
    if not (d / "policy.json").exists() and (d / "q.json").exists():
        from offline_adp.policies import GreedyPolicy

        return GreedyPolicy(load_q(d)[0])
    return _read(d, "policy", "policy", _import_policy, "policy")[0]
