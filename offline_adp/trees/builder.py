"""Extremely randomized regression trees, grown by a compiled builder.

Geurts, Ernst & Wehenkel (2006), "Extremely randomized trees", Machine Learning 63,
Algorithm 1 (``Build_an_extra_tree``), as scikit-learn's ``ExtraTreesRegressor`` grows
them; Ernst, Geurts & Wehenkel (2005) use these trees in fitted Q-iteration. A node of
``m`` rows with targets ``y`` and weights ``w`` splits, unless it is a leaf
(``m < min_samples_split``, ``m < 2 min_samples_leaf``, the depth reached ``max_depth``,
or the targets are constant: weighted variance <= machine epsilon), as follows::

    draw features in random order (without replacement); for each, until
    max_features were drawn and at least one was not constant:
        skip it if constant on the node (max <= min + 1e-7, in float32)
        cut  t_f ~ Uniform[min_f, max_f)          (t_f = min_f if the draw lands on max_f)
        score(f) = S_L^2 / W_L + S_R^2 / W_R       (S: sum of w y, W: sum of w on each side;
                                                    the variance reduction up to a constant)
    split on the feature of highest score (a side with fewer than min_samples_leaf rows
    disqualifies a cut; equal scores, common in nodes of two or three rows, go to one of
    them uniformly at random, which a random feature order gives in exact arithmetic);
    the node's value is the weighted mean of y. When every feature is drawn
    (max_features >= d, the default), the cuts are drawn in feature order: the same
    distribution without a shuffle per node. A node's sums are computed afresh from its
    rows, as scikit-learn does.

Rows with weight 0 are left out (a bootstrap sample is the rows' draw counts as
weights, as in scikit-learn). Inputs are compared as float32, as scikit-learn does, so
a tree reads the same inputs the same way in either implementation.

Where it differs from scikit-learn 1.9, knowingly:

- scikit-learn also makes a node a leaf when the split's *computed* impurity decrease is
  negative (``improvement + EPSILON < min_impurity_decrease``, even at 0). That only
  happens through rounding, on targets equal up to ~1e-6 at |y| >~ 1: exactly the ties the
  frozen learner breaks with a tiny jitter so that such nodes split. There scikit-learn
  stops at random points (1 to 290 leaves for 2000 rows of 2 + N(0, 2.4e-6)) and this
  builder splits on, as Algorithm 1 says (nearly one row per leaf).
- Ties between equal scores: scikit-learn computes the right side as total minus left,
  so exactly tied splits often differ in the last bit there and it takes the same
  feature every time; this builder chooses uniformly.
- Its sums are taken in row order in IEEE double precision, with no reordering or fused
  multiply-add, so the trees are bit-for-bit the same on any x86-64 CPU for the same data,
  settings and seed (``docs/fqi-modes.md``, "What is reproducible").

Why a second implementation: the frozen-structure mode of fitted Q-iteration
(:class:`offline_adp.learn.frozen.FrozenTreesLearner`) spends most of its time growing
structures, and this builder grows them in less CPU than scikit-learn (measurements in
docs/fqi-modes.md) and returns each training row's leaf, so no training row is looked
up again. Its trees
are tested node by node against the algorithm's definition and statistically against
scikit-learn's (``tests/test_extra_trees.py``). Everything else (refit, any other
regressor or setting) uses scikit-learn.

The kernel (:mod:`offline_adp.trees.builder_kernel`) is compiled by numba on first use (a few
seconds, cached on disk after).
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from offline_adp.errors import InvalidArgumentError

# the compiled kernel (builder_kernel.py); its constants and kernels importable from here too
from offline_adp.trees.builder_kernel import (  # noqa: F401
    _EPSILON,
    _FAST,
    FEATURE_THRESHOLD,
    _grow,
    _kernel,
    _left_sums4,
    _left_sums4_unweighted,
    _minmax4,
    _varies,
    available,
)


@dataclass(frozen=True)
class TreeParams:
    """The settings of one forest, resolved for its data (what :func:`grow_trees` reads)."""

    n_estimators: int
    max_features: int
    min_samples_split: int
    min_samples_leaf: int
    max_depth: int
    bootstrap: bool
    n_bootstrap: int  # rows drawn per tree when bootstrapping
    random_state: int
    n_jobs: int


#: the node record the kernel writes: scikit-learn's ``Tree`` node layout where this
#: scikit-learn has the one we know (then a tree is handed to scikit-learn without a copy
#: field by field), else the same fields in a record of our own
_OWN_NODE = np.dtype([("left_child", np.int64), ("right_child", np.int64), ("feature", np.int64),
                      ("threshold", np.float64), ("impurity", np.float64), ("n_node_samples", np.int64),
                      ("weighted_n_node_samples", np.float64)])
_NODE_INTS = ("left_child", "right_child", "feature", "n_node_samples")
_NODE_FLOATS = ("threshold", "impurity", "weighted_n_node_samples")


def node_dtype() -> np.dtype:
    """scikit-learn's tree node record if every field we write is an aligned 8-byte
    integer or float in it, else our own record with those fields."""
    global _NODE
    if _NODE is None:
        try:
            from sklearn.tree._tree import Tree

            dt = Tree(1, np.array([1], dtype=np.intp), 1).__getstate__()["nodes"].dtype
            ok = dt.itemsize % 8 == 0 and all(
                name in dt.fields and dt.fields[name][1] % 8 == 0
                and dt.fields[name][0] == (np.dtype(np.int64) if name in _NODE_INTS else np.dtype(np.float64))
                for name in _NODE_INTS + _NODE_FLOATS)
            _NODE = dt if ok else _OWN_NODE
        except Exception:
            _NODE = _OWN_NODE
    return _NODE


_NODE: np.dtype | None = None


@dataclass(frozen=True)
class GrownTree:
    """One tree: its node records (:func:`node_dtype`; local node ids, leaves have
    ``left_child == -1`` and ``feature == -2``), each node's value (the weighted mean of
    its rows' targets) and the leaf of each training row (int32; -1: a row with weight 0,
    not in the tree; None when not recorded)."""

    nodes: np.ndarray
    value: np.ndarray
    train_leaf: np.ndarray | None

    @property
    def left(self) -> np.ndarray:
        return self.nodes["left_child"]

    @property
    def right(self) -> np.ndarray:
        return self.nodes["right_child"]

    @property
    def feature(self) -> np.ndarray:
        return self.nodes["feature"]

    @property
    def threshold(self) -> np.ndarray:
        return self.nodes["threshold"]


_UNSUPPORTED_DEFAULTS = {"criterion": "squared_error", "max_leaf_nodes": None, "min_impurity_decrease": 0.0,
                         "min_weight_fraction_leaf": 0.0, "ccp_alpha": 0.0, "monotonic_cst": None, "oob_score": False}


def native_params(regressor: Any, n_rows: int, n_features: int) -> TreeParams | None:
    """The compiled builder's settings for ``regressor`` on ``n_rows`` x ``n_features``
    inputs, or None when it does not apply: anything but a plain scikit-learn
    ``ExtraTreesRegressor``, or one with a setting the builder does not implement
    (criterion other than squared error, ``max_leaf_nodes``, ``min_impurity_decrease``,
    ``min_weight_fraction_leaf``, ``ccp_alpha``, ``monotonic_cst``, ``oob_score``)."""
    from sklearn.ensemble import ExtraTreesRegressor

    from offline_adp.trees.averaging import resolve_n_jobs

    if type(regressor) is not ExtraTreesRegressor:
        return None
    p = regressor.get_params()
    for key, default in _UNSUPPORTED_DEFAULTS.items():
        if key not in p:
            continue
        v = p[key]
        same = v is None if default is None else (isinstance(v, str | bool | int | float) and v == default)
        if not same:  # an array (monotonic_cst) or any other value: scikit-learn's own builder
            return None
    if p.get("max_samples") is not None and not p.get("bootstrap"):  # scikit-learn refuses it: let it say so
        return None
    seed = p.get("random_state")
    if not isinstance(seed, int | np.integer):  # None or a RandomState: scikit-learn's own draws
        return None
    mf = p.get("max_features", 1.0)
    if mf is None:
        k = n_features
    elif mf == "sqrt":
        k = max(1, int(math.sqrt(n_features)))
    elif mf == "log2":
        k = max(1, int(math.log2(n_features)))
    elif isinstance(mf, int | np.integer) and not isinstance(mf, bool):
        k = int(mf)
    elif isinstance(mf, float):
        k = max(1, int(mf * n_features))
    else:
        return None
    mss, msl = p.get("min_samples_split", 2), p.get("min_samples_leaf", 1)
    mss = int(mss) if isinstance(mss, int | np.integer) else max(2, math.ceil(float(mss) * n_rows))
    msl = int(msl) if isinstance(msl, int | np.integer) else max(1, math.ceil(float(msl) * n_rows))
    depth = p.get("max_depth")
    ms = p.get("max_samples")
    n_boot = n_rows if ms is None else (int(ms) if isinstance(ms,
                                                              int | np.integer) else max(1, round(float(ms) * n_rows)))
    jobs = resolve_n_jobs(p.get("n_jobs"))  # scikit-learn's own resolution (affinity, cgroups)
    return TreeParams(n_estimators=int(p["n_estimators"]), max_features=max(1, min(k, n_features)),
                      min_samples_split=max(2, mss), min_samples_leaf=max(1, msl),
                      max_depth=2**31 - 1 if depth is None else int(depth), bootstrap=bool(p.get("bootstrap")),
                      n_bootstrap=n_boot, random_state=int(seed), n_jobs=jobs)


def tree_seeds(random_state: int, t: int) -> tuple[int, np.random.Generator]:
    """Tree ``t``'s seed for the kernel's draws and its bootstrap generator: functions of
    ``(random_state, t)`` only, so the first trees of a forest are the same whatever its
    size (a forest grown in two steps equals one grown at once)."""
    ss = np.random.SeedSequence([int(random_state) & 0xFFFFFFFF, int(t)])
    kernel_seed, boot_seed = ss.generate_state(2)
    return int(kernel_seed), np.random.default_rng(int(boot_seed))


def grow_trees(X: np.ndarray, y: np.ndarray, sample_weight: np.ndarray | None, params: TreeParams,
               trees: range | None = None, finish: Any = None, record_leaves: bool = True) -> list[Any]:
    """Grow trees ``trees`` (default: all ``params.n_estimators``) of the forest on ``(X, y)``.

    ``X`` is read as float32 (as scikit-learn does), ``y`` and the weights as float64;
    all three must be finite (ValueError otherwise). Trees are grown in ``params.n_jobs``
    threads (the kernel releases the GIL); the result does not depend on the threads.
    ``finish(tree)``, if given, is applied to each tree (in the calling thread) and its
    result returned instead; it must copy what it keeps (the tree's arrays are the thread's
    buffers, reused for its next tree). ``record_leaves=False``: no ``train_leaf``
    (None), and no (n,) array per thread for it.
    """
    X32 = np.ascontiguousarray(X, dtype=np.float32)
    y = np.asarray(y, dtype=np.float64).ravel()
    n, d = X32.shape
    if len(y) != n:
        raise InvalidArgumentError(f"X has {n} rows, y has {len(y)}")
    w = None if sample_weight is None else np.asarray(sample_weight, dtype=np.float64).ravel()
    if w is not None and len(w) != n:
        raise InvalidArgumentError(f"X has {n} rows, sample_weight has {len(w)}")
    for name, a in (("X", X32), ("y", y), ("sample_weight", w)):
        if a is not None and not np.isfinite(a).all():
            raise InvalidArgumentError(f"the extra-trees builder needs finite {name}")
    if w is not None and (w < 0).any():
        raise InvalidArgumentError("sample_weight must be >= 0")
    every = w is None or bool((w > 0).all())
    record = bool(record_leaves)
    trees = range(params.n_estimators) if trees is None else trees
    dt = node_dtype()
    cols = np.array([dt.fields[k][1] // 8 for k in _NODE_INTS + _NODE_FLOATS], np.int64)
    local = threading.local()  # each thread's buffers, reused tree after tree (no repeated
    # large allocations: they would leave the allocator's per-thread arenas holding memory)

    most = min(n, params.n_bootstrap) if params.bootstrap else n  # rows a tree can hold

    def buffers(rows: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        if getattr(local, "rows", -1) < rows or getattr(local, "width", -1) != width:
            cap = max(rows, most)
            size = max(2 * cap - 1, 1)
            local.R, local.nodes = np.empty((cap, width)), np.zeros(size, dt)
            local.value, local.train_leaf = np.empty(size), np.empty(n if record else 1, np.int32)
            local.rows, local.width = cap, width
        return local.R[:rows], local.nodes, local.value, local.train_leaf  # full width: C-contiguous

    def one(t: int) -> GrownTree:
        seed, rng = tree_seeds(params.random_state, t)
        keep, wk = None, None  # the rows in the tree (None: all) and their weights (None: all 1)
        if params.bootstrap:
            counts = np.bincount(rng.integers(0, n, params.n_bootstrap), minlength=n)
            keep = np.flatnonzero(counts if w is None else counts * (w > 0))
            wk = counts[keep].astype(np.float64) if w is None else counts[keep] * w[keep]
        elif w is not None:
            keep = np.flatnonzero(w > 0) if not every else None
            wk = w if keep is None else w[keep]
        rows = n if keep is None else len(keep)
        weighted = wk is not None and bool((wk != 1.0).any())
        width = d + 3 if weighted else d + 2  # x, y, original index (, w): one column less to move without w
        R, nodes, value, train_leaf = buffers(rows, width)
        if keep is None:
            R[:, :d], R[:, d], R[:, d + 1] = X32, y, np.arange(n)
        else:
            R[:, :d], R[:, d], R[:, d + 1] = X32[keep], y[keep], keep
        if weighted:
            R[:, d + 2] = wk
        size = max(2 * rows - 1, 1)
        node_view = nodes[:size]
        ints, floats = node_view.view(np.int64).reshape(size, -1), node_view.view(np.float64).reshape(size, -1)
        train_leaf.fill(-1)
        count = _grow(R, d, weighted, params.max_features, params.min_samples_split, params.min_samples_leaf,
                      params.max_depth, seed, ints, floats, cols, value, train_leaf, record)
        tree = GrownTree(nodes[:count], value[:count], train_leaf if record else None)
        if finish is not None and not threads:  # finish copies what it keeps
            return finish(tree)
        # the buffers are this thread's for its next tree: hand out copies (finish, if any,
        # then runs in the calling thread)
        return GrownTree(tree.nodes.copy(), tree.value.copy(), train_leaf.copy() if record else None)

    threads = params.n_jobs > 1 and len(trees) > 1
    if not threads:
        return [one(t) for t in trees]
    with ThreadPoolExecutor(max_workers=min(params.n_jobs, len(trees))) as pool:
        # finish in this thread: what it keeps (scikit-learn trees) is allocated by the
        # caller's thread, not left in the worker threads' memory arenas
        return [finish(t) if finish is not None else t for t in pool.map(one, trees)]


def warm_up() -> float:
    """Compile the kernel (or load it from numba's on-disk cache) by growing one tiny
    tree; returns the CPU seconds it took (a few seconds the first time on a machine,
    a fraction of a second after)."""
    import time

    t = time.process_time()
    if available():
        rng = np.random.default_rng(0)
        grow_trees(rng.random((8, 2)), rng.random(8), None, TreeParams(1, 2, 2, 1, 2**31 - 1, False, 8, 0, 1))
    return time.process_time() - t
