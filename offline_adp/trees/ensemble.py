"""Tree ensembles as plain arrays: prediction, leaf lookups and safe ``.npz`` storage.

:class:`TreeEnsemble` is our own export of scikit-learn forests (and of the compiled
builder's trees, :mod:`offline_adp.trees.builder`). With its structure fixed,
re-estimating leaf values from new targets is a kernel averager
(:class:`~offline_adp.learn.frozen.FrozenTreesLearner`), the frozen-structure fast path
of Ernst et al. (2005). The leaf lookups here come in two shapes: whole-ensemble
(``(rows, trees)``, :meth:`TreeEnsemble.apply`) and per tree (one tree's leaves at a
time, from any thread, :func:`per_tree_leaves`, :func:`compiled_per_tree_leaves`), so
that no ``(rows, trees)`` matrix is held for large query sets.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from offline_adp.errors import ArtifactError
from offline_adp.trees import averaging, builder
from offline_adp.trees.sklearn import forest_trees, sklearn_leaves, sklearn_tree, tree_arrays

#: rows per chunk of a whole-ensemble leaf lookup (bounded temporaries)
LOOKUP_CHUNK = 262_144


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
        out = cls(**tree_arrays(forest_trees(forest)))
        if hasattr(forest, "estimators_"):
            out._forest = forest  # type: ignore[attr-defined]
        return out

    @classmethod
    def from_trees(cls, trees: list[Any], consume: bool = False) -> TreeEnsemble:
        """From scikit-learn ``Tree`` objects (see :func:`~offline_adp.trees.sklearn.tree_arrays`)."""
        return cls(**tree_arrays(trees, consume=consume))

    def apply(self, X: np.ndarray) -> np.ndarray:
        """Global leaf index reached in each tree, shape (n, n_trees).

        Uses the originating scikit-learn forest's compiled ``apply`` when this ensemble
        was exported in this process (same leaves), else a vectorised numpy traversal.
        """
        forest = getattr(self, "_forest", None)
        if forest is not None:
            return sklearn_leaves(forest, X)
        self.check_inputs(X)
        trees = self.compiled_trees()
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

    def compiled_trees(self) -> list[Any] | None:
        """Compiled per-tree lookups rebuilt from our arrays (plain numbers, no code from any
        file): :class:`~offline_adp.trees.builder.CompactTree` where numba is installed (the
        leaves scikit-learn's ``apply`` reaches, in 32 bytes a node), else scikit-learn
        ``Tree`` objects for its compiled ``apply``; None if this scikit-learn's tree state
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
        compact = builder.available()  # 32 bytes a node and a lookup in threads (scikit-learn's: 72)
        for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
            leaf = self.left[lo:hi] < 0
            if compact:
                trees.append(builder.CompactTree(np.where(leaf, -1, self.left[lo:hi] - lo),
                                                 np.where(leaf, -1, self.right[lo:hi] - lo),
                                                 np.where(leaf, -2, self.feature[lo:hi]),
                                                 np.where(leaf, -2.0, self.threshold[lo:hi]), self.value[lo:hi]))
                continue
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
        shared with every ensemble made this way, now or when first built: a
        finite-horizon fit's per-step snapshots of one structure need one compiled copy,
        not one per step (the lookup reads no value; sizes in docs/fqi-modes.md)."""
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


def constant_ensemble(value: float, n_trees: int) -> TreeEnsemble:
    """An ensemble of ``n_trees`` one-leaf trees predicting ``value``."""
    minus = np.full(n_trees, -1, np.int64)
    return TreeEnsemble(left=minus, right=minus.copy(), feature=np.full(n_trees, -2, np.int64),
                        threshold=np.full(n_trees, -2.0), value=np.full(n_trees, value),
                        roots=np.arange(n_trees, dtype=np.int64))


def ensemble_predict(values: np.ndarray, leaves: np.ndarray) -> np.ndarray:
    """Mean over trees of leaf values at precomputed leaves (n, n_trees) -> (n,).

    Always summed in C order, so the result is bitwise reproducible whatever the
    layout of ``leaves`` (resumed fits depend on that).
    """
    return np.ascontiguousarray(values[leaves]).mean(axis=1)


def tree_mean(values: np.ndarray, pos: np.ndarray, n_jobs: int = 1) -> np.ndarray:
    """``values[pos].mean(axis=0)`` for tree-major ``pos`` (m, nq), in ``n_jobs`` threads
    (:func:`offline_adp.trees.averaging.tree_mean`; the same numbers for any count).
    Every position must be in range: nothing is checked."""
    return averaging.tree_mean(values, pos, n_jobs)


def chunked_leaves(leaves_of: Any, X: np.ndarray, chunk: int = LOOKUP_CHUNK) -> np.ndarray:
    """``leaves_of(X) -> (len(X), n_trees)`` in row chunks (bounded temporaries)."""
    first = leaves_of(X[:chunk])
    if len(X) <= chunk:
        return first
    out = np.empty((len(X), first.shape[1]), first.dtype)
    out[:chunk] = first
    for lo in range(chunk, len(X), chunk):
        out[lo:lo + chunk] = leaves_of(X[lo:lo + chunk])
    return out


def per_tree_leaves(leaves_of: Any) -> Any:
    """A per-tree lookup ``prepare(X)`` from a whole-ensemble lookup ``leaves_of(X) ->
    (len(X), n_trees)``: ``prepare(X)`` returns ``leaves(t)``, the global leaf id of every
    row of ``X`` in tree ``t`` (int64), safe to call from several threads."""
    def prepare(X: np.ndarray) -> Any:
        full = chunked_leaves(leaves_of, X)
        return lambda t: np.array(full[:, t], dtype=np.int64)  # a copy: the caller may change it
    return prepare


def compiled_per_tree_leaves(trees: list[Any], roots: np.ndarray) -> Any:
    """A per-tree lookup (as :func:`per_tree_leaves`) for compiled scikit-learn ``Tree``
    objects: ``prepare(X)`` looks ``X`` up in the first tree; ``leaves(t)`` is tree ``t``'s
    ``apply`` on float32 inputs (scikit-learn releases the GIL in it: trees can be looked up
    in threads, each independent of the others), one tree at a time (no (rows, trees)
    matrix); ``roots``: each tree's first global node id."""
    def prepare(X: np.ndarray) -> Any:
        X32 = np.ascontiguousarray(X, dtype=np.float32)
        first = np.asarray(trees[0].apply(X32), dtype=np.int64)
        # rows in the order of their leaf in the first tree (depth-first ids): neighbours
        # in space descend the other trees together, so their nodes stay in cache
        # (less CPU on large lookups into deep trees; docs/fqi-modes.md)
        order = np.argsort(first, kind="stable") if len(trees) > 1 else None
        Xs = np.ascontiguousarray(X32[order]) if order is not None else None
        del X32

        def leaves(t: int) -> np.ndarray:
            if t == 0:
                return first + int(roots[0])
            out = np.empty(len(first), np.int64)
            out[order] = trees[t].apply(Xs)
            out += int(roots[t])
            return out
        return leaves
    return prepare


def ensemble_per_tree_leaves(ens: TreeEnsemble, probe: np.ndarray) -> Any:
    """A per-tree lookup for a structure held as arrays: scikit-learn's compiled trees
    rebuilt from the arrays, tree by tree, after checking that every feature a split reads
    is among the inputs (``probe``: one input row, 2-d); the numpy traversal where they
    cannot be rebuilt."""
    ens.check_inputs(probe)  # before any compiled lookup
    trees = ens.compiled_trees()
    return per_tree_leaves(ens.apply) if trees is None else compiled_per_tree_leaves(trees, np.asarray(ens.roots))
