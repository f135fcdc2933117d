"""Conversion between our tree arrays and scikit-learn's tree objects.

The only module that touches scikit-learn's private tree state (``sklearn.tree._tree.Tree``
set through ``__setstate__``): its compiled ``apply`` is the fastest leaf lookup we have,
for trees we hold as arrays (:class:`~offline_adp.trees.ensemble.TreeEnsemble`) and for
the compiled builder's trees (:mod:`offline_adp.trees.builder`). Where this scikit-learn's
tree state layout is not the one we know, the builders here return None and the callers
fall back to a numpy traversal.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.trees.averaging import release_freed

#: what a tree state layout we do not know raises while we set it
_LAYOUT_ERRORS = (ImportError, AttributeError, KeyError, TypeError, ValueError)


def sklearn_tree(left: np.ndarray, right: np.ndarray, feature: np.ndarray, threshold: np.ndarray, value: np.ndarray,
                 n_features: int) -> Any:
    """A scikit-learn ``Tree`` from one tree's arrays (local node ids; leaves: children -1,
    feature -2), for its compiled ``apply``: plain numbers set through its state, no code
    from any file. None if this scikit-learn's tree state layout is not the one we know."""
    try:
        from sklearn.tree._tree import Tree

        n = len(left)
        t = Tree(int(n_features), np.array([1], dtype=np.intp), 1)
        nodes = np.zeros(n, dtype=t.__getstate__()["nodes"].dtype)
        nodes["left_child"], nodes["right_child"] = left, right
        nodes["feature"], nodes["threshold"] = feature, threshold
        nodes["n_node_samples"] = 1
        nodes["weighted_n_node_samples"] = 1.0
        t.__setstate__({"max_depth": int(n), "node_count": int(n), "nodes": nodes,
                        "values": np.asarray(value, dtype=np.float64).reshape(n, 1, 1)})
        return t
    except _LAYOUT_ERRORS:
        return None


def sklearn_tree_from_records(nodes: np.ndarray, value: np.ndarray, n_features: int) -> Any:
    """A scikit-learn ``Tree`` from node records already in its own layout (the compiled
    extra-trees builder writes them, :func:`offline_adp.trees.builder.node_dtype`), set
    through its state without a field-by-field copy; from the fields otherwise. None if
    this scikit-learn's tree state layout is not the one we know."""
    try:
        from sklearn.tree._tree import Tree

        n = len(nodes)
        t = Tree(int(n_features), np.array([1], dtype=np.intp), 1)
        if nodes.dtype != t.__getstate__()["nodes"].dtype:
            return sklearn_tree(nodes["left_child"], nodes["right_child"], nodes["feature"], nodes["threshold"], value,
                                n_features)
        t.__setstate__({"max_depth": int(n), "node_count": int(n), "nodes": np.ascontiguousarray(nodes),
                        "values": np.asarray(value, dtype=np.float64).reshape(n, 1, 1)})
        return t
    except _LAYOUT_ERRORS:
        return None


def sklearn_trees_known() -> bool:
    """Whether scikit-learn ``Tree`` objects can be set from arrays here (the compiled
    builder's trees are looked up through them)."""
    z = np.zeros(1, np.int64)
    return sklearn_tree(z - 1, z - 1, z - 2, np.full(1, -2.0), np.zeros(1), 1) is not None


def is_sklearn_forest(model: Any) -> bool:
    """Whether ``model`` is a fitted scikit-learn tree ensemble (``estimators_`` of trees)."""
    return (hasattr(model, "estimators_") and hasattr(model, "apply") and len(model.estimators_) > 0
            and hasattr(model.estimators_[0], "tree_"))


def forest_trees(forest: Any) -> list[Any]:
    """The ``Tree`` objects of a forest (``estimators_``), or of a single fitted tree."""
    return [e.tree_ for e in getattr(forest, "estimators_", [forest])]


def forest_leaf_values(forest: Any) -> np.ndarray:
    """Every node's value, trees concatenated (indexed by the global leaf ids of
    :func:`sklearn_leaves`)."""
    return np.concatenate([t.value[:, 0, 0] for t in forest_trees(forest)])


def tree_arrays(trees: list[Any], consume: bool = False) -> dict[str, np.ndarray]:
    """Flat arrays ``left, right, feature, threshold, value, roots`` of a list of ``Tree``
    objects (global node ids; see :class:`~offline_adp.trees.ensemble.TreeEnsemble`).
    ``consume``: drop each tree from ``trees`` once copied (the caller's list), so that
    the trees' memory and the arrays' are not both held at their peak."""
    sizes = np.array([t.node_count for t in trees], dtype=np.int64)
    offs = np.r_[0, np.cumsum(sizes)[:-1]].astype(np.int64)
    total = int(sizes.sum())
    left, right = np.empty(total, np.int64), np.empty(total, np.int64)
    feature, threshold, value = np.empty(total, np.int64), np.empty(total), np.empty(total)
    for i, (o, k) in enumerate(zip(offs, sizes, strict=True)):  # one copy of each field, into place
        t = trees[i]
        if consume:
            trees[i] = None
        lt, rt = left[o:o + k], right[o:o + k]
        lt[:], rt[:] = t.children_left, t.children_right
        feature[o:o + k], threshold[o:o + k], value[o:o + k] = t.feature, t.threshold, t.value[:, 0, 0]
        inner = lt >= 0  # child ids are local to their tree: make them global (tree by tree, in cache)
        np.add(lt, o, out=lt, where=inner)
        np.add(rt, o, out=rt, where=inner)
        del t
        if consume and i % 8 == 7:  # the copied trees' pages back to the system as the arrays fill
            release_freed()
    return {"left": left, "right": right, "feature": feature, "threshold": threshold, "value": value, "roots": offs}


def sklearn_leaves(forest: Any, X: np.ndarray) -> np.ndarray:
    """Global leaf ids (as in :func:`tree_arrays`) via scikit-learn's fast ``apply``."""
    sizes = np.array([e.tree_.node_count for e in forest.estimators_])
    offs = np.r_[0, np.cumsum(sizes)[:-1]]
    jobs = forest.n_jobs
    if len(X) < 20_000:  # thread start-up costs more than it saves on small batches (rollouts)
        forest.n_jobs = 1
    try:
        leaves = forest.apply(np.asarray(X, dtype=np.float32))
    finally:
        forest.n_jobs = jobs
    dtype = np.int32 if sizes.sum() < 2**31 else np.int64
    # C order: a mean over the trees axis then sums in the same order as TreeEnsemble.predict
    return np.ascontiguousarray((leaves + offs[None, :]).astype(dtype))
