"""Tree ensembles in the compact layout: read straight into their leaf lookups, written
without renumbering a structure twice.

A saved ensemble (:meth:`~offline_adp.trees.ensemble.TreeEnsemble.to_arrays`, artifact
format 2) stores each tree's leaf flags in depth-first order, the splits' features and
thresholds, and the leaves' values. Scoring needs only one lookup record a node (left and
right child as local ids, feature, the threshold's float32 floor: 16 bytes, the layout of
:class:`~offline_adp.trees.compact.CompactTree`'s ``packed``) and the leaf values; the
per-node ``left, right, feature, threshold`` arrays a :class:`TreeEnsemble` holds (40 bytes a
node as int64/float64) serve re-saving, resuming and export only. So
:func:`load_compact_ensemble` checks the members
(:func:`~offline_adp.artifacts.checks.compact_tree_members`), finds every split's children
in one vectorised pass (:func:`preorder_children`), writes the records, and returns a
:class:`LoadedEnsemble` over them: numpy descends them for a few states, and the per-tree
compiled lookups (:class:`~offline_adp.trees.compact.CompactTree`) are views of them, used
when lookups grow (:mod:`offline_adp.trees.loaded`), so loading imports no numba. Both
reach the leaves :meth:`TreeEnsemble.compiled_trees` would reach from the per-node arrays,
so predictions are the same bit for bit.

Writing, :func:`compact_arrays` makes the arrays :meth:`TreeEnsemble.to_arrays` makes (the
format's definition; tested equal) with a compiled depth-first walk, and keeps the last
structures written, so that a frozen fit's checkpoints and model, which share one
structure between builds, write only their leaf values anew.
"""

from __future__ import annotations

import functools
import sys
import weakref
from collections import OrderedDict
from typing import Any

import numpy as np

from offline_adp.artifacts import checks as C
from offline_adp.errors import ArtifactError
from offline_adp.trees import jit
from offline_adp.trees.ensemble import TreeEnsemble, float32_floor
from offline_adp.trees.ensemble import preorder_positions as _numpy_preorder_positions
from offline_adp.trees.loaded import LoadedEnsemble, _Structure


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


def load_compact_ensemble(arrays: Any, prefix: str, where: str, n_features: int | None = None,
                          structure_prefix: str | None = None) -> TreeEnsemble:
    """The compact-layout ensemble under ``prefix`` (structure under ``structure_prefix``
    when shared), every member checked as :func:`~offline_adp.artifacts.checks.check_compact_tree_arrays`
    checks it, each split's children found in one vectorised pass (:func:`preorder_children`)
    and checked inside its tree: a :class:`LoadedEnsemble` over the node records
    (:class:`~offline_adp.trees.compact.CompactTree`'s layout, local ids; numpy descends
    them for small lookups, the compiled lookups are views of them) where numba is
    installed, else a :class:`TreeEnsemble` of per-node arrays (scikit-learn's trees are
    then rebuilt from them on first use). Nothing here imports numba."""
    sp = prefix if structure_prefix is None else structure_prefix
    is_leaf, roots, feature, threshold, values = C.compact_tree_members(arrays, prefix, where, n_features,
                                                                        structure_prefix)
    n = len(is_leaf)
    value = np.zeros(n)
    value[is_leaf] = values
    width = int(feature.max()) + 1 if len(feature) else 0
    splits, right = preorder_children(is_leaf)
    # each right child after its left child and before the end of its tree (flags that passed
    # preorder_valid always are; checked anyway: the compiled lookups read children unchecked)
    first = np.searchsorted(splits, roots)  # each tree's first split (trees of one leaf: none)
    has = first < np.r_[first[1:], len(splits)]
    last_right = np.maximum.reduceat(right, first[has]) if len(splits) else right[:0]
    if (right <= splits + 1).any() or (last_right >= np.r_[roots[1:], n][has]).any():
        raise ArtifactError(f"{where}: {sp}leaf_bits: a split has no right child inside its tree")
    if not jit.installed() or n >= 2**31 - 1:  # per-node arrays for scikit-learn's trees (or the numpy traversal)
        left_g, right_g = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
        left_g[splits], right_g[splits] = splits + 1, right
        f, t = np.full(n, -2, np.int64), np.full(n, -2.0)
        f[splits], t[splits] = feature, threshold
        C.tree_structure(left_g, right_g, roots, where, sp)  # scikit-learn's compiled trees read children unchecked
        return TreeEnsemble(left_g, right_g, f, t, value, roots)
    thr = np.asarray(threshold, dtype=np.float64)  # a stored float32 is its own float32 floor
    root = roots[np.searchsorted(roots, splits, side="right") - 1]  # each split's tree (local ids)
    rec = np.empty((n, 4), np.int32)
    rec[:, 0] = -1
    rec[:, 1] = -1
    rec[:, 2] = -2
    rec[:, 3] = np.float32(-2.0).view(np.int32)
    rec[splits, 0] = splits + 1 - root
    rec[splits, 1] = right - root
    del root
    rec[splits, 2] = feature
    rec[splits, 3] = float32_floor(thr).view(np.int32)
    structure = _Structure(records=rec, split_thresholds=thr, roots=roots, value=value)
    return LoadedEnsemble(structure, value, roots, width)


@functools.cache
def _compiled(fn: Any) -> Any:
    """``fn`` compiled by numba on its first call (:func:`~offline_adp.trees.jit.kernel`)."""
    return jit.kernel(fn, cache=True, nogil=True)


def load_ensemble(arrays: Any, prefix: str, where: str, n_features: int | None = None) -> TreeEnsemble:
    """The ensemble under ``prefix`` in either layout: compact (:func:`load_compact_ensemble`)
    or per-node arrays (artifact format 1, :func:`~offline_adp.artifacts.checks.check_tree_arrays`)."""
    if prefix + "leaf_bits" in C._members(arrays):
        return load_compact_ensemble(arrays, prefix, where, n_features)
    return TreeEnsemble(**C.check_tree_arrays(arrays, prefix, where, n_features))


# ----------------------------------------------------------------------------- writing
#: The structures last written (id of ``left`` -> entry), so that saving the same structure
#: again (a frozen fit's checkpoints, then its model) writes its leaf values only.
_WRITTEN: OrderedDict[int, _Written] = OrderedDict()
#: How many structures :data:`_WRITTEN` keeps (each ~2.5 bytes a node and 4 bytes a leaf).
WRITTEN_KEPT = 2


class _Written:
    """One structure's compact members (keys without prefix) and the node ids of its leaves
    in depth-first order, for the arrays it was made from (held weakly: the same objects)."""

    def __init__(self, ens: TreeEnsemble, members: dict[str, np.ndarray], leaf_nodes: np.ndarray) -> None:
        key = id(ens.left)  # the entry goes when the structure does
        self.refs = [weakref.ref(getattr(ens, k), lambda _, key=key: _WRITTEN.pop(key, None)) for k in _STRUCTURE]
        self.sizes = [len(getattr(ens, k)) for k in _STRUCTURE]
        self.members, self.leaf_nodes = members, leaf_nodes

    def of(self, ens: TreeEnsemble) -> bool:
        return all(r() is getattr(ens, k) and len(getattr(ens, k)) == s
                   for r, k, s in zip(self.refs, _STRUCTURE, self.sizes, strict=True))


_STRUCTURE = ("left", "right", "feature", "threshold", "roots")


def compact_arrays(ens: TreeEnsemble, prefix: str = "", structure: bool = True) -> dict[str, np.ndarray]:
    """``ens.to_arrays(prefix, structure=structure)`` (the compact layout; the per-node one
    where the trees do not each span their range), the same arrays, made faster: the
    depth-first renumbering by a compiled walk (:func:`preorder_nodes`), the distinct
    leaf values by a hash table when pandas is loaded, and a structure written before
    (the same ``left, right, feature, threshold, roots`` objects, which nothing changes in
    place) taken from :data:`_WRITTEN`: then only the leaf values are new."""
    left = getattr(ens, "left", None)
    if not isinstance(left, np.ndarray) or any(not isinstance(getattr(ens, k, None), np.ndarray) for k in _STRUCTURE):
        return ens.to_arrays(prefix, structure=structure)
    hit = _WRITTEN.get(id(left))
    if hit is None or not hit.of(ens):
        hit = _structure_members(ens)
        if hit is None:  # not trees each spanning its range: stored node by node, as to_arrays does
            return ens.to_arrays(prefix, "nodes")
        _WRITTEN[id(left)] = hit
        while len(_WRITTEN) > WRITTEN_KEPT:
            _WRITTEN.popitem(last=False)
    _WRITTEN.move_to_end(id(left))
    out = _leaf_value_members(np.asarray(ens.value, dtype=np.float64)[hit.leaf_nodes], prefix)
    if structure:
        out.update({prefix + k: v for k, v in hit.members.items()})
    return out


def _structure_members(ens: TreeEnsemble) -> _Written | None:
    """The compact members of ``ens``'s structure (as :meth:`TreeEnsemble.to_arrays`
    makes them), or None where the per-node layout is needed."""
    left, right, roots = (np.asarray(a, dtype=np.int64) for a in (ens.left, ens.right, ens.roots))
    node = preorder_nodes(left, right, roots)  # node[p]: the node numbered p depth-first
    if node is None:
        return None
    is_leaf = left[node] < 0
    inner = node[~is_leaf]
    f = np.asarray(ens.feature)[inner]
    top = int(f.max()) if len(f) else 0
    t = np.asarray(ens.threshold, dtype=np.float64)[inner]
    t32 = float32_floor(t)
    members = {"roots": roots.astype(np.int32) if len(left) < 2**31 - 1 else roots,
               "leaf_bits": np.packbits(is_leaf),
               "feature": f.astype(next(d for d in (np.uint8, np.uint16, np.uint32,
                                                    np.int64) if top <= np.iinfo(d).max)),
               "threshold": t32 if np.all(np.isfinite(t32) == np.isfinite(t)) else t}
    leaf_nodes = node[is_leaf]
    return _Written(ens, members, leaf_nodes.astype(np.int32) if len(left) < 2**31 - 1 else leaf_nodes)


def _leaf_value_members(values: np.ndarray, prefix: str) -> dict[str, np.ndarray]:
    """Leaf values as ``value``, or ``value_table`` + ``value_code`` when smaller: what
    :meth:`TreeEnsemble.to_arrays` writes (distinct by their bits, in ascending order of
    the bits), the table found by pandas' hash table when pandas is loaded (5x a sort)."""
    bits = values.view(np.uint64)
    pd = sys.modules.get("pandas")
    if pd is not None:
        code, table_bits = pd.factorize(bits, sort=True)
        table_bits = np.asarray(table_bits, dtype=np.uint64)
    else:
        table_bits, code = np.unique(bits, return_inverse=True)
    k = len(table_bits)
    ctype = next(t for t in (np.uint8, np.uint16, np.uint32, np.uint64) if k - 1 <= np.iinfo(t).max)
    if k * 8 + len(values) * np.dtype(ctype).itemsize >= len(values) * 8:
        return {prefix + "value": values}
    return {prefix + "value_table": table_bits.view(np.float64),
            prefix + "value_code": np.asarray(code).reshape(-1).astype(ctype)}


def preorder_nodes(left: np.ndarray, right: np.ndarray, roots: np.ndarray) -> np.ndarray | None:
    """The nodes in the order of :meth:`TreeEnsemble.to_arrays`' compact layout: every tree
    numbered depth-first, left subtree first, from its root (``out[p]`` is the node
    numbered ``p``); None unless every tree spans exactly its own range (each node reached
    once, from one root), where the per-node layout is stored instead. A compiled walk of
    each tree where numba runs (large ensembles), else
    :func:`offline_adp.trees.ensemble.preorder_positions`' level-by-level passes."""
    n = len(left)
    if n == 0:
        return None
    if jit.available() and n >= COMPILED_WALK_NODES:
        out = np.empty(n, np.int64)
        ok = _compiled(_preorder_walk)(left, right, roots, out, np.zeros(n, np.uint8), np.empty(n + 1, np.int64))
        return out if ok else None
    pos = _numpy_preorder_positions(left, right, roots)
    if int(pos.min()) < 0 or int(pos.max()) >= n or np.bincount(pos, minlength=n).max() != 1 \
            or not np.array_equal(pos[roots], roots):  # (nodes no walk reached hold what np.empty held)
        return None
    out = np.empty(n, np.int64)
    out[pos] = np.arange(n)
    return out


#: Ensembles of at least this many nodes are numbered by the compiled walk (loading it costs
#: ~0.1 CPU-s a process, compiling it once ~1 s; the numpy passes take ~0.15 s a million nodes).
COMPILED_WALK_NODES = 1 << 19


def _preorder_walk(left: Any, right: Any, roots: Any, out: Any, seen: Any, stack: Any) -> bool:
    """Walk each tree depth-first, left subtree first, from its root: ``out[p] = j`` for
    the node ``j`` numbered ``p`` (from the root's own index on). False unless every node
    is reached exactly once and each tree's numbers end where the next tree begins."""
    n = len(left)
    p = 0
    for m in range(len(roots)):
        r = roots[m]
        end = roots[m + 1] if m + 1 < len(roots) else n
        if r != p or end <= r or end > n:
            return False
        top = 0
        stack[0] = r
        while top >= 0:
            j = stack[top]
            top -= 1
            if j < 0 or j >= n or seen[j] or p >= end:
                return False
            seen[j] = 1
            out[p] = j
            p += 1
            if left[j] >= 0:
                if top + 2 >= len(stack):
                    return False
                top += 1
                stack[top] = right[j]
                top += 1
                stack[top] = left[j]
        if p != end:
            return False
    return p == n
