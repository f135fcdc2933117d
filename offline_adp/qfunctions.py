"""Q-functions over (x, a) for a finite action set, and the frozen-structure tree averager.

A Q-function answers ``values(obs, t) -> (n, n_actions)`` for all actions in one
batched call. Representations:

- :class:`QEncoder` turns observations (and actions) into regressor inputs: an optional
  feature map ``phi(x)`` (any fitted scikit-learn transformer), and either one *joint*
  model on ``[phi(x), action features]`` (the action's value vector or a one-hot code)
  or one model *per action* on ``phi(x)``.
- :class:`RegressorQ` wraps fitted regressors (one joint or one per action).
- :class:`TreeEnsemble` is a tree ensemble as plain arrays (our own export of
  scikit-learn forests): vectorised prediction, leaf lookup, and safe ``.npz`` storage.
  With its structure fixed, re-estimating leaf values from new targets is a
  kernel averager (:class:`~offline_adp.learners.FrozenTreesLearner`), the frozen-structure fast path of
  Ernst et al. (2005).
- :class:`TimeIndexedQ` holds one Q per step for finite horizons (Algorithm 10).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np

from offline_adp.errors import ArtifactError

TimeArg = int | np.ndarray


class QFunction(ABC):
    """Q(x, a[, t]) for all actions at once."""

    n_actions: int

    @abstractmethod
    def values(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        """Q-values, shape (n, n_actions)."""


@dataclass
class QEncoder:
    """Builds regressor inputs from observations and actions.

    Parameters
    ----------
    n_actions : int
    action_features : ndarray (n_actions, k)
        What a joint model sees of each action (value vectors or one-hot rows).
    per_action : bool
        One model per action on ``phi(x)`` instead of a joint model.
    feature_map : fitted transformer, optional
        ``phi``; applied to observations before anything else.
    """

    n_actions: int
    action_features: np.ndarray
    per_action: bool = False
    feature_map: Any = None

    def phi(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        return obs if self.feature_map is None else np.asarray(self.feature_map.transform(obs), dtype=np.float64)

    def pairs(self, phi: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """Joint inputs ``[phi(x_i), f(a_i)]``, shape (n, d + k)."""
        return np.hstack([phi, self.action_features[np.asarray(actions, dtype=np.int64)]])

    def all_pairs(self, phi: np.ndarray) -> np.ndarray:
        """Joint inputs for every action, action-major: row ``a * n + i`` is (x_i, a)."""
        n = len(phi)
        return np.hstack([np.tile(phi, (self.n_actions, 1)), np.repeat(self.action_features, n, axis=0)])


def predict_model(model: Any, X: np.ndarray) -> np.ndarray:
    """``model.predict(X)`` as float64; scikit-learn forests go through their leaves
    (``apply`` + a fixed-order mean), which is deterministic (the threaded
    ``predict`` sums trees in a racy order) and equal to a saved :class:`TreeEnsemble`."""
    if hasattr(model, "estimators_") and hasattr(model, "apply") and hasattr(model.estimators_[0], "tree_"):
        values = getattr(model, "_oadp_values", None)
        if values is None:
            values = np.concatenate([e.tree_.value[:, 0, 0] for e in model.estimators_])
            model._oadp_values = values
        return ensemble_predict(values, sklearn_leaves(model, X))
    return np.asarray(model.predict(X), dtype=np.float64)


class RegressorQ(QFunction):
    """Q from fitted regressors: one joint model, or one model per action."""

    def __init__(self, models: list[Any], encoder: QEncoder) -> None:
        self.models, self.encoder, self.n_actions = models, encoder, encoder.n_actions

    def values(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        phi = self.encoder.phi(obs)
        return self.values_phi(phi)

    def values_phi(self, phi: np.ndarray) -> np.ndarray:
        n = len(phi)
        if self.encoder.per_action:
            return np.column_stack([predict_model(m, phi) for m in self.models])
        return predict_model(self.models[0], self.encoder.all_pairs(phi)).reshape(self.n_actions, n).T


def per_step(obs: np.ndarray, t: TimeArg, n_steps: int, width: int, fn: Any) -> np.ndarray:
    """Evaluate ``fn(step, obs_rows) -> (m, width)`` once per distinct step in ``t``
    (a scalar or one per row; steps >= ``n_steps`` use the last)."""
    obs = np.asarray(obs)
    tt = np.broadcast_to(np.minimum(np.asarray(t), n_steps - 1), (len(obs),))
    out = np.empty((len(obs), width))
    for step in np.unique(tt):
        rows = tt == step
        out[rows] = fn(int(step), obs[rows])
    return out


class TimeIndexedQ(QFunction):
    """One Q-function per step t = 0..T-1 (finite horizon); steps >= T use the last."""

    def __init__(self, qs: list[QFunction]) -> None:
        self.qs, self.n_actions = qs, qs[0].n_actions

    def values(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return per_step(obs, t, len(self.qs), self.n_actions, lambda k, x: self.qs[k].values(x, k))


# ----------------------------------------------------------------------------- tree ensembles
@dataclass
class TreeEnsemble:
    """An averaging ensemble of binary regression trees as flat arrays.

    Node ``j`` (global index over all trees) splits on ``feature[j]`` at
    ``threshold[j]`` (go left when ``x <= threshold``); leaves have ``left[j] == -1``
    and predict ``value[j]``. ``roots[m]`` is tree m's root. The prediction is the mean
    over trees of the reached leaf values, as in scikit-learn's forests.
    """

    left: np.ndarray
    right: np.ndarray
    feature: np.ndarray
    threshold: np.ndarray
    value: np.ndarray
    roots: np.ndarray

    @property
    def n_trees(self) -> int:
        return len(self.roots)

    @classmethod
    def from_sklearn(cls, forest: Any) -> TreeEnsemble:
        """Export a fitted scikit-learn forest (or a single tree) to arrays."""
        out = cls._from_trees([e.tree_ for e in getattr(forest, "estimators_", [forest])])
        if hasattr(forest, "estimators_"):
            out._forest = forest  # type: ignore[attr-defined]
        return out

    @classmethod
    def _from_trees(cls, trees: list[Any], consume: bool = False) -> TreeEnsemble:
        """``consume``: drop each tree from ``trees`` once copied (the caller's list), so that
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
        return cls(left=left, right=right, feature=feature, threshold=threshold, value=value, roots=offs)

    def apply(self, X: np.ndarray) -> np.ndarray:
        """Global leaf index reached in each tree, shape (n, n_trees).

        Uses the originating scikit-learn forest's compiled ``apply`` when this ensemble
        was exported in this process (same leaves), else a vectorised numpy traversal.
        """
        forest = getattr(self, "_forest", None)
        if forest is not None:
            return sklearn_leaves(forest, X)
        self.check_inputs(X)
        trees = self._compiled_trees()
        if trees is not None:
            X32 = np.ascontiguousarray(X, dtype=np.float32)
            out = np.empty((len(X32), self.n_trees), dtype=np.int64)
            for m, (tree, root) in enumerate(zip(trees, self.roots, strict=True)):
                out[:, m] = tree.apply(X32) + root
            return out
        # scikit-learn trees compare float32 inputs with their thresholds: do the same
        X = np.asarray(X, dtype=np.float32).astype(np.float64)
        n, m = len(X), self.n_trees
        # all (row, tree) pairs descend together, one level per pass; finished pairs drop out
        node = np.tile(np.asarray(self.roots, dtype=np.int64), n)  # flat (n * m), row-major
        row = np.repeat(np.arange(n), m)
        idx = np.flatnonzero(self.left[node] >= 0)
        while len(idx):
            nd = node[idx]
            go_left = X[row[idx], self.feature[nd]] <= self.threshold[nd]
            nxt = np.where(go_left, self.left[nd], self.right[nd])
            node[idx] = nxt
            idx = idx[self.left[nxt] >= 0]
        return node.reshape(n, m)

    def check_inputs(self, X: np.ndarray) -> None:
        """Raise ArtifactError unless ``X`` is 2-d and has every feature a split reads:
        compiled trees read ``X[:, feature]`` unchecked, so call this before using them."""
        need = getattr(self, "_n_features", None)
        if need is None:
            inner = self.left >= 0
            need = self._n_features = int(self.feature[inner].max()) + 1 if inner.any() else 0  # type: ignore[attr-defined]
        if np.ndim(X) != 2 or np.shape(X)[1] < need:
            raise ArtifactError(f"tree ensemble splits on feature {need - 1}, the input has shape {np.shape(X)}")

    def _compiled_trees(self) -> list[Any] | None:
        """scikit-learn ``Tree`` objects rebuilt from our arrays (plain numbers, no code
        from any file), for its compiled ``apply``; None if this scikit-learn's tree state
        layout is not the one we know (then the numpy traversal is used)."""
        cached = getattr(self, "_trees", False)
        if cached is not False:
            return cached
        shared = getattr(self, "_same_structure", None)  # ensembles made by with_values share one set
        if shared is not None and "trees" in shared:
            self._trees = shared["trees"]  # type: ignore[attr-defined]
            return self._trees  # type: ignore[attr-defined]
        trees: list[Any] | None = []
        bounds = np.r_[self.roots, len(self.left)]
        n_features = int(max(self.feature.max(), 0)) + 1
        for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
            leaf = self.left[lo:hi] < 0
            t = sklearn_tree(np.where(leaf, -1, self.left[lo:hi] - lo), np.where(leaf, -1, self.right[lo:hi] - lo),
                             np.where(leaf, -2, self.feature[lo:hi]), np.where(leaf, -2.0, self.threshold[lo:hi]),
                             self.value[lo:hi], n_features)
            if t is None:  # an unknown scikit-learn layout: fall back to numpy
                trees = None
                break
            trees.append(t)
        self._trees = trees  # type: ignore[attr-defined]
        if shared is not None:
            shared["trees"] = trees
        return trees

    def predict(self, X: np.ndarray) -> np.ndarray:
        return ensemble_predict(self.value, self.apply(X))

    def with_values(self, value: np.ndarray) -> TreeEnsemble:
        """The same structure with other leaf values. The structure's compiled lookup is
        shared with every ensemble made this way, now or when first built: a finite-horizon
        fit's T per-step snapshots of one structure compiled T copies of it (CartPole, 79
        steps of 20 trees on 50k rows: 19 GB), one is enough (the lookup reads no value)."""
        out = TreeEnsemble(self.left, self.right, self.feature, self.threshold, np.asarray(value, dtype=np.float64), self.roots)
        if getattr(self, "_same_structure", None) is None:
            self._same_structure = {}  # type: ignore[attr-defined]
        out._same_structure = self._same_structure  # type: ignore[attr-defined]
        for k in ("_forest", "_trees", "_n_features", "n_features_in_"):  # same structure: same leaf lookup
            if getattr(self, k, None) is not None:
                setattr(out, k, getattr(self, k))
        return out

    def to_arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        """The arrays to store: node indices as int32 when they fit (a fully grown forest
        on 50k samples has ~5M nodes: 26 instead of 40 bytes a node)."""
        out = {prefix + k: getattr(self, k) for k in ("threshold", "value")}
        small = len(self.left) < 2**31 - 1
        for k in ("left", "right", "roots"):
            a = np.asarray(getattr(self, k))
            out[prefix + k] = a.astype(np.int32) if small else a
        f = np.asarray(self.feature)
        out[prefix + "feature"] = f.astype(np.int16) if len(f) == 0 or f.max() < 2**15 - 1 else f
        return out

    @classmethod
    def from_arrays(cls, arrays: Any, prefix: str = "") -> TreeEnsemble:
        return cls(**{k: np.asarray(arrays[prefix + k]) for k in ("left", "right", "feature", "threshold", "value", "roots")})


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
    except Exception:
        return None


def sklearn_tree_from_records(nodes: np.ndarray, value: np.ndarray, n_features: int) -> Any:
    """A scikit-learn ``Tree`` from node records already in its own layout (the compiled
    extra-trees builder writes them, :func:`offline_adp.extra_trees.node_dtype`), set
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
    except Exception:
        return None


def sklearn_leaves(forest: Any, X: np.ndarray) -> np.ndarray:
    """Global leaf ids (as in :meth:`TreeEnsemble.from_sklearn`) via scikit-learn's fast ``apply``."""
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


def ensemble_predict(values: np.ndarray, leaves: np.ndarray) -> np.ndarray:
    """Mean over trees of leaf values at precomputed leaves (n, n_trees) -> (n,).

    Always summed in C order, so the result is bitwise reproducible whatever the
    layout of ``leaves`` (resumed fits depend on that).
    """
    return np.ascontiguousarray(values[leaves]).mean(axis=1)


class TreeQ(QFunction):
    """Q from :class:`TreeEnsemble` s (one joint, or one per action)."""

    def __init__(self, ensembles: list[TreeEnsemble], encoder: QEncoder) -> None:
        self.ensembles, self.encoder, self.n_actions = ensembles, encoder, encoder.n_actions
        self.models = ensembles  # same interface as RegressorQ

    def values(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return RegressorQ.values_phi(self, self.encoder.phi(obs))  # type: ignore[arg-type]


class FunctionQ(QFunction):
    """Q from a vectorised function ``fn(obs, t) -> (n, n_actions)`` (e.g. a linear start)."""

    def __init__(self, fn: Any, n_actions: int) -> None:
        self.fn, self.n_actions = fn, n_actions

    def values(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return np.asarray(self.fn(np.asarray(obs, dtype=np.float64), t), dtype=np.float64).reshape(len(obs), self.n_actions)
