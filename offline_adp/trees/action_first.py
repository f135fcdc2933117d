"""Trees that split on the action first: per-action extra-trees held as one joint forest.

Ernst, Geurts & Wehenkel (2005), section 4.3, fit fitted Q-iteration's Q either with the
action as one more input (the joint model) or with one ensemble per action; mushroom-rl's
``FQI`` with an ``ActionRegressor`` fits the latter. Tree ``t`` of this forest is::

    route on f(a) (axis-aligned cuts between the distinct logged action rows; no state split)
    then, below the node that isolates action rows f(a_g):
        tree t of the extra-trees forest grown on the rows {i : f(a_i) = f(a_g)} alone

so its leaves are those of the per-action forests, and its value at ``(x, a)`` is the
per-action forest's at ``x``: the same Q as one model per action, read by everything that
reads a joint :class:`~offline_adp.trees.ensemble.TreeEnsemble` (lookups, export, ONNX). An
action with no logged row is routed to one that has rows (a per-action model has no
model for it at all). The frozen LEARN step grows its structures this way for
``action_encoding="per_action"`` (:mod:`offline_adp.learn.frozen`); measured on
car-on-the-hill and CartPole-v1 in docs/fqi-modes.md.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from offline_adp.trees import builder as compiled
from offline_adp.trees.compact import CompactTree


def action_groups(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct action rows of ``A`` (n, k) as float32 (the builder's and the lookups'
    precision), sorted, and each row's index among them."""
    keys, group = np.unique(np.asarray(A, dtype=np.float32), axis=0, return_inverse=True)
    return keys, np.asarray(group).ravel()


def router(keys: np.ndarray, first: int) -> tuple[Any, ...]:
    """A binary tree of axis-aligned cuts isolating each row of ``keys`` (distinct, float32):
    ``("leaf", g)`` or ``("split", feature, threshold, left, right)``, the feature being
    ``first + column``. A node cuts the first column that varies among its rows, between the
    lower and the upper half of that column's distinct values (at their float64 midpoint,
    strictly between two float32 values: ``x <= t`` holds for the lower half only)."""

    def split(ids: np.ndarray) -> tuple[Any, ...]:
        if len(ids) == 1:
            return ("leaf", int(ids[0]))
        col = next(c for c in range(keys.shape[1]) if len(np.unique(keys[ids, c])) > 1)
        vals = np.unique(keys[ids, col])
        h = len(vals) // 2
        t = (float(vals[h - 1]) + float(vals[h])) / 2.0
        low = keys[ids, col] <= t
        return ("split", first + col, t, split(ids[low]), split(ids[~low]))

    return split(np.arange(len(keys)))


def compose(route: tuple[Any, ...], trees: list[CompactTree], means: np.ndarray,
            weights: np.ndarray) -> tuple[CompactTree, np.ndarray]:
    """One tree: ``route``'s cuts (in preorder), each of its leaves replaced by ``trees[g]``
    (its node ids shifted); a routing node's value is the weighted mean of its groups'
    ``means`` (weights ``weights``). Returns the tree and the node id of each group's root."""
    parts: list[tuple[np.ndarray, ...]] = []
    roots = np.zeros(len(trees), np.int64)
    pos = 0

    def emit(node: tuple[Any, ...]) -> tuple[int, float, float]:
        nonlocal pos
        me = pos
        if node[0] == "leaf":
            g = node[1]
            t = trees[g]
            left, right = t.children_left.astype(np.int64), t.children_right.astype(np.int64)
            parts.append((np.where(left >= 0, left + me, -1), np.where(right >= 0, right + me, -1),
                          t.feature.astype(np.int64), t.thresholds, t.values))
            roots[g] = me
            pos += t.node_count
            return me, float(means[g] * weights[g]), float(weights[g])
        record = [np.zeros(1, np.int64), np.zeros(1, np.int64), np.array([node[1]], np.int64),
                  np.array([node[2]]), np.zeros(1)]
        parts.append(tuple(record))
        pos += 1
        lo, s_lo, w_lo = emit(node[3])
        hi, s_hi, w_hi = emit(node[4])
        record[0][0], record[1][0] = lo, hi
        record[4][0] = (s_lo + s_hi) / (w_lo + w_hi) if w_lo + w_hi > 0 else 0.0
        return me, s_lo + s_hi, w_lo + w_hi

    emit(route)
    left, right, feature, threshold, value = (np.concatenate([p[j] for p in parts]) for j in range(5))
    return CompactTree(left, right, feature, threshold, value), roots


def grow_action_first(X: np.ndarray, y: np.ndarray, sample_weight: np.ndarray | None, params: compiled.TreeParams,
                      trees: range, n_action_columns: int,
                      record_leaves: bool = True) -> list[tuple[CompactTree, np.ndarray | None]]:
    """Trees ``trees`` of the action-first forest (module docstring) on the joint inputs
    ``X`` (the last ``n_action_columns`` columns: ``f(a)``), grown by the compiled builder
    (:func:`~offline_adp.trees.builder.grow_trees`; tree ``t`` of an action's forest depends
    on ``(params.random_state, t)`` and that action's rows only). A bootstrap draws the same
    fraction of each action's rows. Each tree comes with its training rows' leaves (node
    ids in the composed tree), or None unless ``record_leaves`` and every row is in it."""
    X32 = np.ascontiguousarray(X, dtype=np.float32)
    y = np.asarray(y, dtype=np.float64).ravel()
    n, d = X32.shape
    w = None if sample_weight is None else np.asarray(sample_weight, dtype=np.float64).ravel()
    keys, group = action_groups(X32[:, d - n_action_columns:])
    route = router(keys, d - n_action_columns)
    rows = [np.flatnonzero(group == g) for g in range(len(keys))]
    wg = np.ones(n) if w is None else w
    weights = np.array([wg[r].sum() for r in rows])
    means = np.array([(wg[r] * y[r]).sum() for r in rows]) / np.where(weights > 0, weights, 1.0)

    def finish(t: compiled.GrownTree) -> tuple[CompactTree, np.ndarray | None]:
        leaf = t.train_leaf
        return CompactTree.from_grown(t), (leaf.copy() if leaf is not None and int(leaf.min(initial=0)) >= 0
                                           else None)

    grown = []
    for r in rows:
        p = params
        if params.bootstrap:
            p = dataclasses.replace(params, n_bootstrap=max(1, round(params.n_bootstrap * len(r) / n)))
        grown.append(compiled.grow_trees(X32[r], y[r], None if w is None else w[r], p, trees, finish=finish,
                                         record_leaves=record_leaves))
    out = []
    for j in range(len(trees)):
        tree, roots = compose(route, [g[j][0] for g in grown], means, weights)
        leaf: np.ndarray | None = None
        if all(g[j][1] is not None for g in grown):
            leaf = np.empty(n, np.int32)
            for g, r in enumerate(rows):
                leaf[r] = grown[g][j][1] + roots[g]
        out.append((tree, leaf))
    return out
