"""Q-functions in artifacts: each kind's writer and checked reader (time-indexed, boosted
sums, regressors over an encoder, continuous-command candidates), :func:`save_q` and
:func:`load_q` (see :mod:`offline_adp.artifacts`)."""

from __future__ import annotations

from os import PathLike
from typing import Any

import numpy as np

from offline_adp.artifacts import checks as C
from offline_adp.artifacts.estimators import (
    Arrays,
    _Booster,
    _export_estimator,
    _guard,
    _import_estimator,
    _width,
)
from offline_adp.artifacts.kinds import _Kinds
from offline_adp.artifacts.storage import _read, _write
from offline_adp.errors import ArtifactError
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


#: The largest scaled logged state a neighbour search reads: squared distances over the
#: features of larger ones overflow (scipy raises a bare ValueError), and the logged states
#: scaled by their own spread are a few units (an outlier among a billion rows: thousands).
_MAX_SCALED_POINT = 1e100


def _read_candidates(e: dict[str, Any], arrays: Any, where: str, n_actions: int, n_dims: int) -> NeighbourCommands:
    """A :class:`NeighbourCommands` from an encoder entry, every array checked (shapes agree,
    finite, positive scales, ``k`` <= the logged states, ``k`` plus the extra commands = the
    encoder's candidate slots)."""
    c = e.get("candidates")
    if not isinstance(c, dict) or c.get("kind") != "neighbour_commands":
        raise ArtifactError(f"{where}: encoder.candidates must be a neighbour_commands entry")
    got = {name: np.asarray(C.array(arrays, c.get(name), where, kinds="f",
                                    ndim=2 if name in ("points", "commands") else 1),
                            dtype=np.float64) for name in ("points", "commands", "center", "scale")}
    pts, cmd, center, scale = got["points"], got["commands"], got["center"], got["scale"]
    k = C.check_int(c.get("k"), where, "encoder.candidates.k", 1, 4096)
    extra = None
    if c.get("extra") is not None:
        extra = np.asarray(C.array(arrays, c.get("extra"), where, kinds="f", ndim=2), dtype=np.float64)
        got["extra"] = extra
        if extra.shape[1] != n_dims or len(extra) == 0:
            raise ArtifactError(f"{where}: encoder.candidates.extra has shape {extra.shape}, expected (e >= "
                                f"1, {n_dims})")
    slots = k + (0 if extra is None else len(extra))
    if (len(pts) != len(cmd) or len(pts) < k or slots != n_actions or cmd.shape[1] != n_dims
            or center.shape != (pts.shape[1],) or scale.shape != center.shape):
        raise ArtifactError(f"{where}: encoder.candidates: shapes points {pts.shape}, commands {cmd.shape}, center "
                            f"{center.shape}, scale {scale.shape} with k={k} do not agree with {n_actions} slots of "
                            f"{n_dims}-component commands")
    if not all(np.isfinite(v).all() for v in got.values()) or not (scale > 0).all():
        raise ArtifactError(f"{where}: encoder.candidates: non-finite values or a scale <= 0")
    if len(pts) and np.abs(pts).max() > _MAX_SCALED_POINT:  # the neighbour search squares them
        raise ArtifactError(f"{where}: encoder.candidates.points: a scaled logged state of magnitude "
                            f"{np.abs(pts).max():.3g} (at most {_MAX_SCALED_POINT:.0e}: they are (phi - center) / "
                            "scale, a few units for data we wrote)")
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
        q = RegressorQ([_guard(_import_estimator(m, arrays, where), where, f"model {i}") for i, m in enumerate(models)],
                       enc)
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
        raise ArtifactError(f"{where}: {e.get('action_features')}: shape {af.shape} (or non-finite) for "
                            f"{n_actions} actions")
    per_action = e.get("per_action")
    if not isinstance(per_action, bool):
        raise ArtifactError(f"{where}: encoder.per_action must be true or false")
    fmap = None if e.get("feature_map") is None else _guard(_import_estimator(e["feature_map"], arrays, where), where,
                                                            "feature_map")
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



def save_q(q: QFunction, directory: str | PathLike[str], extra: dict[str, Any] | None = None, *,
           compress: bool = True) -> None:
    """Write ``q`` into ``directory`` (``q.json`` + ``q.npz``; ``compress=False``: the
    arrays stored uncompressed, e.g. a checkpoint's)."""
    arrays = Arrays()
    _write(directory, "q", {"q": _export_q(q, arrays, "q")}, arrays, extra, compress)


def load_q(directory: str | PathLike[str]) -> tuple[QFunction, dict[str, Any]]:
    """Read a Q-function written by :func:`save_q`; returns it and the JSON metadata.

    Warns (``FormatVersionWarning``) when the package or library versions differ.
    """
    return _read(directory, "q", "q", _import_q, "Q-function")
