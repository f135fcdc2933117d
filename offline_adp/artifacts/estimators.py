"""Estimators inside artifacts: scikit-learn forests as :class:`TreeEnsemble` arrays,
LightGBM model text, allow-listed scikit-learn estimators as parameters and fitted arrays;
loaded back without executing code, each checked and probed (see :mod:`offline_adp.artifacts`)."""

from __future__ import annotations

import importlib
import json
import warnings
import weakref
from typing import Any

import numpy as np

import offline_adp.artifacts.checks as C
from offline_adp.artifacts.lightgbm_text import check_lightgbm_text
from offline_adp.artifacts.tree_tables import (
    LoadedEnsemble,
    compact_arrays,
    load_compact_ensemble,
    load_ensemble,
)
from offline_adp.errors import ArtifactError
from offline_adp.trees import TreeEnsemble

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



def _jsonable(v: Any) -> bool:
    try:
        json.dumps(v)
        return True
    except TypeError:
        return False


def _export_estimator(est: Any, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
    est = getattr(est, "_oadp_inner", est)  # a loaded estimator re-saved (resume)
    name = type(est).__name__
    if hasattr(est, "classes_") and hasattr(est, "estimators_") and hasattr(est.estimators_[0], "tree_"):
        ens = TreeEnsemble.from_sklearn(est)
        arrays.update(ens.to_arrays(f"{key}."))
        probs = np.concatenate([e.tree_.value[:, 0, :] for e in est.estimators_])
        arrays[f"{key}.class_values"] = probs / np.maximum(probs.sum(axis=1, keepdims=True), 1e-300)
        arrays[f"{key}.classes"] = np.asarray(est.classes_)
        return {"kind": "tree_classifier", "key": key}
    if isinstance(est, _TreeClassifier):  # a loaded forest classifier saved again (e.g. the policy FQE evaluates)
        arrays.update(est.ensemble.to_arrays(f"{key}.", layout="nodes"))  # its node order: the class values'
        arrays[f"{key}.class_values"], arrays[f"{key}.classes"] = est.class_values, np.asarray(est.classes_)
        return {"kind": "tree_classifier", "key": key}
    if hasattr(est, "estimators_") and hasattr(est.estimators_[0], "tree_"):
        return _export_ensemble(TreeEnsemble.from_sklearn(est), arrays, key, _width(est))
    if isinstance(est, TreeEnsemble):
        return _export_ensemble(est, arrays, key, _width(getattr(est, "_forest", None) or est))
    booster = getattr(est, "booster_", None) if name == "LGBMRegressor" else (est if name == "Booster" else None)
    if booster is not None:
        return {"kind": "lightgbm", "model": booster.model_to_string()}
    if name not in ALLOWED:
        raise ArtifactError(f"cannot save a {name} safely; allowed: scikit-learn forests, LightGBM, {sorted(ALLOWED)}")
    if name == "Pipeline":
        return {
            "kind": "pipeline",
            "steps": [[n, _export_estimator(s, arrays, f"{key}.{i}")] for i, (n, s) in enumerate(est.steps)],
        }
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


class Arrays(dict):
    """The arrays of one artifact being written, and the tree structures already among
    them (``structures``: id of the child array -> (that array, its key)), so that
    ensembles sharing one structure (:meth:`TreeEnsemble.with_values`, e.g. a
    finite-horizon fit's per-step Q-functions) store it once."""

    def __init__(self) -> None:
        super().__init__()
        self.structures: dict[int, tuple[np.ndarray, str]] = {}


def _export_ensemble(ens: TreeEnsemble, arrays: dict[str, np.ndarray], key: str, width: int | None) -> dict[str, Any]:
    """A tree ensemble in the compact layout; its structure written once per artifact."""
    spec: dict[str, Any] = {"kind": "tree_ensemble", "key": key, "n_features": width}
    seen = getattr(arrays, "structures", None)
    if seen is not None and id(ens.left) in seen and seen[id(ens.left)][0] is ens.left:
        arrays.update(compact_arrays(ens, f"{key}.", structure=False))
        spec["structure"] = seen[id(ens.left)][1]
        return spec
    a = compact_arrays(ens, f"{key}.")
    arrays.update(a)
    if seen is not None and f"{key}.leaf_bits" in a:
        seen[id(ens.left)] = (ens.left, key)
    return spec


def _width(est: Any) -> int | None:
    """The input width a fitted estimator declares, if any."""
    w = getattr(est, "n_features_in_", None)
    return int(w) if isinstance(w, int | np.integer) else None


class _Booster:
    """A LightGBM booster rebuilt from checked model text (:func:`check_lightgbm_text`)."""

    def __init__(self, model: str, where: str = "<memory>", member: str = "lightgbm model") -> None:
        import lightgbm as lgb

        text = check_lightgbm_text(model, where, member) if where != "<memory>" else model
        self.booster = lgb.Booster(model_str=text)
        self.where, self.member = where, member

    def input_width(self) -> int:
        return int(self.booster.num_feature())

    def predict(self, X: np.ndarray, raw_score: bool = False) -> np.ndarray:
        n = self.booster.num_feature()
        if np.ndim(X) != 2 or np.shape(X)[1] != n:
            raise ArtifactError(f"{self.where}: {self.member}: model reads {n} features, the input has shape "
                                f"{np.shape(X)}")
        return self.booster.predict(X, raw_score=raw_score)


class _Guarded:
    """A loaded scikit-learn estimator (or pipeline) whose ``predict``/``transform``/
    ``predict_proba`` turn any failure into one ArtifactError naming the artifact: stored
    attributes can be consistent with each other and still not fit the data they are
    given (e.g. a scaler declaring 1 input feature applied to 7)."""

    def __init__(self, inner: Any, where: str, what: str) -> None:
        self._oadp_inner, self._oadp_where, self._oadp_what = inner, where, what

    def __getattr__(self, name: str) -> Any:  # fitted attributes (classes_, n_features_in_...)
        if name.startswith("_oadp"):
            raise AttributeError(name)
        found = getattr(self._oadp_inner, name)
        if name == "seen" and callable(found):  # a lookup table's support (TabularRegressor.seen), guarded too
            return lambda X: self._call("seen", X)
        return found

    def _call(self, method: str, X: Any) -> Any:
        try:  # on a copy: stored parameters (e.g. copy=False) must not let it edit the caller's array
            return getattr(self._oadp_inner, method)(np.array(X, copy=True))
        except ArtifactError:
            raise
        except Exception as exc:  # whatever the stored attributes make the estimator raise
            raise ArtifactError(f"{self._oadp_where}: {self._oadp_what}.{method} failed on input of shape "
                                f"{np.shape(X)} ({type(exc).__name__}: {exc})") from None

    def predict(self, X: Any) -> Any:
        return self._call("predict", X)

    def transform(self, X: Any) -> Any:
        return self._call("transform", X)

    def predict_proba(self, X: Any) -> Any:
        return self._call("predict_proba", X)


def _guard(est: Any, where: str, what: str) -> Any:
    """Wrap a loaded scikit-learn estimator or pipeline in :class:`_Guarded` (tree
    ensembles and boosters check their inputs themselves and stay as they are)."""
    return est if isinstance(est,
                             TreeEnsemble | _TreeClassifier
                             | _Booster) or where == "<memory>" else _Guarded(est, where, what)


class _TreeClassifier:
    """A saved forest classifier: mean over trees of the leaves' class fractions."""

    def __init__(self, ensemble: TreeEnsemble, class_values: np.ndarray, classes: np.ndarray) -> None:
        self.ensemble, self.class_values, self.classes_ = ensemble, class_values, classes

    def input_width(self) -> None:  # not declared by the saved arrays
        return None

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        leaves = self.ensemble.apply(X)
        return np.ascontiguousarray(self.class_values[leaves]).mean(axis=1)

    def predict(self, X: np.ndarray) -> np.ndarray:
        return self.classes_[self.predict_proba(X).argmax(axis=1)]


#: Structures checked while one artifact is read, by the opened file (id -> (weak reference, cache)),
#: for ensembles that share them. (An opened .npz is a Mapping: not hashable, so no WeakKeyDictionary.)
_CHECKED: dict[int, tuple[Any, dict[tuple[str, int | None], TreeEnsemble]]] = {}


def _structures(arrays: Any) -> dict[tuple[str, int | None], TreeEnsemble]:
    """The structures checked so far in the opened file ``arrays`` (an empty dict, kept
    nowhere, for what cannot be weakly referenced, e.g. an in-memory dict)."""
    key = id(arrays)
    hit = _CHECKED.get(key)
    if hit is not None and hit[0]() is arrays:
        return hit[1]
    try:
        ref = weakref.ref(arrays, lambda _, key=key: _CHECKED.pop(key, None))
    except TypeError:
        return {}
    _CHECKED[key] = (ref, {})
    return _CHECKED[key][1]


def _shared_structure(arrays: Any, key: str, structure: str, width: int | None, where: str) -> TreeEnsemble:
    """Ensemble ``key``'s leaf values on the structure stored under ``structure`` (checked
    once per file; the ensembles made from it share its compiled lookup)."""
    cache = _structures(arrays)
    base = cache.get((structure, width))
    if base is None:
        base = cache[(structure, width)] = load_compact_ensemble(arrays, f"{structure}.", where, width)
    values = C.check_leaf_values(arrays, f"{key}.", where)
    leaves = base.leaf_mask() if isinstance(base, LoadedEnsemble) else base.left < 0
    if len(values) != int(leaves.sum()):
        raise ArtifactError(f"{where}: {key}.value: {len(values)} leaf values for the {int(leaves.sum())} leaves of "
                            f"structure {structure}")
    full = np.zeros(len(base.value))
    full[leaves] = values
    return base.with_values(full)


def _import_estimator(spec: dict[str, Any], arrays: Any, where: str = "<memory>") -> Any:
    """Rebuild an estimator from its JSON ``spec`` and checked arrays (see
    :mod:`offline_adp.artifacts.checks`); anything malformed is an :class:`ArtifactError`."""
    if not isinstance(spec, dict):
        raise ArtifactError(f"{where}: estimator entry is not a JSON object")
    kind = spec.get("kind")
    if kind in ("tree_ensemble", "tree_classifier"):
        key = spec.get("key")
        if not isinstance(key, str):
            raise ArtifactError(f"{where}: {kind} entry without an array key")
        width = spec.get("n_features")
        width = None if width is None else C.check_int(width, where, f"{key}.n_features", 1, C.MAX_WIDTH)
        shared = spec.get("structure")
        if shared is not None and (kind != "tree_ensemble" or not isinstance(shared, str)):
            raise ArtifactError(f"{where}: {key}.structure: a tree ensemble's shared structure is named by its key")
        if shared is not None:
            ens = _shared_structure(arrays, key, shared, width, where)
        else:
            ens = load_ensemble(arrays, f"{key}.", where, width)
            if kind == "tree_ensemble" and isinstance(ens, LoadedEnsemble):  # others may share its structure
                _structures(arrays).setdefault((key, width), ens)
        ens.n_features_in_ = width  # type: ignore[attr-defined]
        if kind == "tree_ensemble":
            return ens
        cv = C.array(arrays, f"{key}.class_values", where, kinds="f", ndim=2)
        classes = C.array(arrays, f"{key}.classes", where, kinds="biufU", ndim=1)
        if cv.shape != (len(ens.value), len(classes)) or len(classes) == 0 or not np.all(np.isfinite(cv)):
            raise ArtifactError(f"{where}: {key}.class_values: shape {cv.shape} (or non-finite values) where "
                                f"({len(ens.value)} nodes, {len(classes)} classes) is required")
        return _TreeClassifier(ens, cv, classes)
    if kind == "lightgbm":
        return _Booster(spec.get("model"), where)
    if kind == "pipeline":
        from sklearn.pipeline import Pipeline

        steps = spec.get("steps")
        if not isinstance(steps,
                          list) or not steps or not all(isinstance(x,
                                                                   list) and len(x) == 2
                                                                   and isinstance(x[0], str) for x in steps):
            raise ArtifactError(f"{where}: pipeline entry needs a list of [name, estimator] steps")
        return Pipeline([(n, _import_estimator(s, arrays, where)) for n, s in steps])
    if kind != "sklearn" or spec.get("class") not in ALLOWED:
        raise ArtifactError(f"{where}: refusing to load estimator {spec.get('class', kind)!r}: not in the allow-list")
    cls = getattr(importlib.import_module(ALLOWED[spec["class"]]), spec["class"])
    params, attrs = spec.get("params"), spec.get("attrs")
    if not isinstance(params, dict) or not isinstance(attrs, dict):
        raise ArtifactError(f"{where}: {spec['class']} entry needs 'params' and 'attrs' objects")
    try:
        est = cls(**params)
    except (TypeError, ValueError) as exc:
        raise ArtifactError(f"{where}: {spec['class']} parameters rejected ({exc})") from None
    fit_data = {}
    for k, a in attrs.items():
        # only fitted data attributes: never a dunder or anything the class defines (methods)
        if not isinstance(k, str) or k.startswith("__") or hasattr(cls, k) or not isinstance(a, dict):
            raise ArtifactError(f"{where}: {spec['class']} attribute {k!r} is not a fitted attribute")
        if "array" in a:
            val: Any = C.array(arrays, a["array"], where, kinds="biufUV")
        elif "arrays" in a and isinstance(a["arrays"], list):
            val = [C.array(arrays, x, where, kinds="biufUV") for x in a["arrays"]]
        elif "value" in a:
            val = a["value"]
        else:
            raise ArtifactError(f"{where}: {spec['class']} attribute {k!r} has no array or value")
        if k in ("_fit_X", "_y"):
            fit_data[k] = val
        else:
            setattr(est, k, val)
    if fit_data:  # k-NN: rebuild the search structure from the stored training data
        if set(fit_data) != {"_fit_X", "_y"}:
            raise ArtifactError(f"{where}: {spec['class']} needs both _fit_X and _y")
        est.fit(fit_data["_fit_X"], fit_data["_y"])
    # fitted sklearn estimators declare it
    if "n_features_in_" in attrs or ALLOWED[spec["class"]].startswith("sklearn"):
        w = getattr(est, "n_features_in_", None)
        if isinstance(w, bool) or not isinstance(w, int | np.integer) or not 1 <= w <= 1_000_000:
            raise ArtifactError(f"{where}: {spec['class']}: n_features_in_ must be an integer in [1, "
                                f"1000000], found {w!r}")
    _probe(est, where, spec["class"])
    return est


def _probe(est: Any, where: str, what: str) -> None:
    """Run a fitted estimator once on a representative input of its declared width, so
    inconsistent stored attributes fail here as an ArtifactError, not later as a raw error."""
    width = _width(est)
    if width is None:
        return
    if not 1 <= width <= 1_000_000:
        raise ArtifactError(f"{where}: {what}: n_features_in_ = {width} out of range")
    cats = getattr(est, "categories_", None)
    X = np.zeros((2, width)) if cats is None else np.array([[c[0] if len(c) else 0 for c in cats]] * 2, dtype=object)
    method = next((getattr(est, m) for m in ("predict", "transform") if hasattr(est, m)), None)
    if method is None:
        return
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = np.asarray(method(X))
    except Exception as exc:  # any failure means the stored attributes do not fit together
        raise ArtifactError(f"{where}: {what}: stored attributes are inconsistent "
                            f"({type(exc).__name__}: {exc})") from None
    if out.dtype == object or len(out) != 2:
        raise ArtifactError(f"{where}: {what}: predicts {out.shape} {out.dtype} for 2 rows")
