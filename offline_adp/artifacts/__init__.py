"""Saving and loading fitted Q-functions without executing code from the files.

Everything is JSON, ``.npz`` arrays (loaded with ``allow_pickle=False``) or LightGBM's
text model format. scikit-learn forests are exported to :class:`TreeEnsemble` arrays;
other scikit-learn estimators go through an explicit allow-list: their constructor
parameters (JSON) and fitted array attributes are stored, and loading rebuilds the
estimator from the allow-listed class and sets those attributes. Anything else raises
:class:`ArtifactError` naming the type, rather than falling back to pickle. The estimators'
part is :mod:`offline_adp.artifacts.estimators`; Q-functions and policies are saved here,
each kind through a registry (:func:`register_q_kind`, :func:`register_policy_kind`).
"""

from __future__ import annotations

import json
import warnings
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp._version import __version__
from offline_adp.artifacts import checks as C
from offline_adp.artifacts.estimators import (
    ALLOWED,
    Arrays,
    _Booster,
    _export_estimator,
    _guard,
    _import_estimator,
    _width,
)
from offline_adp.errors import ArtifactError, FormatVersionWarning
from offline_adp.qfunctions import (
    BoostedSumQ,
    CommandEncoder,
    NeighbourCommands,
    QEncoder,
    QFunction,
    RegressorQ,
    TimeIndexedQ,
    TreeQ,
)

__all__ = ["ALLOWED", "ARTIFACT_VERSION", "load_index_policy", "load_q", "register_policy_kind", "register_q_kind",
           "save_policy", "save_q", "versions"]

#: The artifact format written: "2" stores tree ensembles in the compact layout
#: (:meth:`~offline_adp.trees.ensemble.TreeEnsemble.to_arrays`) in a compressed ``.npz``;
#: "1" (per-node arrays) is still read.
ARTIFACT_VERSION = "2"
#: The artifact formats this version reads.
READABLE_VERSIONS = ("1", "2")


def versions() -> dict[str, str]:
    """Versions of the package and the libraries whose models we store."""
    import lightgbm
    import sklearn

    return {"offline_adp": __version__, "numpy": np.__version__, "scikit-learn": sklearn.__version__, "lightgbm": lightgbm.__version__}


# ----------------------------------------------------------------------------- kinds
class _Kinds:
    """A registry of savable kinds (Q-functions, policies): ``kind`` in the JSON names the
    reader; the writer is found by the object's class (its MRO), never by an isinstance chain."""

    def __init__(self, what: str, load: Any = None) -> None:
        self.what, self.load = what, load  # load(): registers the package's kinds on first use
        self.writers: dict[type, tuple[str, Any]] = {}
        self.readers: dict[str, Any] = {}

    def register(self, kind: str, cls: type, write: Any, read: Any) -> None:
        """Make objects of class ``cls`` savable as ``kind``: ``write(obj, arrays, key) ->
        dict`` (JSON fields besides ``kind``) and ``read(spec, arrays, where) -> object``
        (checking every field before use; ``ArtifactError`` naming ``where``)."""
        self.writers[cls] = (kind, write)
        self.readers[kind] = read

    def _ready(self) -> None:
        if self.load is not None and not self.readers:
            self.load()

    def export(self, obj: Any, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
        self._ready()
        for cls in type(obj).__mro__:
            if cls in self.writers:
                kind, write = self.writers[cls]
                return {"kind": kind, **write(obj, arrays, key)}
        raise ArtifactError(f"cannot save a {type(obj).__name__} {self.what} safely")

    def read(self, spec: Any, arrays: Any, where: str = "<memory>") -> Any:
        self._ready()
        if not isinstance(spec, dict):
            raise ArtifactError(f"{where}: {self.what} entry is not a JSON object")
        read = self.readers.get(spec.get("kind"))  # type: ignore[arg-type]
        if read is None:
            raise ArtifactError(f"{where}: unknown {self.what} kind {spec.get('kind')!r}; known: {sorted(self.readers)}")
        return read(spec, arrays, where)


# ----------------------------------------------------------------------------- Q-functions
_Q_KINDS = _Kinds("Q-function")


#: ``register_q_kind(kind, cls, write, read)``: see :meth:`_Kinds.register`
register_q_kind = _Q_KINDS.register
_export_q, _import_q = _Q_KINDS.export, _Q_KINDS.read


def _write_time_indexed(q: Any, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
    return {"qs": [_export_q(x, arrays, f"{key}.t{t}") for t, x in enumerate(q.qs)]}


def _read_time_indexed(spec: dict[str, Any], arrays: Any, where: str) -> QFunction:
    qs = spec.get("qs")
    if not isinstance(qs, list) or not qs:
        raise ArtifactError(f"{where}: time_indexed Q needs a non-empty 'qs' list")
    out = TimeIndexedQ([_import_q(x, arrays, where) for x in qs])
    if len({q.n_actions for q in out.qs}) != 1:
        raise ArtifactError(f"{where}: time_indexed Q mixes action counts")
    cands = [getattr(getattr(q, "encoder", None), "candidates", None) for q in out.qs]
    if any(c is not None for c in cands):  # over commands: the greedy policy reads step 0's candidates for every step
        first = cands[0]
        same = all(isinstance(c, NeighbourCommands) and isinstance(first, NeighbourCommands) and c.k == first.k
                   and _same_extra(c.extra, first.extra)
                   and all(np.array_equal(getattr(c, n), getattr(first, n)) for n in ("points", "commands", "center",
                                                                                       "scale")) for c in cands)
        if not same:
            raise ArtifactError(f"{where}: time_indexed Q over commands: its steps read different candidate sets")
    return out


def _write_encoder(q: Any, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
    enc = q.encoder
    arrays[f"{key}.action_features"] = enc.action_features
    out = {
        "n_actions": enc.n_actions,
        "per_action": enc.per_action,
        "action_features": f"{key}.action_features",
        "feature_map": None if enc.feature_map is None else _export_estimator(enc.feature_map, arrays, f"{key}.phi"),
    }
    if isinstance(enc, CommandEncoder):  # continuous commands: the candidate set's logged states and commands
        c = enc.candidates
        assert c is not None
        names = ("points", "commands", "center", "scale") + (() if c.extra is None else ("extra",))
        for name in names:
            arrays[f"{key}.candidates.{name}"] = getattr(c, name)
        out["candidates"] = {"kind": "neighbour_commands", "k": c.k,
                             **{name: f"{key}.candidates.{name}" for name in names}}
    return out


def _same_extra(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b))


def _read_candidates(e: dict[str, Any], arrays: Any, where: str, n_actions: int, n_dims: int) -> NeighbourCommands:
    """A :class:`NeighbourCommands` from an encoder entry, every array checked (shapes agree,
    finite, positive scales, ``k`` <= the logged states, ``k`` plus the extra commands = the
    encoder's candidate slots)."""
    c = e.get("candidates")
    if not isinstance(c, dict) or c.get("kind") != "neighbour_commands":
        raise ArtifactError(f"{where}: encoder.candidates must be a neighbour_commands entry")
    got = {name: np.asarray(C.array(arrays, c.get(name), where, kinds="f", ndim=2 if name in ("points", "commands") else 1),
                            dtype=np.float64) for name in ("points", "commands", "center", "scale")}
    pts, cmd, center, scale = got["points"], got["commands"], got["center"], got["scale"]
    k = C.check_int(c.get("k"), where, "encoder.candidates.k", 1, 4096)
    extra = None
    if c.get("extra") is not None:
        extra = np.asarray(C.array(arrays, c.get("extra"), where, kinds="f", ndim=2), dtype=np.float64)
        got["extra"] = extra
        if extra.shape[1] != n_dims or len(extra) == 0:
            raise ArtifactError(f"{where}: encoder.candidates.extra has shape {extra.shape}, expected (e >= 1, {n_dims})")
    slots = k + (0 if extra is None else len(extra))
    if (len(pts) != len(cmd) or len(pts) < k or slots != n_actions or cmd.shape[1] != n_dims
            or center.shape != (pts.shape[1],) or scale.shape != center.shape):
        raise ArtifactError(f"{where}: encoder.candidates: shapes points {pts.shape}, commands {cmd.shape}, center "
                            f"{center.shape}, scale {scale.shape} with k={k} do not agree with {n_actions} slots of "
                            f"{n_dims}-component commands")
    if not all(np.isfinite(v).all() for v in got.values()) or not (scale > 0).all():
        raise ArtifactError(f"{where}: encoder.candidates: non-finite values or a scale <= 0")
    return NeighbourCommands(pts, cmd, center, scale, k, extra=extra)


def _write_boosted_sum(q: Any, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
    return {"encoder": _write_encoder(q, arrays, key), "boosters": [
        b.model_to_string() if hasattr(b, "model_to_string") else b.booster.model_to_string() for b in q.boosters]}


def _write_regressor(q: Any, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
    e = _write_encoder(q, arrays, key)
    return {"encoder": e, "models": [_export_estimator(m, arrays, f"{key}.m{i}") for i, m in enumerate(q.models)]}


def _read_boosted_sum(spec: dict[str, Any], arrays: Any, where: str) -> QFunction:
    def build(enc: QEncoder) -> tuple[QFunction, list[int | None]]:
        b = spec.get("boosters")
        if not isinstance(b, list) or not b or enc.per_action:
            raise ArtifactError(f"{where}: boosted_sum Q needs a non-empty 'boosters' list and a joint encoder")
        q = BoostedSumQ([_Booster(m, where, f"booster {i}") for i, m in enumerate(b)], enc)
        return q, [x.booster.num_feature() for x in q.boosters]

    return _read_encoded(spec, arrays, where, build)


def _read_regressor(spec: dict[str, Any], arrays: Any, where: str) -> QFunction:
    def build(enc: QEncoder) -> tuple[QFunction, list[int | None]]:
        models = spec.get("models")
        n = enc.n_actions if enc.per_action else 1
        if not isinstance(models, list) or len(models) != n:
            raise ArtifactError(f"{where}: regressor Q needs {n} model(s)")
        q = RegressorQ([_guard(_import_estimator(m, arrays, where), where, f"model {i}") for i, m in enumerate(models)], enc)
        return q, [_model_width(m) for m in q.models]

    return _read_encoded(spec, arrays, where, build)


def _read_encoded(spec: dict[str, Any], arrays: Any, where: str, build: Any) -> QFunction:
    """A Q-function over an encoder (``spec["encoder"]``): the encoder checked and built,
    ``build(encoder) -> (q, model input widths)``, then the widths checked against the
    encoder's and one probe prediction."""
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
    if e.get("candidates") is None:
        enc = QEncoder(n_actions, np.asarray(af, dtype=np.float64), per_action, fmap)
    else:
        if per_action:
            raise ArtifactError(f"{where}: an encoder over continuous commands cannot be per action")
        enc = CommandEncoder(n_actions, np.asarray(af, dtype=np.float64), False, fmap,
                             candidates=_read_candidates(e, arrays, where, n_actions, af.shape[1]))
    q, widths = build(enc)
    if isinstance(enc, CommandEncoder) and isinstance(enc.candidates, NeighbourCommands):
        w = enc.candidates.points.shape[1]
        known_w = {x for x in widths if x is not None}
        if fmap is None and known_w and known_w != {w + af.shape[1]}:
            raise ArtifactError(f"{where}: encoder.candidates: logged states of {w} features, models reading "
                                f"{sorted(known_w)} inputs with {af.shape[1]} command components")
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
        _probe(where, "the Q-function", lambda: q.values(np.zeros((2, d))), (2, n_actions))
    return q


def _probe(where: str, what: str, predict: Any, shape: tuple[int, ...]) -> None:
    """One probe prediction of a loaded model: any failure, or an output of another shape
    than ``shape``, is an :class:`ArtifactError` naming ``where`` and ``what``."""
    try:
        v = np.asarray(predict())
    except ArtifactError:
        raise
    except Exception as exc:
        raise ArtifactError(f"{where}: {what} cannot predict ({type(exc).__name__}: {exc})") from None
    if v.shape != shape:
        raise ArtifactError(f"{where}: {what} predicts shape {v.shape}, expected {shape}")


register_q_kind("time_indexed", TimeIndexedQ, _write_time_indexed, _read_time_indexed)
register_q_kind("boosted_sum", BoostedSumQ, _write_boosted_sum, _read_boosted_sum)
register_q_kind("regressor", RegressorQ, _write_regressor, _read_regressor)
register_q_kind("regressor", TreeQ, _write_regressor, _read_regressor)  # read back as a RegressorQ over a TreeEnsemble


def _model_width(m: Any) -> int | None:
    """The input width of a loaded model: its own ``input_width()`` (boosters, forest
    classifiers), else the ``n_features_in_`` it declares."""
    m = getattr(m, "_oadp_inner", m)
    width = getattr(m, "input_width", None)
    return width() if width is not None else _width(m)


def _write(directory: str | PathLike[str], stem: str, payload: dict[str, Any], arrays: dict[str, np.ndarray],
           extra: dict[str, Any] | None) -> None:
    """``<stem>.json`` (payload, versions, extra) + ``<stem>.npz`` (arrays) in ``directory``."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(d / f"{stem}.npz", **arrays)
    spec = {"artifact_version": ARTIFACT_VERSION, "versions": versions(), **payload, **(extra or {})}
    (d / f"{stem}.json").write_text(json.dumps(spec, indent=1))


#: The files of a model directory whose sha256 a run records (``run.json`` ``model_sha256``).
HASHED = ("q.json", "q.npz", "policy.json", "policy.npz")


def model_hashes(model_dir: str | PathLike[str]) -> dict[str, str]:
    """sha256 of each artifact file in ``model_dir`` (those of :data:`HASHED` present), for
    ``run.json``: loading checks them (:func:`check_recorded_hashes`)."""
    from offline_adp.data.files import sha256_file

    d = Path(model_dir)
    return {n: sha256_file(d / n) for n in HASHED if (d / n).is_file()}


def check_recorded_hashes(model_dir: Path, files: tuple[Path, ...]) -> None:
    """When the run holding ``model_dir`` recorded its model's hashes (``run.json``
    ``model_sha256``), each of ``files`` must still have the recorded sha256: a model file
    changed after its fit (a flipped byte in a leaf table) is refused, naming the file."""
    run_json = model_dir.parent / "run.json"
    if model_dir.name != "model" or not run_json.is_file():
        return
    from offline_adp.data.files import read_json_file, sha256_file

    recorded = read_json_file(run_json).get("model_sha256")
    if not isinstance(recorded, dict):
        return  # a run written before hashes were recorded
    extra = [n for n in HASHED if (model_dir / n).exists() and n not in recorded]
    if extra:  # e.g. a policy.json dropped next to a fitted Q: loading would prefer it
        raise ArtifactError(f"{model_dir / extra[0]}: not among the model files {run_json} recorded when the fit wrote "
                            "them (the model directory was changed after the fit); remove it or fit again")
    for f in files:
        want = recorded.get(f.name)
        if isinstance(want, str) and (not f.is_file() or sha256_file(f) != want):
            raise ArtifactError(f"{f}: its sha256 differs from the one {run_json} recorded when the fit wrote it (or "
                                "it is missing): the file was changed after the fit; restore it or fit again")


def _read(directory: str | PathLike[str], stem: str, key: str, build: Any, what: str) -> tuple[Any, dict[str, Any]]:
    """Read what :func:`_write` wrote (arrays without pickle, every member checked before
    use, see :mod:`offline_adp.artifacts.checks`); warns on other versions."""
    d = Path(directory)
    jpath, npath = d / f"{stem}.json", d / f"{stem}.npz"
    check_recorded_hashes(d, (jpath, npath))
    try:
        if jpath.stat().st_size > 1 << 30:
            raise ArtifactError(f"{jpath}: {jpath.stat().st_size} bytes is too large for an artifact description")
        spec = json.loads(jpath.read_bytes().decode("utf-8"))
        C.check_node_budget(C.check_npz(npath), npath.stat().st_size, str(npath))
        arrays = np.load(npath, allow_pickle=False)
    except FileNotFoundError as exc:
        raise ArtifactError(f"{d}: no saved {what} ({exc.filename} missing)") from exc
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise ArtifactError(f"{jpath}: unreadable {what} description ({type(exc).__name__}: {exc})") from None
    except C.ZIP_ERRORS as exc:
        raise ArtifactError(f"{npath}: unreadable {what} arrays ({exc})") from None
    if not isinstance(spec, dict) or key not in spec:
        raise ArtifactError(f"{jpath}: no {key!r} entry (not a saved {what})")
    fmt = spec.get("artifact_version", "1")
    if fmt not in READABLE_VERSIONS:
        raise ArtifactError(f"{jpath}: artifact format {fmt!r}, this offline_adp {__version__} reads formats "
                            f"{', '.join(READABLE_VERSIONS)}: written by a newer version? (upgrade offline_adp to read it)")
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
    arrays = Arrays()
    _write(directory, "q", {"q": _export_q(q, arrays, "q")}, arrays, extra)


def load_q(directory: str | PathLike[str]) -> tuple[QFunction, dict[str, Any]]:
    """Read a Q-function written by :func:`save_q`; returns it and the JSON metadata.

    Warns (``FormatVersionWarning``) when the package or library versions differ.
    """
    return _read(directory, "q", "q", _import_q, "Q-function")


# ----------------------------------------------------------------------------- policies
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
    low, high = (np.asarray(C.array(arrays, spec.get(k), where, kinds="f", ndim=1), np.float64) for k in ("low", "high"))
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

