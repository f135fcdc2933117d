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

from offline_adp import artifact_checks as C
from offline_adp._version import __version__
from offline_adp.errors import ArtifactError, FormatVersionWarning
from offline_adp.qfunctions import (
    BoostedSumQ,
    QEncoder,
    QFunction,
    RegressorQ,
    TimeIndexedQ,
    TreeQ,
)
from offline_adp.trees import TreeEnsemble

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
    est = getattr(est, "_oadp_inner", est)  # a loaded estimator re-saved (resume)
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
        return {"kind": "tree_ensemble", "key": key, "n_features": _width(est)}
    if isinstance(est, TreeEnsemble):
        arrays.update(est.to_arrays(f"{key}."))
        return {"kind": "tree_ensemble", "key": key, "n_features": _width(getattr(est, "_forest", None) or est)}
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


def _width(est: Any) -> int | None:
    """The input width a fitted estimator declares, if any."""
    w = getattr(est, "n_features_in_", None)
    return int(w) if isinstance(w, int | np.integer) else None


class _Booster:
    """A LightGBM booster rebuilt from checked model text (:func:`check_lightgbm_text`)."""

    def __init__(self, model: str, where: str = "<memory>", member: str = "lightgbm model") -> None:
        import lightgbm as lgb

        text = C.check_lightgbm_text(model, where, member) if where != "<memory>" else model
        self.booster = lgb.Booster(model_str=text)
        self.where, self.member = where, member

    def predict(self, X: np.ndarray, raw_score: bool = False) -> np.ndarray:
        n = self.booster.num_feature()
        if np.ndim(X) != 2 or np.shape(X)[1] != n:
            raise ArtifactError(f"{self.where}: {self.member}: model reads {n} features, the input has shape {np.shape(X)}")
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
        return getattr(self._oadp_inner, name)

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
    return est if isinstance(est, TreeEnsemble | _TreeClassifier | _Booster) or where == "<memory>" else _Guarded(est, where, what)


class _TreeClassifier:
    """A saved forest classifier: mean over trees of the leaves' class fractions."""

    def __init__(self, ensemble: TreeEnsemble, class_values: np.ndarray, classes: np.ndarray) -> None:
        self.ensemble, self.class_values, self.classes_ = ensemble, class_values, classes

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        leaves = self.ensemble.apply(X)
        return np.ascontiguousarray(self.class_values[leaves]).mean(axis=1)

    def predict(self, X: np.ndarray) -> np.ndarray:
        return self.classes_[self.predict_proba(X).argmax(axis=1)]


def _import_estimator(spec: dict[str, Any], arrays: Any, where: str = "<memory>") -> Any:
    """Rebuild an estimator from its JSON ``spec`` and checked arrays (see
    :mod:`offline_adp.artifact_checks`); anything malformed is an :class:`ArtifactError`."""
    if not isinstance(spec, dict):
        raise ArtifactError(f"{where}: estimator entry is not a JSON object")
    kind = spec.get("kind")
    if kind in ("tree_ensemble", "tree_classifier"):
        key = spec.get("key")
        if not isinstance(key, str):
            raise ArtifactError(f"{where}: {kind} entry without an array key")
        width = spec.get("n_features")
        width = None if width is None else C.check_int(width, where, f"{key}.n_features", 1, C.MAX_WIDTH)
        ens = TreeEnsemble(**C.check_tree_arrays(arrays, f"{key}.", where, width))
        ens.n_features_in_ = width  # type: ignore[attr-defined]
        if kind == "tree_ensemble":
            return ens
        cv = C.array(arrays, f"{key}.class_values", where, kinds="f", ndim=2)
        classes = C.array(arrays, f"{key}.classes", where, kinds="biufU", ndim=1)
        if cv.shape != (len(ens.left), len(classes)) or len(classes) == 0 or not np.all(np.isfinite(cv)):
            raise ArtifactError(f"{where}: {key}.class_values: shape {cv.shape} (or non-finite values) where "
                                f"({len(ens.left)} nodes, {len(classes)} classes) is required")
        return _TreeClassifier(ens, cv, classes)
    if kind == "lightgbm":
        return _Booster(spec.get("model"), where)
    if kind == "pipeline":
        from sklearn.pipeline import Pipeline

        steps = spec.get("steps")
        if not isinstance(steps, list) or not steps or not all(isinstance(x, list) and len(x) == 2 and isinstance(x[0], str) for x in steps):
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
    if "n_features_in_" in attrs or ALLOWED[spec["class"]].startswith("sklearn"):  # fitted sklearn estimators declare it
        w = getattr(est, "n_features_in_", None)
        if isinstance(w, bool) or not isinstance(w, int | np.integer) or not 1 <= w <= 1_000_000:
            raise ArtifactError(f"{where}: {spec['class']}: n_features_in_ must be an integer in [1, 1000000], found {w!r}")
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
        raise ArtifactError(f"{where}: {what}: stored attributes are inconsistent ({type(exc).__name__}: {exc})") from None
    if out.dtype == object or len(out) != 2:
        raise ArtifactError(f"{where}: {what}: predicts {out.shape} {out.dtype} for 2 rows")


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


def _import_q(spec: dict[str, Any], arrays: Any, where: str = "<memory>") -> QFunction:
    if not isinstance(spec, dict):
        raise ArtifactError(f"{where}: Q-function entry is not a JSON object")
    if spec.get("kind") == "time_indexed":
        qs = spec.get("qs")
        if not isinstance(qs, list) or not qs:
            raise ArtifactError(f"{where}: time_indexed Q needs a non-empty 'qs' list")
        out = TimeIndexedQ([_import_q(x, arrays, where) for x in qs])
        if len({q.n_actions for q in out.qs}) != 1:
            raise ArtifactError(f"{where}: time_indexed Q mixes action counts")
        return out
    e = spec.get("encoder")
    if not isinstance(e, dict):
        raise ArtifactError(f"{where}: Q-function entry without an 'encoder' object")
    n_actions = C.check_int(e.get("n_actions"), where, "encoder.n_actions", 1, 1_000_000)
    af = C.array(arrays, e.get("action_features"), where, kinds="biuf", ndim=2)
    if af.shape[0] != n_actions or not np.all(np.isfinite(af)):
        raise ArtifactError(f"{where}: {e.get('action_features')}: shape {af.shape} (or non-finite) for {n_actions} actions")
    per_action = e.get("per_action")
    if not isinstance(per_action, bool):
        raise ArtifactError(f"{where}: encoder.per_action must be true or false")
    fmap = None if e.get("feature_map") is None else _guard(_import_estimator(e["feature_map"], arrays, where), where, "feature_map")
    enc = QEncoder(n_actions, np.asarray(af, dtype=np.float64), per_action, fmap)
    kind = spec.get("kind")
    if kind == "boosted_sum":
        b = spec.get("boosters")
        if not isinstance(b, list) or not b or per_action:
            raise ArtifactError(f"{where}: boosted_sum Q needs a non-empty 'boosters' list and a joint encoder")
        q: QFunction = BoostedSumQ([_Booster(m, where, f"booster {i}") for i, m in enumerate(b)], enc)
        widths = [x.booster.num_feature() for x in q.boosters]  # type: ignore[attr-defined]
    elif kind == "regressor":
        models = spec.get("models")
        if not isinstance(models, list) or len(models) != (n_actions if per_action else 1):
            raise ArtifactError(f"{where}: regressor Q needs {n_actions if per_action else 1} model(s)")
        q = RegressorQ([_guard(_import_estimator(m, arrays, where), where, f"model {i}") for i, m in enumerate(models)], enc)
        widths = [_model_width(m) for m in q.models]  # type: ignore[attr-defined]
    else:
        raise ArtifactError(f"{where}: unknown Q-function kind {kind!r}")
    # the models' input width agrees with the encoder's; then one probe prediction
    k = 0 if per_action else af.shape[1]
    known = {w for w in widths if w is not None}
    if len(known) > 1:
        raise ArtifactError(f"{where}: the models read different input widths {sorted(known)}")
    d = _width(fmap) if fmap is not None else (known.pop() - k if known else None)
    if d is not None:
        if d < 1:
            raise ArtifactError(f"{where}: models read {d + k} inputs, fewer than the {k} action features")
        if 2 * n_actions * (d + k) > C.MAX_PROBE_ENTRIES:
            raise ArtifactError(f"{where}: models declare {d + k} inputs for {n_actions} actions "
                                f"({2 * n_actions * (d + k)} values per 2 states, at most {C.MAX_PROBE_ENTRIES}): "
                                "out of proportion, not a model we wrote")
        try:
            v = np.asarray(q.values(np.zeros((2, d))))
        except ArtifactError:
            raise
        except Exception as exc:
            raise ArtifactError(f"{where}: the Q-function cannot predict ({type(exc).__name__}: {exc})") from None
        if v.shape != (2, n_actions):
            raise ArtifactError(f"{where}: the Q-function predicts shape {v.shape}, expected (2, {n_actions})")
    return q


def _model_width(m: Any) -> int | None:
    m = getattr(m, "_oadp_inner", m)
    if isinstance(m, TreeEnsemble | _TreeClassifier):
        return getattr(m, "n_features_in_", None) if isinstance(m, TreeEnsemble) else None
    if isinstance(m, _Booster):
        return m.booster.num_feature()
    return _width(m)


def _write(directory: str | PathLike[str], stem: str, payload: dict[str, Any], arrays: dict[str, np.ndarray],
           extra: dict[str, Any] | None) -> None:
    """``<stem>.json`` (payload, versions, extra) + ``<stem>.npz`` (arrays) in ``directory``."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    np.savez(d / f"{stem}.npz", **arrays)
    spec = {"artifact_version": ARTIFACT_VERSION, "versions": versions(), **payload, **(extra or {})}
    (d / f"{stem}.json").write_text(json.dumps(spec, indent=1))


def _read(directory: str | PathLike[str], stem: str, key: str, build: Any, what: str) -> tuple[Any, dict[str, Any]]:
    """Read what :func:`_write` wrote (arrays without pickle, every member checked before
    use, see :mod:`offline_adp.artifact_checks`); warns on other versions."""
    d = Path(directory)
    jpath, npath = d / f"{stem}.json", d / f"{stem}.npz"
    try:
        if jpath.stat().st_size > 1 << 30:
            raise ArtifactError(f"{jpath}: {jpath.stat().st_size} bytes is too large for an artifact description")
        spec = json.loads(jpath.read_bytes().decode("utf-8"))
        C.check_npz(npath)
        arrays = np.load(npath, allow_pickle=False)
    except FileNotFoundError as exc:
        raise ArtifactError(f"{d}: no saved {what} ({exc.filename} missing)") from exc
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise ArtifactError(f"{jpath}: unreadable {what} description ({type(exc).__name__}: {exc})") from None
    except C.ZIP_ERRORS as exc:
        raise ArtifactError(f"{npath}: unreadable {what} arrays ({exc})") from None
    if not isinstance(spec, dict) or key not in spec:
        raise ArtifactError(f"{jpath}: no {key!r} entry (not a saved {what})")
    vs = spec.get("versions", {})
    now = versions()
    diff = {k: (v, now.get(k)) for k, v in vs.items() if now.get(k) != v} if isinstance(vs, dict) else {}
    if diff:
        warnings.warn(f"{d}: written with other versions {diff} (saved, current)", FormatVersionWarning, stacklevel=3)
    where = f"{jpath.parent / stem}.{{json,npz}}"
    with arrays:
        try:
            return build(spec[key], arrays, where), spec
        except (ArtifactError, FormatVersionWarning):
            raise
        except (*C.ZIP_ERRORS, IndexError, AttributeError, RecursionError, MemoryError) as exc:
            raise ArtifactError(f"{where}: malformed {what} ({type(exc).__name__}: {exc})") from None


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
# Each policy kind registers how it is written and read: ``kind`` in policy.json names the
# reader; the writer is found by the policy's class (its MRO), never by an isinstance chain.
_POLICY_WRITERS: dict[type, tuple[str, Any]] = {}
_POLICY_READERS: dict[str, Any] = {}


def register_policy_kind(kind: str, cls: type, write: Any, read: Any) -> None:
    """Make policies of class ``cls`` savable as ``kind``: ``write(pi, arrays, key) ->
    dict`` (JSON fields besides ``kind``) and ``read(spec, arrays, where) -> policy``
    (checking every field before use; ``ArtifactError`` naming ``where``)."""
    _POLICY_WRITERS[cls] = (kind, write)
    _POLICY_READERS[kind] = read


def _export_policy(pi: Any, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
    _register_policies()
    for cls in type(pi).__mro__:
        if cls in _POLICY_WRITERS:
            kind, write = _POLICY_WRITERS[cls]
            return {"kind": kind, **write(pi, arrays, key)}
    raise ArtifactError(f"cannot save a {type(pi).__name__} policy safely")


def _import_policy(spec: dict[str, Any], arrays: Any, where: str = "<memory>") -> Any:
    _register_policies()
    if not isinstance(spec, dict):
        raise ArtifactError(f"{where}: policy entry is not a JSON object")
    read = _POLICY_READERS.get(spec.get("kind"))  # type: ignore[arg-type]
    if read is None:
        raise ArtifactError(f"{where}: unknown policy kind {spec.get('kind')!r}; known: {sorted(_POLICY_READERS)}")
    return read(spec, arrays, where)


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
    if not isinstance(w, list) or len(w) != len(pols) or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in w):
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
    clf = None if spec.get("classifier") is None else _guard(_import_estimator(spec["classifier"], arrays, where), where, "classifier")
    if clf is None and constant is None:
        raise ArtifactError(f"{where}: classifier policy with neither a classifier nor a constant action")
    classes = getattr(clf, "classes_", None)
    if classes is not None:
        c = np.asarray(classes)
        if c.dtype.kind not in "iu" or (len(c) and (c.min() < 0 or c.max() >= n_actions)):
            raise ArtifactError(f"{where}: classifier classes {c[:10].tolist()} are not action indices in [0, {n_actions})")
    fmap = None if spec.get("feature_map") is None else _guard(_import_estimator(spec["feature_map"], arrays, where), where, "feature_map")
    return ClassifierPolicy(clf, n_actions, constant, fmap)


def _register_policies() -> None:
    """Register the package's policy kinds (once; policies import lazily to keep this module light)."""
    if _POLICY_READERS:
        return
    from offline_adp.policies import (
        ClassifierPolicy,
        GreedyPolicy,
        MixturePolicy,
        NonStationaryPolicy,
        TabularPolicy,
        UniformPolicy,
    )

    register_policy_kind("greedy", GreedyPolicy, lambda pi, arrays, key: {"q": _export_q(pi.q, arrays, f"{key}.q")},
                         lambda spec, arrays, where: GreedyPolicy(_import_q(spec.get("q"), arrays, where)))  # type: ignore[arg-type]
    register_policy_kind("uniform", UniformPolicy, lambda pi, arrays, key: {"n_actions": pi.n_actions},
                         lambda spec, arrays, where: UniformPolicy(C.check_int(spec.get("n_actions"), where, "n_actions", 1,
                                                                               1_000_000)))
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


def save_policy(policy: Any, directory: str | PathLike[str], extra: dict[str, Any] | None = None) -> None:
    """Write a policy (greedy, uniform, tabular, mixture, non-stationary, classifier) as
    ``policy.json`` + ``policy.npz``."""
    arrays: dict[str, np.ndarray] = {}
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
        from offline_adp.policies import GreedyPolicy

        return GreedyPolicy(load_q(d)[0])
    return _read(d, "policy", "policy", _import_policy, "policy")[0]

