"""Tree ensembles read from the compact layout straight into their leaf lookups.

A saved ensemble (:meth:`~offline_adp.trees.ensemble.TreeEnsemble.to_arrays`, artifact
format 2) stores each tree's leaf flags in depth-first order, the splits' features and
thresholds, and the leaves' values. Scoring needs only the per-tree lookups
(:class:`~offline_adp.trees.compact.CompactTree`, 32 bytes a node) and the leaf values;
the per-node ``left, right, feature, threshold`` arrays a :class:`TreeEnsemble` holds (40
bytes a node as int64/float64) serve re-saving, resuming and export only. So
:func:`load_compact_ensemble` checks the members (:func:`~offline_adp.artifacts.checks.compact_tree_members`),
finds every split's children in one vectorised pass (:func:`preorder_children`), builds
the lookups tree by tree, and returns a :class:`LoadedEnsemble` whose per-node arrays are
made from the lookups when first read. The lookups are those
:meth:`TreeEnsemble.compiled_trees` would build from the per-node arrays (the same
numbers), so predictions are the same bit for bit.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.artifacts import checks as C
from offline_adp.errors import ArtifactError
from offline_adp.trees import builder
from offline_adp.trees.compact import CompactTree
from offline_adp.trees.ensemble import TreeEnsemble
from offline_adp.trees.sklearn import tree_arrays


def preorder_children(is_leaf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The splits (global ids, ascending) and their right children of trees numbered
    depth-first whose leaf flags passed :func:`~offline_adp.trees.ensemble.preorder_valid`
    (a split's left child is the next node).

    With ``e[j]`` the count (+1 a leaf, -1 a split) of the nodes before ``j``, a split's
    left subtree holds counts below ``e[j]`` and ends where the count is back at ``e[j]``:
    the right child is the next node after ``j`` whose ``e`` equals ``e[j]``, its
    successor in a stable sort of the nodes by ``e`` (a radix sort: ``e`` spans about the
    trees' depth plus their number). The caller checks each child inside its tree."""
    n = len(is_leaf)
    step = is_leaf.view(np.int8) * np.int8(2) - np.int8(1)
    small = n < 2**31 - 1
    e = np.cumsum(step, dtype=np.int32 if small else np.int64)
    e -= step
    del step
    lo = int(e.min())
    key = (e - lo).astype(np.int16) if int(e.max()) - lo < 2**15 else e
    del e
    order = np.argsort(key, kind="stable")
    del key
    rank = np.empty(n, np.int32 if small else np.int64)
    rank[order] = np.arange(n, dtype=rank.dtype)
    splits = np.flatnonzero(~is_leaf)
    nxt = rank[splits].astype(np.int64)
    del rank
    nxt += 1
    np.minimum(nxt, n - 1, out=nxt)  # the last node has no successor (it is a leaf in trees that passed)
    return splits, order[nxt]


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

    def __init__(self, structure: _Structure, value: np.ndarray, roots: np.ndarray, n_features: int) -> None:  # noqa: D107
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


def load_compact_ensemble(arrays: Any, prefix: str, where: str, n_features: int | None = None,
                          structure_prefix: str | None = None) -> TreeEnsemble:
    """The compact-layout ensemble under ``prefix`` (structure under ``structure_prefix``
    when shared), every member checked as :func:`~offline_adp.artifacts.checks.check_compact_tree_arrays`
    checks it: a :class:`LoadedEnsemble` with its lookups built where the compiled lookups
    run (numba), else a :class:`TreeEnsemble` of per-node arrays (scikit-learn's trees are
    then rebuilt from them on first use)."""
    sp = prefix if structure_prefix is None else structure_prefix
    is_leaf, roots, feature, threshold, values = C.compact_tree_members(arrays, prefix, where, n_features, structure_prefix)
    n = len(is_leaf)
    splits, right = preorder_children(is_leaf)
    value = np.zeros(n)
    value[is_leaf] = values
    width = int(feature.max()) + 1 if len(feature) else 0
    if not builder.available():  # per-node arrays for scikit-learn's trees (or the numpy traversal)
        left_g, right_g = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
        left_g[splits], right_g[splits] = splits + 1, right
        f, t = np.full(n, -2, np.int64), np.full(n, -2.0)
        f[splits], t[splits] = feature, threshold
        C.tree_structure(left_g, right_g, roots, where, sp)  # scikit-learn's compiled trees read children unchecked
        return TreeEnsemble(left_g, right_g, f, t, value, roots)
    thr = np.asarray(threshold, dtype=np.float64)  # CompactTree compares with its float32 floor: a stored float32 itself
    bounds = np.r_[roots, n]
    cut = np.searchsorted(splits, bounds)  # tree m's splits: splits[cut[m]:cut[m + 1]]
    trees = []
    for m in range(len(roots)):  # tree by tree (vectorised within each)
        lo, hi, a, b = int(bounds[m]), int(bounds[m + 1]), int(cut[m]), int(cut[m + 1])
        s, r = splits[a:b] - lo, right[a:b] - lo
        if len(s) and (np.any(r <= s + 1) or int(r.max()) >= hi - lo):  # the lookup reads children unchecked
            raise ArtifactError(f"{where}: {sp}leaf_bits: tree {m}: a right child outside its split's tree")
        left_l, right_l = np.full(hi - lo, -1, np.int32), np.full(hi - lo, -1, np.int32)
        left_l[s], right_l[s] = s + 1, r
        f_l, t_l = np.full(hi - lo, -2, np.int32), np.full(hi - lo, -2.0)
        f_l[s], t_l[s] = feature[a:b], thr[a:b]
        trees.append(CompactTree(left_l, right_l, f_l, t_l, value[lo:hi]))
    return LoadedEnsemble(_Structure(trees), value, roots, width)


def load_ensemble(arrays: Any, prefix: str, where: str, n_features: int | None = None) -> TreeEnsemble:
    """The ensemble under ``prefix`` in either layout: compact (:func:`load_compact_ensemble`)
    or per-node arrays (artifact format 1, :func:`~offline_adp.artifacts.checks.check_tree_arrays`)."""
    if prefix + "leaf_bits" in C._members(arrays):
        return load_compact_ensemble(arrays, prefix, where, n_features)
    return TreeEnsemble(**C.check_tree_arrays(arrays, prefix, where, n_features))
