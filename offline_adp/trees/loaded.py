"""A :class:`~offline_adp.trees.ensemble.TreeEnsemble` held as its leaf lookups and node
values, the per-node ``left, right, feature, threshold`` arrays (40 bytes a node as
int64/float64) made only when first read (re-saving, resuming, export): :class:`LoadedEnsemble`.

An artifact's ensembles are read into it (:func:`~offline_adp.artifacts.tree_tables.load_compact_ensemble`)
as one lookup record a node (left and right child as local ids, feature, the threshold's
float32 floor: 16 bytes; the layout of :class:`~offline_adp.trees.compact.CompactTree`'s
``packed``) and the splits' float64 thresholds. A few states are looked up by numpy
descents of the records; the per-tree compiled lookups are :class:`CompactTree` views of the
same records, made when lookups grow (:meth:`_Structure.use_compiled`), so loading a policy
imports no numba and holds the structure once either way. The frozen LEARN step's
structure grown by the compiled builder is held as its :class:`CompactTree` lookups
(:func:`compact_ensemble`, :meth:`~offline_adp.learn.frozen.FrozenTreesLearner._exported`).
Every path reaches the leaves :meth:`TreeEnsemble.compiled_trees` would reach from the
per-node arrays, and the per-node arrays are the ones
:func:`~offline_adp.trees.sklearn.tree_arrays` exports from the lookups, so predictions and
saved files are the same bit for bit.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from offline_adp.trees import jit
from offline_adp.trees.compact import CompactTree
from offline_adp.trees.ensemble import SharedCache, TreeEnsemble, descend
from offline_adp.trees.sklearn import tree_arrays


class _Structure:
    """One tree structure: its per-tree compiled lookups (:class:`CompactTree`) and, made
    when first asked for, its per-node arrays (shared by every ensemble over the structure).

    A structure read from a file is its node records instead (``records``, (n, 4) int32,
    local child ids; ``split_thresholds``: the splits' float64 thresholds in node order;
    ``roots``): small lookups descend them with numpy (:meth:`numpy_leaves`), and the
    compiled lookups are views of them (:attr:`trees`), used once a lookup is large or many
    were made (:meth:`use_compiled`): numba's import and kernel set-up (about 0.6 CPU-s)
    is most of what loading a small policy and acting on a few states would cost. Both
    reach the same leaves, so every number is the same either way."""

    def __init__(self, trees: list[CompactTree] | None = None, records: np.ndarray | None = None,
                 split_thresholds: np.ndarray | None = None, roots: np.ndarray | None = None,
                 value: np.ndarray | None = None) -> None:
        self._trees = trees
        self.records, self.split_thresholds, self.roots, self.value = records, split_thresholds, roots, value
        self._arrays: dict[str, np.ndarray] | None = None
        self.numpy_seconds = 0.0
        self.deep = False  # a numpy descent outran NUMPY_PASSES levels: the compiled lookups from then on

    def __getstate__(self) -> dict[str, Any]:
        """Pickled (to Dask workers) without lookups that are views of the records: numpy
        would copy each view (the structure sent twice); they are made again on first use."""
        state = dict(self.__dict__)
        if self.records is not None:
            state["_trees"] = None
        return state

    @property
    def trees(self) -> list[CompactTree]:
        """The per-tree compiled lookups (views of ``records`` where read from a file; made
        on the first call, no numba needed)."""
        if self._trees is None:
            rec = self.records
            bounds = np.r_[self.roots, len(rec)]  # type: ignore[arg-type]
            splits = np.r_[0, np.cumsum(np.add.reduceat(rec[:, 0] >= 0, self.roots, dtype=np.int64))]  # type: ignore
            self._trees = [CompactTree.of_records(rec[lo:hi], self.split_thresholds[a:b],  # type: ignore[index]
                                                  self.value[lo:hi])  # type: ignore[index]
                           for lo, hi, a, b in zip(bounds[:-1], bounds[1:], splits[:-1], splits[1:], strict=True)]
        return self._trees

    def use_compiled(self, pairs: int) -> bool:
        """Whether a lookup of ``pairs`` (row, tree) pairs goes through the compiled lookups:
        always once they are built or numba is imported in this process, for a large lookup
        (more than :data:`NUMPY_PAIRS`), and after :data:`NUMPY_SECONDS` of numpy lookups on
        this structure (a loop of small lookups), and for every lookup once a numpy descent
        of it outran :data:`NUMPY_PASSES` levels; never where numba does not import."""
        if self._trees is not None or self.deep:
            return True
        if not (jit.warm() or pairs > NUMPY_PAIRS or self.numpy_seconds > NUMPY_SECONDS):
            return False
        return jit.available()  # (imports numba: it is about to be used)

    def numpy_leaves(self, X: np.ndarray) -> np.ndarray | None:
        """The global leaf each row of ``X`` (every feature a split reads present, checked
        by the caller) reaches in every tree, (n, n_trees) int64: all (row, tree) pairs
        descend together a level per pass, comparing the float32 input with the float32
        floor of the threshold as :class:`CompactTree` does (the same leaves). None where
        a pair is deeper than :data:`NUMPY_PASSES` levels and numba imports: this structure
        then uses the compiled lookups (``deep``), which cost a step per level, not a pass."""
        t0 = time.thread_time()
        rec = self.records
        args = (rec[:, 0], rec[:, 1], rec[:, 2], rec[:, 3].view(np.float32), self.roots,  # type: ignore[index]
                np.ascontiguousarray(X, dtype=np.float32))
        out = descend(*args, local=True, max_passes=NUMPY_PASSES)
        if out is None and jit.available():
            self.deep = True
        elif out is None:  # no compiled lookups here: descend on
            out = descend(*args, local=True)
        self.numpy_seconds += time.thread_time() - t0
        return out

    def arrays(self) -> dict[str, np.ndarray]:
        if self._arrays is None:
            if self.records is not None:  # straight from the node records (what the lookups export)
                rec = self.records
                inner = rec[:, 0] >= 0
                root = np.repeat(np.asarray(self.roots, dtype=np.int64), np.diff(np.r_[self.roots, len(rec)]))
                thr = np.full(len(rec), -2.0)
                thr[inner] = self.split_thresholds
                self._arrays = {"left": np.where(inner, rec[:, 0] + root, -1),
                                "right": np.where(inner, rec[:, 1] + root, -1),
                                "feature": rec[:, 2].astype(np.int64), "threshold": thr}
            else:
                a = tree_arrays(self._trees)  # the lookups read like scikit-learn trees
                self._arrays = {k: a[k] for k in ("left", "right", "feature", "threshold")}
        return self._arrays


#: a lookup of more (row, tree) pairs than this uses the compiled lookups (numpy's descent
#: costs about 2.5x a compiled one's on 1,000 rows of 50 deep trees)
NUMPY_PAIRS = 2**17
#: CPU seconds (of the looking-up threads) of numpy lookups on one structure after which
#: the compiled ones are used
NUMPY_SECONDS = 0.5
#: levels a numpy descent goes down before it hands a deeper structure to the compiled
#: lookups (grown trees are 20-60 deep; a crafted chain may be millions)
NUMPY_PASSES = 256


class _PerNode:
    """A per-node array of :class:`LoadedEnsemble` made from its structure's records or
    lookups when first read (assigned ones are kept as they are)."""

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
    """A :class:`TreeEnsemble` read from an artifact (or a frozen fit's structure): ``value``
    and ``roots`` as arrays, leaves looked up through its :class:`_Structure` (numpy
    descents of the node records or the compiled lookups, the same leaves), and ``left,
    right, feature, threshold`` made when first read (re-saving, resuming, export):
    scoring never makes them."""

    left = _PerNode()
    right = _PerNode()
    feature = _PerNode()
    threshold = _PerNode()

    def __init__(self, structure: _Structure, value: np.ndarray, roots: np.ndarray, n_features: int) -> None:
        self._structure = structure
        self.value, self.roots = value, roots
        self._n_features = n_features  # TreeEnsemble.check_inputs' cache: the widest split feature + 1

    def with_values(self, value: np.ndarray) -> TreeEnsemble:
        """As :meth:`TreeEnsemble.with_values` (the same structure and lookups), without
        making the per-node arrays."""
        out = LoadedEnsemble(self._structure, np.asarray(value, dtype=np.float64), self.roots, self._n_features)
        if getattr(self, "_same_structure", None) is None:
            self._same_structure: dict[str, Any] = SharedCache()
        out._same_structure = self._same_structure
        if getattr(self, "n_features_in_", None) is not None:
            out.n_features_in_ = self.n_features_in_  # type: ignore[attr-defined]
        return out

    def compiled_trees(self) -> list[Any] | None:
        """The structure's compiled lookups (built on the first call where read from a file)."""
        if self._structure.records is not None and not jit.available():
            return None  # the numpy descent (TreeEnsemble.apply's without lookups)
        return self._structure.trees

    def apply(self, X: np.ndarray) -> np.ndarray:
        """As :meth:`TreeEnsemble.apply`: by numpy descents of the node records while
        :meth:`_Structure.use_compiled` says so, else by the compiled lookups."""
        s = self._structure
        if s.records is not None and not s.use_compiled(len(X) * self.n_trees):
            self.check_inputs(X)
            out = s.numpy_leaves(X)
            if out is not None:
                return out
        return super().apply(X)

    def lookup_compiled(self, pairs: int) -> bool:
        """Whether a lookup of ``pairs`` (row, tree) pairs would use the compiled lookups."""
        return self._structure.records is None or self._structure.use_compiled(pairs)

    def leaf_mask(self) -> np.ndarray:
        """Which nodes are leaves (without making the per-node arrays)."""
        s = self._structure
        if s.records is not None:
            return s.records[:, 0] < 0
        return np.concatenate([t.children_left < 0 for t in s.trees])


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
