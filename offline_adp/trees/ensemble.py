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

from offline_adp.errors import ArtifactError, InvalidArgumentError
from offline_adp.trees import averaging, jit
from offline_adp.trees.compact import CompactTree
from offline_adp.trees.sklearn import forest_trees, sklearn_leaves, sklearn_tree, tree_arrays

#: rows per chunk of a whole-ensemble leaf lookup (bounded temporaries)
LOOKUP_CHUNK = 262_144


#: derived copies an ensemble caches that pickling leaves out (made again on first use):
#: the pair descents' node records (trees.pairs), 16 bytes a node
_UNPICKLED = ("pair_packed",)


class SharedCache(dict):
    """What the ensembles of one structure (:meth:`TreeEnsemble.with_values`) share: one
    object when pickled with them, without the keys of ``_UNPICKLED``."""

    def __reduce__(self) -> tuple[Any, ...]:
        return (SharedCache, (), None, None, iter([(k, v) for k, v in self.items() if k not in _UNPICKLED]))


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
        out = descend(self.left, self.right, self.feature, self.threshold, self.roots,
                      np.asarray(X, dtype=np.float32).astype(np.float64))
        assert out is not None  # (no max_passes)
        return out

    def check_inputs(self, X: np.ndarray) -> None:
        """Raise ArtifactError unless ``X`` is 2-d and has every feature a split reads:
        compiled trees read ``X[:, feature]`` unchecked, so call this before using them."""
        need = getattr(self, "_n_features", None)
        if need is None:
            inner = self.left >= 0
            need = self._n_features = int(self.feature[inner].max()) + 1 if inner.any() else 0  # type: ignore[attr-defined]
        if np.ndim(X) != 2 or np.shape(X)[1] < need:
            raise ArtifactError(f"tree ensemble splits on feature {need - 1}, the input has shape {np.shape(X)}")

    def __getstate__(self) -> dict[str, Any]:
        """Pickled without the derived copies of ``_UNPICKLED`` (a Dask worker makes its own)."""
        return {k: v for k, v in self.__dict__.items() if k not in _UNPICKLED}

    def compiled_trees(self) -> list[Any] | None:
        """Compiled per-tree lookups rebuilt from our arrays (plain numbers, no code from any
        file): :class:`~offline_adp.trees.compact.CompactTree` where numba is installed (the
        leaves scikit-learn's ``apply`` reaches, in about 28 bytes a node), else scikit-learn
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
        compact = jit.available()  # about 28 bytes a node and a lookup in threads (scikit-learn's: 72)
        for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
            leaf = self.left[lo:hi] < 0
            if compact:
                trees.append(CompactTree(np.where(leaf, -1, self.left[lo:hi] - lo),
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

    def lookup_compiled(self, pairs: int) -> bool:
        """Whether a lookup of ``pairs`` (row, tree) pairs would use compiled lookups (numba's)."""
        return jit.available()

    def predict(self, X: np.ndarray) -> np.ndarray:
        """The mean over trees of the reached leaf values, in row chunks of
        :data:`LOOKUP_CHUNK` (each row's mean is summed alone, so the numbers do not depend
        on the chunks): the (rows, trees) leaf and value matrices of a whole query set are
        never held (2M pairs of a 50-tree policy: 1.6 GB)."""
        if len(X) <= LOOKUP_CHUNK:
            return ensemble_predict(self.value, self.apply(X))
        out = np.empty(len(X))
        for lo in range(0, len(X), LOOKUP_CHUNK):
            out[lo:lo + LOOKUP_CHUNK] = ensemble_predict(self.value, self.apply(X[lo:lo + LOOKUP_CHUNK]))
        return out

    def with_values(self, value: np.ndarray) -> TreeEnsemble:
        """The same structure with other leaf values. The structure's compiled lookup is
        shared with every ensemble made this way, now or when first built: a
        finite-horizon fit's per-step snapshots of one structure need one compiled copy,
        not one per step (the lookup reads no value; sizes in docs/fqi-modes.md)."""
        out = TreeEnsemble(self.left, self.right, self.feature, self.threshold, np.asarray(value, dtype=np.float64),
                           self.roots)
        if getattr(self, "_same_structure", None) is None:
            self._same_structure = SharedCache()  # type: ignore[attr-defined]
        out._same_structure = self._same_structure  # type: ignore[attr-defined]
        for k in ("_forest", "_trees", "_n_features", "n_features_in_"):  # same structure: same leaf lookup
            if getattr(self, k, None) is not None:
                setattr(out, k, getattr(self, k))
        return out

    def to_arrays(self, prefix: str = "", layout: str = "compact", structure: bool = True) -> dict[str, np.ndarray]:
        """The arrays to store, in one of two layouts (both read by the artifact loader).

        ``"compact"`` stores what a prediction reads, about 3-6 bytes a node instead of
        26, with each tree's nodes renumbered depth-first, left subtree first (the
        leaves reached and the predictions are the same; only the node ids change):
        ``roots``; ``leaf_bits`` (the leaf flags in that order, ``np.packbits``: they
        give every child, :func:`preorder_children`); the split nodes' ``feature`` (the
        smallest unsigned type) and ``threshold`` as float32, each rounded down to a
        float32 (inputs are compared as float32 with ``x <= threshold``: the largest
        float32 not above the double threshold sends every float32 the same way, so the
        leaves reached are the same bit for bit); the leaves' values in float64, as
        ``value`` or, when fewer distinct values than leaves makes it smaller,
        ``value_table`` (the distinct values) and ``value_code`` (each leaf's index into
        it). ``structure=False`` writes only the leaf values (an ensemble sharing
        another's structure, :meth:`with_values`).

        ``"nodes"``: per-node ``left, right, feature, threshold, value, roots`` (node
        indices as int32 when they fit), the format of artifact version 1.
        """
        if layout == "nodes":
            out = {prefix + k: np.asarray(getattr(self, k)) for k in ("threshold", "value")}
            small = len(self.left) < 2**31 - 1
            for k in ("left", "right", "roots"):
                a = np.asarray(getattr(self, k))
                out[prefix + k] = a.astype(np.int32) if small else a
            f = np.asarray(self.feature)
            out[prefix + "feature"] = f.astype(np.int16) if len(f) == 0 or f.max() < 2**15 - 1 else f
            return out
        if layout != "compact":
            raise InvalidArgumentError(f"unknown tree layout {layout!r}")
        left, right, roots = (np.asarray(a, dtype=np.int64) for a in (self.left, self.right, self.roots))
        pos = preorder_positions(left, right, roots)
        if len(pos) == 0 or np.bincount(pos, minlength=len(pos)).max() != 1 or not np.array_equal(pos[roots], roots):
            return self.to_arrays(prefix, "nodes")  # not trees each spanning its range: stored node by node

        def renumbered(a: np.ndarray) -> np.ndarray:
            out = np.empty_like(a)
            out[pos] = a
            return out

        is_leaf = renumbered(left < 0)
        out = _leaf_value_arrays(renumbered(np.asarray(self.value, dtype=np.float64))[is_leaf], prefix)
        if not structure:
            return out
        inner = ~is_leaf
        out[prefix + "roots"] = roots.astype(np.int32) if len(is_leaf) < 2**31 - 1 else roots.astype(np.int64)
        out[prefix + "leaf_bits"] = np.packbits(is_leaf)
        f = renumbered(np.asarray(self.feature))[inner]
        top = int(f.max()) if len(f) else 0
        out[prefix + "feature"] = f.astype(next(t for t in (np.uint8, np.uint16, np.uint32, np.int64)
                                                if top <= np.iinfo(t).max))
        t = renumbered(np.asarray(self.threshold, dtype=np.float64))[inner]
        t32 = float32_floor(t)
        out[prefix + "threshold"] = t32 if np.all(np.isfinite(t32) == np.isfinite(t)) else t
        return out

    @classmethod
    def from_arrays(cls, arrays: Any, prefix: str = "", structure_prefix: str | None = None) -> TreeEnsemble:
        """Rebuild from trusted arrays of either layout (:meth:`to_arrays`); untrusted files
        go through :func:`offline_adp.artifacts.checks.check_tree_arrays`."""
        sp = prefix if structure_prefix is None else structure_prefix
        if sp + "leaf_bits" not in arrays:
            return cls(**{k: np.asarray(arrays[prefix + k]) for k in ("left", "right", "feature", "threshold", "value",
                                                                      "roots")})
        values = leaf_values_of(arrays, prefix)
        feature, threshold = np.asarray(arrays[sp + "feature"]), np.asarray(arrays[sp + "threshold"])
        n = len(feature) + len(values)
        is_leaf = np.unpackbits(np.asarray(arrays[sp + "leaf_bits"]), count=n).astype(bool)
        return cls(**expand_compact(is_leaf, np.asarray(arrays[sp + "roots"]), feature, threshold, values))


def preorder_positions(left: np.ndarray, right: np.ndarray, roots: np.ndarray) -> np.ndarray:
    """Each node's index when every tree is numbered depth-first, left subtree first,
    within the tree's own range (trusted trees: each reaches exactly its range). One
    vectorised pass per tree level: depths top-down, subtree sizes bottom-up, positions
    top-down (a left child follows its parent, a right child follows the left subtree)."""
    levels = []
    frontier = np.asarray(roots, dtype=np.int64)
    while len(frontier):
        levels.append(frontier)
        inner = frontier[left[frontier] >= 0]
        frontier = np.concatenate([left[inner], right[inner]])
    size = np.ones(len(left), np.int64)
    for lev in reversed(levels):
        inner = lev[left[lev] >= 0]
        size[inner] += size[left[inner]] + size[right[inner]]
    pos = np.empty(len(left), np.int64)
    pos[roots] = roots
    for lev in levels:
        inner = lev[left[lev] >= 0]
        pos[left[inner]] = pos[inner] + 1
        pos[right[inner]] = pos[inner] + 1 + size[left[inner]]
    return pos


def descend(left: np.ndarray, right: np.ndarray, feature: np.ndarray, threshold: np.ndarray, roots: np.ndarray,
            X: np.ndarray, local: bool = False, max_passes: int | None = None) -> np.ndarray | None:
    """The global leaf each row of ``X`` reaches in every tree, (n, n_trees) int64, by numpy:
    all (row, tree) pairs descend together, one level per pass (``x <= threshold``: left;
    a leaf's left child is negative), finished pairs dropping out. ``X`` is compared as
    given with ``threshold`` (the caller picks the precision); ``local``: children are
    numbered from their tree's root (node records), else globally. Every feature a split
    reads must be a column of ``X`` (checked by the caller). ``max_passes``: None (no
    answer) if a pair is still descending after that many levels (each pass costs a few
    microseconds however few pairs remain: a file's million-deep chain would cost seconds)."""
    n, m = len(X), len(roots)
    base = np.tile(np.asarray(roots, dtype=np.int64), n)  # each pair's root, flat (n * m), row-major
    node = base.copy() if local else base
    row = np.repeat(np.arange(n), m)
    idx = np.flatnonzero(left[node] >= 0)
    passes = 0
    while len(idx):
        if max_passes is not None and passes == max_passes:
            return None
        passes += 1
        nd = node[idx]
        nxt = np.where(X[row[idx], feature[nd]] <= threshold[nd], left[nd], right[nd])
        node[idx] = nxt + base[idx] if local else nxt
        idx = idx[left[node[idx]] >= 0]
    return node.reshape(n, m)


def float32_floor(t: np.ndarray) -> np.ndarray:
    """The largest float32 not above each double in ``t``: for every float32 ``x``,
    ``x <= t`` exactly when ``x <= float32_floor(t)`` (NaN stays NaN)."""
    with np.errstate(over="ignore"):  # (below -float32 max: -inf, by the cast or by nextafter)
        t32 = np.asarray(t, dtype=np.float64).astype(np.float32)
        up = t32.astype(np.float64) > t
        t32[up] = np.nextafter(t32[up], np.float32(-np.inf))
    return t32


def _leaf_value_arrays(values: np.ndarray, prefix: str) -> dict[str, np.ndarray]:
    """Leaf values as ``value``, or as ``value_table`` + ``value_code`` when that is smaller
    (values compared by their bits: -0.0 and 0.0 stay apart, every NaN kept as it was)."""
    bits = values.view(np.uint64)
    table_bits, code = np.unique(bits, return_inverse=True)
    k = len(table_bits)
    ctype = next(t for t in (np.uint8, np.uint16, np.uint32, np.uint64) if k - 1 <= np.iinfo(t).max)
    if k * 8 + len(values) * np.dtype(ctype).itemsize >= len(values) * 8:
        return {prefix + "value": values}
    return {prefix + "value_table": table_bits.view(np.float64), prefix + "value_code": code.reshape(-1).astype(ctype)}


def leaf_values_of(arrays: Any, prefix: str) -> np.ndarray:
    """The leaf values stored by :func:`_leaf_value_arrays` (trusted arrays)."""
    if prefix + "value" in arrays:
        return np.asarray(arrays[prefix + "value"], dtype=np.float64)
    return np.asarray(arrays[prefix + "value_table"], dtype=np.float64)[np.asarray(arrays[prefix + "value_code"])]


def preorder_valid(is_leaf: np.ndarray, roots: np.ndarray) -> bool:
    """Whether the leaf flags ``is_leaf``, cut at ``roots`` (strictly increasing from 0),
    are each a full binary tree's nodes in depth-first order: within a tree, counting +1 a
    leaf and -1 a split, every proper prefix sums to at most 0 and the whole tree to 1."""
    n = len(is_leaf)
    if n == 0 or len(roots) == 0 or roots[0] != 0 or np.any(np.diff(roots) <= 0) or roots[-1] >= n:
        return False
    c = np.cumsum(np.where(is_leaf, 1, -1), dtype=np.int64)
    base = np.r_[0, c[roots[1:] - 1]]  # the sum before each tree
    rel = c - np.repeat(base, np.diff(np.r_[roots, n]))
    last = np.r_[roots[1:] - 1, n - 1]
    ok = rel <= 0
    ok[last] = rel[last] == 1
    return bool(ok.all())


def preorder_children(is_leaf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Global child indices of trees numbered depth-first (leaf flags that pass
    :func:`preorder_valid`): a split's left child is the next node, its right child the
    node after its left subtree, which ends where the running count (+1 a leaf, -1 a
    split) first exceeds its value at the split by one. Leaves get -1."""
    n = len(is_leaf)
    c = np.cumsum(np.where(is_leaf, 1, -1), dtype=np.int64)
    inner = np.flatnonzero(~is_leaf)
    # positions sorted by (count, position), searched for the first position after j with
    # count c_j + 1; the counts span about the trees' depth plus their number, so a stable
    # sort of them as int16 (a radix sort) orders the positions (keys below 2**64 for n < 2**31)
    lo = int(c.min())
    span = int(c.max()) - lo
    order = np.argsort((c - lo).astype(np.int16) if span < 2**15 else c, kind="stable")
    m = np.uint64(n + 1)
    key = (c[order] - lo).astype(np.uint64) * m + order.astype(np.uint64)
    hit = key[np.searchsorted(key, (c[inner] + 1 - lo).astype(np.uint64) * m + (inner + 1).astype(np.uint64))]
    left = np.full(n, -1, np.int64)
    right = np.full(n, -1, np.int64)
    left[inner] = inner + 1
    right[inner] = (hit % m).astype(np.int64) + 1
    return left, right


def expand_compact(is_leaf: np.ndarray, roots: np.ndarray, feature: np.ndarray, threshold: np.ndarray,
                   values: np.ndarray) -> dict[str, np.ndarray]:
    """Per-node arrays (:class:`TreeEnsemble`'s fields) from the compact layout: leaves get
    feature -2 and threshold -2.0 (scikit-learn's marks), splits value 0.0 (never read)."""
    n = len(is_leaf)
    left, right = preorder_children(is_leaf)
    f = np.full(n, -2, np.int64)
    f[~is_leaf] = feature
    t = np.full(n, -2.0)
    t[~is_leaf] = threshold
    v = np.zeros(n)
    v[is_leaf] = values
    return {"left": left, "right": right, "feature": f, "threshold": t, "value": v,
            "roots": np.asarray(roots, np.int64)}


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
