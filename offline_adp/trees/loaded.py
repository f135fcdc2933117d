"""A :class:`~offline_adp.trees.ensemble.TreeEnsemble` held as its per-tree lookups
(:class:`~offline_adp.trees.compact.CompactTree`, about 28 bytes a node) and its node values, the
per-node ``left, right, feature, threshold`` arrays (40 bytes a node as int64/float64) made
from the lookups only when first read (re-saving, resuming, export): :class:`LoadedEnsemble`.

An artifact's ensembles are read into it (:func:`~offline_adp.artifacts.tree_tables.load_compact_ensemble`),
and so is the frozen LEARN step's structure grown by the compiled builder when its Q is
asked for (:meth:`~offline_adp.learn.frozen.FrozenTreesLearner._exported`). The lookups are
the ones :meth:`TreeEnsemble.compiled_trees` would build from the per-node arrays, and the
per-node arrays the ones :func:`~offline_adp.trees.sklearn.tree_arrays` exports from the
lookups, so predictions and saved files are the same bit for bit.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.trees.compact import CompactTree
from offline_adp.trees.ensemble import TreeEnsemble
from offline_adp.trees.sklearn import tree_arrays


class _Structure:
    """One decoded tree structure: its per-tree lookups and, made from them when first
    asked for, its per-node arrays (shared by every ensemble over the structure)."""

    def __init__(self, trees: list[CompactTree]) -> None:
        self.trees = trees
        self._arrays: dict[str, np.ndarray] | None = None

    def arrays(self) -> dict[str, np.ndarray]:
        if self._arrays is None:
            a = tree_arrays(self.trees)  # the lookups read like scikit-learn trees
            self._arrays = {k: a[k] for k in ("left", "right", "feature", "threshold")}
        return self._arrays


class _PerNode:
    """A per-node array of :class:`LoadedEnsemble` made from its structure's lookups when
    first read (assigned ones are kept as they are)."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        if obj is None:
            return self
        d = obj.__dict__
        if self.name not in d:
            d[self.name] = obj._structure.arrays()[self.name]
        return d[self.name]

    def __set__(self, obj: Any, value: Any) -> None:
        obj.__dict__[self.name] = value


class LoadedEnsemble(TreeEnsemble):
    """A :class:`TreeEnsemble` read from an artifact: ``value`` and ``roots`` as arrays,
    the compiled lookups built, and ``left, right, feature, threshold`` made from the
    lookups when first read (re-saving, resuming, export): scoring never makes them."""

    left = _PerNode()
    right = _PerNode()
    feature = _PerNode()
    threshold = _PerNode()

    def __init__(self, structure: _Structure, value: np.ndarray, roots: np.ndarray, n_features: int) -> None:
        self._structure = structure
        self.value, self.roots = value, roots
        self._trees = structure.trees  # TreeEnsemble.compiled_trees' cache: the lookups are built
        self._n_features = n_features  # TreeEnsemble.check_inputs' cache: the widest split feature + 1

    def with_values(self, value: np.ndarray) -> TreeEnsemble:
        """As :meth:`TreeEnsemble.with_values` (the same structure and lookups), without
        making the per-node arrays."""
        out = LoadedEnsemble(self._structure, np.asarray(value, dtype=np.float64), self.roots, self._n_features)
        if getattr(self, "_same_structure", None) is None:
            self._same_structure: dict[str, Any] = {}
        out._same_structure = self._same_structure
        if getattr(self, "n_features_in_", None) is not None:
            out.n_features_in_ = self.n_features_in_  # type: ignore[attr-defined]
        return out

    def leaf_mask(self) -> np.ndarray:
        """Which nodes are leaves (without making the per-node arrays)."""
        return np.concatenate([t.children_left < 0 for t in self._structure.trees])


def compact_ensemble(trees: list[CompactTree]) -> LoadedEnsemble:
    """The ensemble of ``trees`` (each tree's local node ids), held as the trees themselves:
    node values and roots as :func:`~offline_adp.trees.sklearn.tree_arrays` exports them,
    no per-node arrays until asked for. Each tree's values become a view of the ensemble's
    (one copy, not two: 8 bytes a node)."""
    sizes = np.array([t.node_count for t in trees], dtype=np.int64)
    roots = np.r_[0, np.cumsum(sizes)[:-1]].astype(np.int64)
    value = np.concatenate([np.asarray(t.value[:, 0, 0], dtype=np.float64) for t in trees])
    for t, lo, k in zip(trees, roots, sizes, strict=True):
        t.values = value[lo:lo + k]
    width = max((int(t.feature[t.children_left >= 0].max()) + 1 for t in trees if (t.children_left >= 0).any()),
                default=0)
    return LoadedEnsemble(_Structure(trees), value, roots, width)
