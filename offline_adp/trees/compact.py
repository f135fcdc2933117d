"""Grown trees held for leaf lookups in about 28 bytes a node (:class:`CompactTree`) and their
compiled lookup (a nogil numba kernel, so trees are looked up in threads); used by the
frozen LEARN step (:mod:`offline_adp.learn.frozen`) and :class:`~offline_adp.trees.ensemble.TreeEnsemble`."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from offline_adp.errors import InvalidArgumentError
from offline_adp.trees.jit import kernel

if TYPE_CHECKING:
    from offline_adp.trees.builder import GrownTree

_UNDEFINED = -2.0  #: scikit-learn's threshold at a leaf (TREE_UNDEFINED)


class CompactTree:
    """A grown tree held for leaf lookups in about 28 bytes a node (scikit-learn's ``Tree``: 72):
    a packed lookup record per node (left, right, feature as int32 and the threshold as
    the largest float32 not above it, 16 bytes: four nodes a cache line) plus the float64
    values and the splits' float64 thresholds for the export (a leaf's threshold, -2,
    not held). For float32 inputs ``x <= threshold`` and
    ``x <= float32-floor(threshold)`` are the same test, so :meth:`apply` reaches the leaf
    scikit-learn's ``apply`` reaches. It reads like a ``Tree`` where
    :func:`~offline_adp.trees.sklearn.tree_arrays` reads one (``node_count``,
    ``children_left``, ``children_right``, ``feature``, ``threshold``, ``value``)."""

    def __init__(self, left: np.ndarray, right: np.ndarray, feature: np.ndarray, threshold: np.ndarray,
                 value: np.ndarray) -> None:
        """From one tree's arrays (local node ids; leaves: children -1), copied."""
        n = len(left)
        if n >= 2**31 - 1:
            raise InvalidArgumentError(f"a tree of {n} nodes does not fit int32 node ids")
        thr = np.array(threshold, dtype=np.float64)
        t32 = thr.astype(np.float32)
        above = t32.astype(np.float64) > thr
        t32[above] = np.nextafter(t32[above], np.float32(-np.inf))
        pk = np.empty((n, 4), np.int32)
        pk[:, 0], pk[:, 1], pk[:, 2] = left, right, feature
        pk[:, 3] = t32.view(np.int32)
        self.packed, self.values = pk, np.array(value, dtype=np.float64)
        # read only by the export: a leaf's is scikit-learn's -2 (every builder's and decoder's
        # trees), so the splits' only are held where that is so (8 bytes a split, not a node)
        leaf = pk[:, 0] < 0
        self._leaf_undefined = bool((thr[leaf] == _UNDEFINED).all())
        self._thresholds = thr[~leaf] if self._leaf_undefined else thr

    @classmethod
    def of_records(cls, records: np.ndarray, split_thresholds: np.ndarray, values: np.ndarray) -> CompactTree:
        """A tree over its node records as :attr:`packed` holds them ((n, 4) int32, local
        ids, leaves: left -1, feature -2, threshold -2.0; C order), its splits' float64
        thresholds in node order and its node values, held as given (views, not copies)."""
        tree = cls.__new__(cls)
        tree.packed, tree.values = records, values
        tree._leaf_undefined, tree._thresholds = True, split_thresholds
        return tree

    @classmethod
    def from_grown(cls, tree: GrownTree) -> CompactTree:
        """From the builder's node records (copied: the builder reuses its buffers)."""
        return cls(tree.left, tree.right, tree.feature, tree.threshold, tree.value)

    @property
    def node_count(self) -> int:
        return len(self.packed)

    @property
    def children_left(self) -> np.ndarray:
        return self.packed[:, 0]

    @property
    def children_right(self) -> np.ndarray:
        return self.packed[:, 1]

    @property
    def feature(self) -> np.ndarray:
        return self.packed[:, 2]

    @property
    def thresholds(self) -> np.ndarray:
        """The float64 thresholds of every node (a leaf's: -2), as given."""
        if not self._leaf_undefined:
            return self._thresholds
        out = np.full(self.node_count, _UNDEFINED)
        out[self.packed[:, 0] >= 0] = self._thresholds
        return out

    @property
    def threshold(self) -> np.ndarray:
        return self.thresholds

    @property
    def value(self) -> np.ndarray:
        return self.values.reshape(-1, 1, 1)

    def apply(self, X32: np.ndarray) -> np.ndarray:
        """Each row's leaf (local node id, int64) for C-contiguous float32 inputs with every
        feature the tree reads (unchecked); releases the GIL (trees in threads)."""
        out = np.empty(len(X32), np.int64)
        if self.node_count:
            flat = self.packed.reshape(-1)
            _apply(flat, flat.view(np.float32), np.ascontiguousarray(X32, dtype=np.float32), out)
        return out


def _apply(packed: Any, packed_f: Any, X: Any, out: Any) -> None:
    """Descend every row of ``X`` (float32, C order) to its leaf: ``packed`` is the flat
    (left, right, feature, -) int32 records, ``packed_f`` the same memory as float32 (slot 3:
    the threshold); left < 0 at a leaf. Unsigned indices: no negative-index wraparound
    test on the hot path."""
    n, d = X.shape
    flat = X.reshape(n * d)
    four, two, three = np.uint64(4), np.uint64(2), np.uint64(3)
    for i in range(n):
        row = np.uint64(i) * np.uint64(d)
        node = np.uint64(0)
        while True:
            base = node * four
            left = packed[base]
            if left < 0:
                break
            if flat[row + np.uint64(packed[base + two])] <= packed_f[base + three]:
                node = np.uint64(left)
            else:
                node = np.uint64(packed[base + np.uint64(1)])
        out[i] = node


_apply = kernel(_apply, cache=True, nogil=True, boundscheck=False)
