"""Policy export to ONNX: a graph from the named observation vector to the action.

The exported model has

- input ``observation``: double ``(N, d)``, columns in the order of the policy's
  feature names (named with their units in the input's ``doc_string``, as ``name [unit]``
  in column order, and in the model metadata), and for
  time-indexed policies ``t``: int64 ``(N,)`` (steps ``>= T`` use the last step's rule);
- outputs ``action`` (double ``(N, k)``, the action table's value vector), ``action_index``
  (int64 ``(N,)``) and, for greedy policies, ``q_values`` (double ``(N, n_actions)``,
  costs: the policy picks the lowest, ties to the lowest index). Rows ``act`` refuses (a
  NaN or infinite value, ``t < 0``) get index -1 and NaN values or commands.

A continuous policy (:class:`~offline_adp.policies.GreedyCommandPolicy`, exactly: the
nearest logged states' commands and the first minimum of Q over them; or
:class:`~offline_adp.distill.DistilledCommandPolicy`) has one output instead, ``command`` (double ``(N, m)``, within
the bounds), and metadata ``command_low``, ``command_high``, ``max_rate`` (the graph is stateless: the caller applies
the rate limit), ``outputs``; see docs/deploy.md.

Metadata (``model.metadata_props``): ``feature_names``, ``feature_units``,
``action_names``, ``action_dims``, ``action_units``, ``action_values`` (JSON),
``policy_kind``, ``time_indexed``, ``n_steps``, ``offline_adp_version``.

What can be expressed: greedy policies over Q-functions made of scikit-learn forests
(extra trees, random forests, also as saved :class:`~offline_adp.trees.ensemble.TreeEnsemble`
arrays) or LightGBM boosters (including the warm-start sum of boosters), with joint
(``[phi(x), action features]``) or per-action encodings and a column-selection feature
map; time-indexed Q-functions (finite-horizon FQI, FQE) and PSDP's time-indexed
policies (one rule per step); PSDP's forest classifiers. Stochastic policies (CPI
mixtures, uniform, epsilon-greedy) and lookup tables are refused with
:class:`ExportError`: a deployed controller should be deterministic, export the
mixture's components instead.

Numerics: trees are written with the ONNX-ML ``TreeEnsembleRegressor`` operator with
double-precision thresholds and leaf values (``nodes_values_as_tensor``). scikit-learn
compares float32-rounded inputs with its double thresholds; the graph does the same
(a float32 round trip of the regressor input) so splits agree exactly. LightGBM
compares doubles, as does the graph. The remaining difference is the summation order
of leaf values (about 1e-16 relative), which can flip the argmin between two actions
whose Q-values tie to that precision.
"""

from __future__ import annotations

import json
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.data.files import atomic_file
from offline_adp.errors import ExportError  # re-exported: offline_adp.onnx_export.ExportError
from offline_adp.onnx_trees import (
    _booster_of,
    _ensemble_arrays,
    _ensemble_of,
    _float32_roundtrip,
    _forest_classifier,
    _Graph,
    _lightgbm_arrays,
    _regressor,
    _tree_node,
    action_outputs,
    valid_rows,
)
from offline_adp.progress import get_logger

log = get_logger(__name__)

OPSET = 17
ML_OPSET = 5


# ----------------------------------------------------------------------------- Q and policies
def _phi(g: _Graph, fmap: Any, X: str) -> str:
    if fmap is None:
        return X
    from offline_adp.features import SelectColumns

    fmap = getattr(fmap, "_oadp_inner", fmap)  # a loaded map is wrapped in the loader's guard
    if isinstance(fmap, SelectColumns):
        return g.op("Gather", [X, g.const(np.asarray(list(fmap.columns), np.int64), "columns")], "phi", axis=1)
    raise ExportError(f"cannot export the feature map {type(fmap).__name__} to ONNX; supported: SelectColumns "
                      "(drop_features)")


# Each exportable class registers its graph builder; a part is found by its class's MRO,
# never by an isinstance chain (the classes import lazily, see _register).
#: Q-function class -> ``build(g, q, phi) -> (N, n_actions) Q-values``.
_Q_EXPORTERS: dict[type, Any] = {}
#: Policy class -> ``build(g, pi, X) -> (action index (N,), Q-values or None)``.
_RULE_EXPORTERS: dict[type, Any] = {}
#: Policy class -> ``steps(pi) -> its per-step rules, or None when it is stationary``.
_STEP_RULES: dict[type, Any] = {}
#: Continuous policy class -> ``build(g, pi, X) -> (command (N, m), low (m,), high (m,))``.
_COMMAND_EXPORTERS: dict[type, Any] = {}


def _lookup(table: dict[type, Any], obj: Any) -> Any | None:
    _register()
    return next((table[c] for c in type(obj).__mro__ if c in table), None)


def _q_values(g: _Graph, q: Any, X: str) -> str:
    """Q-values (N, n_actions) of a stationary Q-function."""
    build = _lookup(_Q_EXPORTERS, q)
    if build is None:
        raise ExportError(f"cannot export a {type(q).__name__} Q-function to ONNX")
    return build(g, q, _phi(g, q.encoder.feature_map, X))


def _action_major(g: _Graph, flat: str, n_actions: int) -> str:
    """Action-major rows (a * N + i) -> (N, A)."""
    return g.op("Transpose", [g.op("Reshape", [flat, g.const(np.array([n_actions, -1], np.int64))])], "q", perm=[1, 0])


def _boosted_sum_q(g: _Graph, q: Any, phi: str) -> str:
    enc = q.encoder
    boosters = [_booster_of(b) for b in q.boosters]
    if any(b is None for b in boosters):
        raise ExportError("cannot export a BoostedSumQ whose boosters are not LightGBM models")
    pairs = _all_pairs(g, phi, enc.action_features)
    return _action_major(g, _tree_node(g, pairs, _lightgbm_arrays(boosters), "SUM"), enc.n_actions)


def _regressor_q(g: _Graph, q: Any, phi: str) -> str:
    enc = q.encoder
    if enc.per_action:
        return g.op("Concat", [_regressor(g, m, phi) for m in q.models], "q", axis=1)
    return _action_major(g, _regressor(g, q.models[0], _all_pairs(g, phi, enc.action_features)), enc.n_actions)


def _all_pairs(g: _Graph, phi: str, action_features: np.ndarray) -> str:
    """Joint inputs for every action, action-major: row ``a * N + i`` is ``[phi(x_i), f(a)]``."""
    af = np.asarray(action_features, dtype=np.float64)
    A, k = af.shape
    key = ("pairs", phi, af.shape, af.tobytes())
    if key in g.memo:  # every step of a time-indexed Q reads the same pairs: built once
        return g.memo[key]
    n = g.op("Slice", [g.op("Shape", [phi]), g.const(np.array([0], np.int64)), g.const(np.array([1], np.int64))], "n")
    tiled = g.op("Tile", [phi, g.const(np.array([A, 1], np.int64))], "tiled")
    shape = g.op("Concat", [g.const(np.array([A], np.int64)), n, g.const(np.array([k], np.int64))], "shape", axis=0)
    acts = g.op("Expand", [g.const(af.reshape(A, 1, k), "action_features"), shape], "acts")
    acts = g.op("Reshape", [acts, g.const(np.array([-1, k], np.int64))], "acts2")
    g.memo[key] = g.op("Concat", [tiled, acts], "pairs", axis=1)
    return g.memo[key]


def _policy(g: _Graph, pi: Any, X: str) -> tuple[str, str | None]:
    """(action index (N,) int64, Q-values (N, A) or None) of a stationary rule."""
    build = _lookup(_RULE_EXPORTERS, pi)
    if build is None:
        raise ExportError(_refusal(pi))
    return build(g, pi, X)


def _greedy_rule(g: _Graph, pi: Any, X: str) -> tuple[str, str | None]:
    q = _q_values(g, pi.q, X)
    return g.op("ArgMin", [q], "index", axis=1, keepdims=0, select_last_index=0), q


def _refusal(pi: Any) -> str:
    kind = type(pi).__name__
    if kind == "GreedyCommandPolicy" and getattr(pi, "time_varying", False):
        return ("this GreedyCommandPolicy is time-indexed (a finite-horizon fit: one Q per step), which neither ONNX "
                "export nor distillation supports; fit a stationary policy (a discount gamma < 1, no horizon) to "
                "deploy it")
    if kind == "GreedyCommandPolicy":
        return ("this GreedyCommandPolicy cannot be exported to ONNX (its Q is not a tree ensemble); distill it "
                "(`offline-adp distill RUN --out RUN_DISTILLED`) and export the distilled policy")
    if kind in ("MixturePolicy", "UniformPolicy", "EpsilonPolicy", "StochasticFunctionPolicy"):
        return (f"a {kind} is stochastic (it draws its action at random) and is not exported to ONNX; export a "
                "deterministic policy (for a CPI mixture: one of its components, policy.components[k])")
    return (f"cannot export a {kind} to ONNX; supported: greedy policies over tree-ensemble/LightGBM Q-functions "
            "(FQI, FQE, API), PSDP's time-indexed policies (forest classifiers or greedy regression)")


def _classifier_policy(g: _Graph, pi: Any, X: str) -> str:
    from onnx import TensorProto


    one = g.op("Slice", [g.op("Shape", [X]), g.const(np.array([0], np.int64)), g.const(np.array([1], np.int64))], "n")
    if pi.constant is not None:
        return g.op("Expand", [g.const(np.array(pi.constant, np.int64)), one], "index")
    clf = pi.classifier
    forest = _forest_classifier(clf)
    if forest is None:
        raise ExportError(f"cannot export a {type(clf).__name__} classifier to ONNX; supported: scikit-learn forest "
                          "classifiers (PSDP's classifier='extra_trees')")
    ens, cv, classes = forest
    phi = _float32_roundtrip(g, _phi(g, pi.feature_map, X))
    proba = g.op("Concat", [_tree_node(g, phi, _ensemble_arrays(ens, cv[:, c]), "AVERAGE") for c in range(cv.shape[1])],
                 "proba", axis=1)
    k = g.op("ArgMax", [proba], "class", axis=1, keepdims=0, select_last_index=0)
    idx = g.op("Gather", [g.const(classes.astype(np.int64), "classes"), k], "index", axis=0)
    return g.op("Cast", [idx], "index64", to=TensorProto.INT64)


def _steps(pi: Any) -> list[Any] | None:
    """The per-step rules of a time-indexed policy, or None if stationary."""
    steps = _lookup(_STEP_RULES, pi)
    return None if steps is None else steps(pi)


def _greedy_steps(pi: Any) -> list[Any] | None:
    """A greedy policy over a time-indexed Q: one greedy rule per step's Q."""
    from offline_adp.policies import GreedyPolicy
    from offline_adp.qfunctions import TimeIndexedQ

    return [GreedyPolicy(q) for q in pi.q.qs] if isinstance(pi.q, TimeIndexedQ) else None


def _register() -> None:
    """Register the package's exportable classes (once; imported lazily to keep this module light)."""
    if _Q_EXPORTERS:
        return
    from offline_adp.policies import ClassifierPolicy, GreedyPolicy, NonStationaryPolicy
    from offline_adp.qfunctions import BoostedSumQ, RegressorQ, TreeQ

    _Q_EXPORTERS.update({RegressorQ: _regressor_q, TreeQ: _regressor_q, BoostedSumQ: _boosted_sum_q})
    _RULE_EXPORTERS.update({GreedyPolicy: _greedy_rule,
                            ClassifierPolicy: lambda g, pi, X: (_classifier_policy(g, pi, X), None)})
    _STEP_RULES.update({NonStationaryPolicy: lambda pi: list(pi.steps), GreedyPolicy: _greedy_steps})
    from offline_adp.distill import DistilledCommandPolicy
    from offline_adp.policies import GreedyCommandPolicy

    _COMMAND_EXPORTERS.update({DistilledCommandPolicy: _distilled_commands, GreedyCommandPolicy: _greedy_commands})


# ----------------------------------------------------------------------------- public API
INPUT_DTYPES = ("float64", "float32")


def policy_to_onnx(policy: Any, signature: Any = None, name: str = "offline_adp_policy", *,
                   input_dtype: str = "float64") -> Any:
    """The ONNX model (``onnx.ModelProto``) of a deterministic policy; see the module docstring.

    Parameters
    ----------
    policy : Policy
    signature : PolicySignature, optional
        Feature names/units and action table (default: ``policy.signature``).
    name : str
        Graph name.
    input_dtype : {"float64", "float32"}
        Element type of the ``observation`` input. ``float32`` (what robot stacks
        usually publish) is cast to double inside the graph, so the same double
        computation follows (exact for scikit-learn forests, which round their input to
        float32 anyway; LightGBM then sees the float32 value).

    Raises
    ------
    ExportError
        The policy has no signature, or a part of it cannot be expressed.
    """
    try:
        from onnx import TensorProto, helper
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ExportError("ONNX export needs the onnx package: pip install 'offline-adp[onnx]'") from exc

    sig = signature if signature is not None else getattr(policy, "signature", None)
    if sig is None:
        raise ExportError("the policy has no signature (feature names and action table); export a run directory, "
                          "or pass signature=PolicySignature.from_info(dataset.info)")
    if input_dtype not in INPUT_DTYPES:
        raise ExportError(f"input_dtype {input_dtype!r}: expected one of {list(INPUT_DTYPES)}")
    d, values = len(sig.feature_names), sig.action_table.values
    continuous = getattr(policy, "continuous", False)
    if not continuous and values.shape[0] != policy.n_actions:
        raise ExportError(f"the signature's action table has {values.shape[0]} actions, the policy {policy.n_actions}")
    g = _Graph()
    cols = ", ".join(f"{n} [{u}]" if u else n for n, u in zip(sig.feature_names, sig.feature_units, strict=True))
    obs_doc = f"observations, one row each, columns in this order (name [unit]): {cols}"
    if input_dtype == "float32":
        inputs = [helper.make_tensor_value_info("observation", TensorProto.FLOAT, ["N", d], doc_string=obs_doc)]
        X = g.op("Cast", ["observation"], "observation_f64", to=TensorProto.DOUBLE)
    else:
        inputs = [helper.make_tensor_value_info("observation", TensorProto.DOUBLE, ["N", d], doc_string=obs_doc)]
        X = "observation"
    if continuous:
        return _command_model(g, policy, sig, X, inputs, name, input_dtype)
    steps = _steps(policy)
    if steps is None:
        index, q = _policy(g, policy, X)
    else:
        inputs.append(helper.make_tensor_value_info("t", TensorProto.INT64, ["N"],
                                                    doc_string="time step of each row (int64)"))
        T = len(steps)
        outs = [_policy(g, s, X) for s in steps]
        tc = g.op("Max", [g.op("Min", ["t", g.const(np.array(T - 1, np.int64))]), g.const(np.array(0, np.int64))], "tc")
        col = g.op("Unsqueeze", [tc, g.const(np.array([1], np.int64))], "tcol")
        stacked = g.op("Concat", [g.op("Unsqueeze", [i, g.const(np.array([1], np.int64))]) for i, _ in outs], "steps",
                       axis=1)
        index = g.op("Squeeze", [g.op("GatherElements", [stacked, col], axis=1), g.const(np.array([1], np.int64))],
                     "index")
        q = None
        if all(qq is not None for _, qq in outs):
            A = policy.n_actions
            qs = g.op("Concat", [g.op("Unsqueeze", [qq, g.const(np.array([1], np.int64))]) for _, qq in outs], "qs",
                      axis=1)
            n = g.op("Slice", [g.op("Shape", [X]), g.const(np.array([0], np.int64)), g.const(np.array([1], np.int64))],
                     "n")
            shape = g.op("Concat", [n, g.const(np.array([1, A], np.int64))], "qshape", axis=0)
            idx3 = g.op("Expand", [g.op("Reshape", [tc, g.const(np.array([-1, 1, 1], np.int64))]), shape], "qidx")
            q = g.op("Reshape", [g.op("GatherElements", [qs, idx3], axis=1), g.const(np.array([-1, A], np.int64))], "q")
    action_outputs(g, X, index, q, values, t_input=steps is not None)
    at_ = sig.action_table
    a_units = [*at_.units, *[""] * (len(at_.dims) - len(at_.units))]  # a table may carry no units
    act_cols = ", ".join(f"{n} [{u}]" if u else n for n, u in zip(at_.dims, a_units[:len(at_.dims)], strict=True))
    outputs = [helper.make_tensor_value_info("action", TensorProto.DOUBLE, ["N", values.shape[1]],
                                             doc_string="action values, one row each, columns (name "
                                             f"[unit]): {act_cols}"),
               helper.make_tensor_value_info("action_index", TensorProto.INT64, ["N"])]
    if q is not None:
        outputs.append(helper.make_tensor_value_info("q_values", TensorProto.DOUBLE, ["N", policy.n_actions]))
    at = sig.action_table
    doc = ("observation columns: " + cols + "; action: " + ", ".join(at.dims)
           + (" ; t: time step (int64)" if steps else ""))
    meta = {
        **_signature_meta(sig, input_dtype, t_input=steps is not None),
        "action_names": json.dumps(at.names),
        "action_values": json.dumps(values.tolist()),
        "policy_kind": type(policy).__name__,
        "time_indexed": json.dumps(steps is not None),
        "n_steps": json.dumps(len(steps) if steps is not None else None),
    }
    return _model(g, name, inputs, outputs, doc, meta)


def _model(g: _Graph, name: str, inputs: list[Any], outputs: list[Any], doc: str, meta: dict[str, str]) -> Any:
    """The checked ``ModelProto`` of graph ``g`` with its doc string and metadata."""
    import onnx
    from onnx import helper

    from offline_adp._version import __version__

    graph = helper.make_graph(g.nodes, name, inputs, outputs, g.inits)
    graph.doc_string = doc
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET),
                                                    helper.make_opsetid("ai.onnx.ml", ML_OPSET)],
                              producer_name="offline_adp", producer_version=__version__)
    model.ir_version = min(model.ir_version, 9)
    helper.set_model_props(model, {**meta, "offline_adp_version": __version__})
    onnx.checker.check_model(model)
    return model


def _signature_meta(sig: Any, input_dtype: str, t_input: bool = False) -> dict[str, str]:
    """Metadata every exported policy carries: the observation's and the action's names and units, the inputs."""
    at = sig.action_table
    return {
        "feature_names": json.dumps(list(sig.feature_names)),
        "feature_units": json.dumps(list(sig.feature_units)),
        "action_dims": json.dumps(list(at.dims)),
        "action_units": json.dumps(list(at.units)),
        "inputs": json.dumps({"observation": {"dtype": input_dtype, "shape": ["N", len(sig.feature_names)],
                                              "columns": list(sig.feature_names)},
                              **({"t": {"dtype": "int64", "shape": ["N"]}} if t_input else {})}),
    }


def _command_model(g: _Graph, policy: Any, sig: Any, X: str, inputs: list[Any], name: str, input_dtype: str) -> Any:
    """The model of a continuous policy: output ``command`` (double, N x m) within the bounds."""
    from onnx import TensorProto, helper

    build = _lookup(_COMMAND_EXPORTERS, policy)
    if build is None:
        raise ExportError(_refusal(policy))
    u, low, high = build(g, policy, X)
    at = sig.action_table
    m = len(at.dims)
    if len(low) != m:
        raise ExportError(f"the policy commands {len(low)} components, the signature's action table has {m}")
    _, ok_col = valid_rows(g, X, t_input=False)
    g.nodes.append(helper.make_node("Where", [ok_col, u, g.const(np.array(np.nan))], ["command"]))
    units = [*at.units, *[""] * (m - len(at.units))]
    comps = ", ".join(f"{n} [{x}]" if x else n for n, x in zip(at.dims, units[:m], strict=True))
    outputs = [helper.make_tensor_value_info("command", TensorProto.DOUBLE, ["N", m],
                                             doc_string="commands, one row each, within [low, high], "
                                             f"columns: {comps}")]
    rate = getattr(policy, "max_rate", None)
    meta = {
        **_signature_meta(sig, input_dtype),
        "command_low": json.dumps([_finite_or_none(x) for x in low]),
        "command_high": json.dumps([_finite_or_none(x) for x in high]),
        "max_rate": json.dumps(None if rate is None else np.asarray(rate, np.float64).tolist()),
        "rate_limit_in_graph": json.dumps(False),
        "policy_kind": type(policy).__name__,
        "time_indexed": json.dumps(False),
        "outputs": json.dumps({"command": {"dtype": "float64", "shape": ["N", m], "columns": list(at.dims)}}),
    }
    doc = (f"observation columns: {', '.join(sig.feature_names)}; command: {comps}; stateless: a max_rate in the "
           "metadata is for the caller to apply (|u_t - u_(t-1)| <= max_rate per component)")
    return _model(g, name, inputs, outputs, doc, meta)


def _finite_or_none(x: float) -> float | None:
    """A bound for JSON: None where undeclared (infinite)."""
    return float(x) if np.isfinite(x) else None


def _greedy_commands(g: _Graph, pi: Any, X: str) -> tuple[str, np.ndarray, np.ndarray]:
    """The greedy command policy itself, exactly: the ``k`` logged states nearest each row
    (squared differences of the scaled features summed in feature order, as the library's
    k-d tree does; ``TopK`` keeps ties in index order), their logged commands as the
    candidates followed by the extra commands offered everywhere (``n_representatives``), the Q-values of every
    candidate (slot-major pairs, the library's order), the
    first minimum, the bounds. Memory: ``N x (logged states) x d`` doubles per batch."""
    from offline_adp.qfunctions import SCALED_LIMIT, NeighbourCommands, TimeIndexedQ

    enc = pi.encoder
    cands = enc.candidates
    if isinstance(pi.q, TimeIndexedQ) or not isinstance(cands, NeighbourCommands):
        raise ExportError(_refusal(pi))
    phi = _phi(g, enc.feature_map, X)
    M, d = cands.points.shape
    k, m = cands.k, cands.commands.shape[1]
    z = g.op("Div", [g.op("Sub", [phi, g.const(cands.center.reshape(1, d), "center")]),
                     g.const(cands.scale.reshape(1, d), "scale")], "z")
    z = g.op("Min", [g.op("Max", [z, g.const(np.array(-SCALED_LIMIT))], "zlo"), g.const(np.array(SCALED_LIMIT))], "zc")
    diff = g.op("Sub", [g.op("Unsqueeze", [z, g.const(np.array([1], np.int64))], "z3"),
                        g.const(cands.points.reshape(1, M, d), "logged_states")], "diff")
    sq = g.op("Mul", [diff, diff], "sq")  # (N, M, d); summed over features in order, as the library sums
    parts = [g.op("Squeeze", [g.op("Slice", [sq, g.const(np.array([j], np.int64)), g.const(np.array([j + 1], np.int64)),
                                              g.const(np.array([2], np.int64))], "sqj"),
                                              g.const(np.array([2], np.int64))],
                  "sqj2") for j in range(d)]
    dist = parts[0]
    for part in parts[1:]:
        dist = g.op("Add", [dist, part], "dist2")
    g.op("TopK", [dist, g.const(np.array([k], np.int64))], "nearest", outputs=2, axis=1, largest=0, sorted=1)
    rows = g.nodes[-1].output[1]  # TopK's second output: the indices
    cand = g.op("Gather", [g.const(cands.commands, "logged_commands"), rows], "candidates", axis=0)  # (N, k, m)
    if cands.extra is not None:  # the commands offered at every state, after the neighbours'
        e = len(cands.extra)
        nn = g.op("Slice", [g.op("Shape", [X]), g.const(np.array([0], np.int64)), g.const(np.array([1], np.int64))],
                  "n_rows")
        eshape = g.op("Concat", [nn, g.const(np.array([e, m], np.int64))], "extra_shape", axis=0)
        extra = g.op("Expand", [g.const(cands.extra.reshape(1, e, m), "extra_commands"), eshape], "extra")
        cand = g.op("Concat", [cand, extra], "candidates_all", axis=1)  # (N, k + e, m)
        k = k + e
    slots = g.op("Reshape", [g.op("Transpose", [cand], "cand_t", perm=[1, 0, 2]), g.const(np.array([-1, m], np.int64))],
                 "slots")  # row j * N + i: candidate j of row i
    pairs = g.op("Concat", [g.op("Tile", [phi, g.const(np.array([k, 1], np.int64))], "tiled"), slots], "pairs", axis=1)
    models = getattr(pi.q, "models", None)
    if not models or len(models) != 1:
        raise ExportError(_refusal(pi))
    q = _action_major(g, _regressor(g, models[0], pairs), k)  # (N, k)
    best = g.op("ArgMin", [q], "best", axis=1, keepdims=1, select_last_index=0)  # (N, 1)
    n = g.op("Slice", [g.op("Shape", [X]), g.const(np.array([0], np.int64)), g.const(np.array([1], np.int64))], "n")
    shape = g.op("Concat", [n, g.const(np.array([1, m], np.int64))], "ushape", axis=0)
    idx = g.op("Expand", [g.op("Unsqueeze", [best, g.const(np.array([2], np.int64))], "best3"), shape], "uidx")
    u = g.op("Reshape", [g.op("GatherElements", [cand, idx], "picked", axis=1), g.const(np.array([-1, m], np.int64))],
             "u")
    low, high = (
        pi.signature.action_table.bounds() if pi.signature is not None else (np.full(m, -np.inf), np.full(m, np.inf))
    )
    u = g.op("Max", [u, g.const(np.asarray(low, np.float64).reshape(1, -1), "low")], "u_low")
    return g.op("Min", [u, g.const(np.asarray(high, np.float64).reshape(1, -1), "high")], "u_clipped"), low, high


def _distilled_commands(g: _Graph, pi: Any, X: str) -> tuple[str, np.ndarray, np.ndarray]:
    """A distilled policy's command: one tree node per component on the float32-rounded
    input (as its ensembles compare), concatenated, then ``min(max(u, low), high)``."""
    x = _float32_roundtrip(g, X)
    cols = []
    for model in pi.models:
        ens = _ensemble_of(model)
        if ens is None:
            raise ExportError(f"cannot export a distilled policy over a {type(model).__name__}; tree ensembles only")
        cols.append(_tree_node(g, x, _ensemble_arrays(ens), "AVERAGE"))
    u = cols[0] if len(cols) == 1 else g.op("Concat", cols, "u", axis=1)
    low, high = np.asarray(pi.low, np.float64), np.asarray(pi.high, np.float64)
    u = g.op("Max", [u, g.const(low.reshape(1, -1), "low")], "u_low")
    return g.op("Min", [u, g.const(high.reshape(1, -1), "high")], "u_clipped"), low, high


def save_onnx(policy: Any, path: str | PathLike[str], signature: Any = None, *, input_dtype: str = "float64") -> Path:
    """Write ``policy`` as an ONNX model to ``path`` (atomically); see :func:`policy_to_onnx`."""
    model = policy_to_onnx(policy, signature, input_dtype=input_dtype)
    out = Path(path)
    with atomic_file(out, what="ONNX file") as tmp:  # the temporary removed whatever happens
        tmp.write_bytes(model.SerializeToString())
    log.info("wrote %s (%d nodes, %.1f kB)", out, len(model.graph.node), out.stat().st_size / 1e3)
    return out


def onnx_metadata(path: str | PathLike[str]) -> dict[str, Any]:
    """The metadata of an exported policy (JSON values decoded)."""
    import onnx

    model = onnx.load(str(path))
    out: dict[str, Any] = {}
    for p in model.metadata_props:
        try:
            out[p.key] = json.loads(p.value)
        except json.JSONDecodeError:
            out[p.key] = p.value
    return out
