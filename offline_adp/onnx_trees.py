"""The ONNX graph builder and tree ensembles in it, for :mod:`offline_adp.onnx_export`: nodes
and initializers with unique names (:class:`_Graph`), tree nodes as one ONNX-ML
``TreeEnsemble`` with double thresholds and leaf values (from a
:class:`~offline_adp.trees.ensemble.TreeEnsemble`, a scikit-learn forest or LightGBM
boosters), and a regressor's prediction as a node (scikit-learn's inputs rounded to
float32 first, as it compares them).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.errors import ExportError


# ----------------------------------------------------------------------------- graph builder
class _Graph:
    """Nodes and initializers with unique names."""

    def __init__(self) -> None:
        from onnx import helper

        self.h = helper
        self.nodes: list[Any] = []
        self.inits: list[Any] = []
        self.k = 0
        self.memo: dict[Any, str] = {}  # shared sub-graphs (inputs every step's rule reads)

    def name(self, stem: str) -> str:
        self.k += 1
        return f"{stem}_{self.k}"

    def const(self, value: np.ndarray, stem: str = "c") -> str:
        from onnx import numpy_helper

        n = self.name(stem)
        self.inits.append(numpy_helper.from_array(np.asarray(value), n))
        return n

    def op(self, op_type: str, inputs: list[str], stem: str | None = None, domain: str = "", outputs: int = 1,
           **attrs: Any) -> str:
        outs = [self.name(stem or op_type.lower()) for _ in range(outputs)]
        self.nodes.append(self.h.make_node(op_type, inputs, outs, domain=domain, **attrs))
        return outs[0]


# ----------------------------------------------------------------------------- trees
def _tree_node(g: _Graph, X: str, trees: dict[str, np.ndarray], aggregate: str) -> str:
    """An ONNX-ML ``TreeEnsemble`` node (double splits, weights and output) on double
    input ``X``; output (N, 1).

    ``trees`` holds global node arrays: ``leaf`` (bool), ``feature``, ``threshold``,
    ``left``/``right`` (global child index, go left when ``x <= threshold``), ``weight``
    (leaf values) and ``roots``.
    """
    from onnx import numpy_helper

    leaf = np.asarray(trees["leaf"], bool)
    left, right = np.asarray(trees["left"], np.int64), np.asarray(trees["right"], np.int64)
    roots = np.asarray(trees["roots"], np.int64)
    interior = np.flatnonzero(~leaf)
    leaves = np.flatnonzero(leaf)
    ipos = np.full(len(leaf), -1, np.int64)
    ipos[interior] = np.arange(len(interior))
    lpos = np.full(len(leaf), -1, np.int64)
    lpos[leaves] = np.arange(len(leaves))

    def child(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        is_leaf = leaf[c]
        return np.where(is_leaf, lpos[c], ipos[c]), is_leaf.astype(np.int64)

    tid, tleaf = child(left[interior])
    fid, fleaf = child(right[interior])
    feature = np.asarray(trees["feature"], np.int64)[interior]
    split = np.asarray(trees["threshold"], np.float64)[interior]
    # a tree that is a single leaf: one node whose branches both reach that leaf
    single = roots[leaf[roots]]
    tree_roots = np.where(leaf[roots], len(interior) + np.cumsum(leaf[roots]) - 1, ipos[roots])
    tid, fid = np.r_[tid, lpos[single]], np.r_[fid, lpos[single]]
    tleaf, fleaf = np.r_[tleaf, np.ones(len(single), np.int64)], np.r_[fleaf, np.ones(len(single), np.int64)]
    feature, split = np.r_[feature, np.zeros(len(single), np.int64)], np.r_[split, np.zeros(len(single))]
    n_nodes = len(feature)
    attrs: dict[str, Any] = {
        "tree_roots": tree_roots.tolist(),
        "nodes_featureids": feature.tolist(),
        "nodes_splits": numpy_helper.from_array(split.astype(np.float64)),
        "nodes_modes": numpy_helper.from_array(np.zeros(n_nodes, np.uint8)),  # BRANCH_LEQ
        "nodes_truenodeids": tid.tolist(),
        "nodes_trueleafs": tleaf.tolist(),
        "nodes_falsenodeids": fid.tolist(),
        "nodes_falseleafs": fleaf.tolist(),
        "leaf_targetids": [0] * len(leaves),
        "leaf_weights": numpy_helper.from_array(np.asarray(trees["weight"], np.float64)[leaves]),
        "n_targets": 1,
        "aggregate_function": {"AVERAGE": 0, "SUM": 1}[aggregate],
        "post_transform": 0,
    }
    return g.op("TreeEnsemble", [X], "trees", domain="ai.onnx.ml", **attrs)


def _ensemble_arrays(ens: Any, weight: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Node arrays of a :class:`TreeEnsemble` (leaf weights: its values or ``weight``)."""
    left = np.asarray(ens.left)
    return {"leaf": left < 0, "feature": np.asarray(ens.feature), "threshold": np.asarray(ens.threshold), "left": left,
            "right": np.asarray(ens.right), "roots": np.asarray(ens.roots),
            "weight": np.asarray(ens.value if weight is None else weight, np.float64)}


def _lightgbm_arrays(boosters: list[Any]) -> dict[str, np.ndarray]:
    """Node arrays of LightGBM boosters (all trees summed: the raw score)."""
    cols: dict[str, list[Any]] = {k: [] for k in ("leaf", "feature", "threshold", "left", "right", "weight")}
    roots: list[int] = []
    for b in boosters:
        dump = b.dump_model()
        if dump.get("num_class", 1) != 1:
            raise ExportError("a multi-class LightGBM model is not a Q-function regressor")
        for info in dump["tree_info"]:
            roots.append(len(cols["leaf"]))
            stack = [info["tree_structure"]]
            pending: list[tuple[int, str, Any]] = []
            while stack or pending:  # one tree's nodes (model size, not data size)
                if pending:
                    parent, side, nd = pending.pop()
                    cols[side][parent] = len(cols["leaf"])
                else:
                    nd = stack.pop()
                j = len(cols["leaf"])
                if "split_feature" not in nd:
                    for k, v in (("leaf", True), ("feature", 0), ("threshold", 0.0), ("left", -1), ("right", -1),
                                 ("weight", float(nd.get("leaf_value", 0.0)))):
                        cols[k].append(v)
                    continue
                if nd.get("decision_type", "<=") != "<=" or nd.get("missing_type", "None") == "Zero":
                    raise ExportError(f"LightGBM split {nd.get('decision_type')} with missing_type "
                                      f"{nd.get('missing_type')} "
                                      "is not supported (numerical '<=' splits only, no zero_as_missing)")
                for k, v in (("leaf", False), ("feature", int(nd["split_feature"])),
                             ("threshold", float(nd["threshold"])),
                             ("left", -1), ("right", -1), ("weight", 0.0)):
                    cols[k].append(v)
                pending.append((j, "right", nd["right_child"]))
                pending.append((j, "left", nd["left_child"]))
    out = {k: np.asarray(v) for k, v in cols.items()}
    out["leaf"] = out["leaf"].astype(bool)
    out["roots"] = np.asarray(roots, np.int64)
    return out


#: The LightGBM booster of a model, by the model's class name (artifacts' ``_Booster`` is a
#: loaded one; by name because this module does not import artifacts, a higher layer).
_BOOSTERS: dict[str, Any] = {
    "Booster": lambda m: m,
    "_Booster": lambda m: m.booster,
    "LGBMRegressor": lambda m: m.booster_,
}


def _booster_of(model: Any) -> Any | None:
    get = _BOOSTERS.get(type(model).__name__)
    return None if get is None else get(model)


def _is_forest(model: Any, classifier: bool) -> bool:
    """A fitted scikit-learn forest (regressor, or classifier if ``classifier``)."""
    return (hasattr(model, "estimators_") and hasattr(model.estimators_[0], "tree_")
            and hasattr(model, "classes_") == classifier)


def _ensemble_of(model: Any) -> Any | None:
    """The :class:`TreeEnsemble` of a regressor: itself, a scikit-learn forest's arrays, or None."""
    from offline_adp.trees import TreeEnsemble

    if isinstance(model, TreeEnsemble):
        return model
    return TreeEnsemble.from_sklearn(model) if _is_forest(model, classifier=False) else None


def _regressor(g: _Graph, model: Any, X: str) -> str:
    """``model.predict(X)`` as a node: (N, 1) double."""
    booster = _booster_of(model)
    if booster is not None:
        return _tree_node(g, X, _lightgbm_arrays([booster]), "SUM")
    ens = _ensemble_of(model)
    if ens is not None:
        return _tree_node(g, _float32_roundtrip(g, X), _ensemble_arrays(ens), "AVERAGE")
    raise ExportError(f"cannot export a {type(model).__name__} regressor to ONNX; supported: scikit-learn forests "
                      "(extra_trees, random_forest), LightGBM")


def _float32_roundtrip(g: _Graph, X: str) -> str:
    from onnx import TensorProto

    key = ("f32", X)
    if key not in g.memo:
        g.memo[key] = g.op("Cast", [g.op("Cast", [X], "x32", to=TensorProto.FLOAT)], "x32d", to=TensorProto.DOUBLE)
    return g.memo[key]


def _forest_classifier(clf: Any) -> tuple[Any, np.ndarray, np.ndarray] | None:
    """(TreeEnsemble, leaf class fractions, classes) of a forest classifier (a loaded
    artifact's ``_TreeClassifier``, by name: a layer above; or a scikit-learn forest), else None."""
    from offline_adp.trees import TreeEnsemble

    if type(clf).__name__ == "_TreeClassifier":
        return clf.ensemble, np.asarray(clf.class_values), np.asarray(clf.classes_)
    if not _is_forest(clf, classifier=True):
        return None
    probs = np.concatenate([e.tree_.value[:, 0, :] for e in clf.estimators_])
    return (TreeEnsemble.from_sklearn(clf), probs / np.maximum(probs.sum(axis=1, keepdims=True), 1e-300),
            np.asarray(clf.classes_))


def valid_rows(g: _Graph, X: str, t_input: bool) -> tuple[str, str]:
    """Rows the policy acts on, as ``policy.act`` does: every observation value finite (and
    ``t >= 0`` with a time input); ``(N,)`` and ``(N, 1)`` booleans. The other rows get
    ``action_index`` -1 and NaN values (``act`` refuses them), never a plausible action: a
    tree compares NaN as it likes (LightGBM as 0 or to a default side), and a deployed
    controller must see that there is none. ``0 * x`` is NaN exactly where ``x`` is NaN or
    infinite, so a row's sum of them tests the row."""
    bad = g.op("IsNaN", [g.op("ReduceSum", [g.op("Mul", [X, g.const(np.array(0.0))], "zeroed"),
                                            g.const(np.array([1], np.int64))], "rowsum", keepdims=1)], "nonfinite")
    ok_col = g.op("Not", [bad], "finite_row")
    if t_input:
        t_ok = g.op("GreaterOrEqual", ["t", g.const(np.array(0, np.int64))], "t_ok")
        ok_col = g.op("And", [ok_col, g.op("Unsqueeze", [t_ok, g.const(np.array([1], np.int64))])], "valid_row")
    ok = g.op("Squeeze", [ok_col, g.const(np.array([1], np.int64))], "valid")
    return ok, ok_col


def action_outputs(g: _Graph, X: str, index: str, q: str | None, values: np.ndarray, t_input: bool) -> None:
    """The outputs ``action_index`` (int64), ``action`` (the action table's values) and, with
    ``q``, ``q_values`` of a discrete policy, the rows it does not act on (:func:`valid_rows`)
    given index -1 and NaN values."""
    from onnx import TensorProto

    ok, ok_col = valid_rows(g, X, t_input)
    nan = g.const(np.array(np.nan))
    index = g.op("Cast", [index], "index64", to=TensorProto.INT64)
    g.nodes.append(g.h.make_node("Where", [ok, index, g.const(np.array(-1, np.int64))], ["action_index"]))
    gathered = g.op("Gather", [g.const(values, "action_values"), "action_index"], "gathered", axis=0)
    g.nodes.append(g.h.make_node("Where", [ok_col, gathered, nan], ["action"]))
    if q is not None:
        g.nodes.append(g.h.make_node("Where", [ok_col, q, nan], ["q_values"]))
