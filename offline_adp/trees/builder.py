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

The kernel is compiled by numba on first use (a few seconds, cached on disk after).
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from offline_adp.errors import InvalidArgumentError

#: scikit-learn's constants: a feature is constant on a node when max <= min + this (float32)
FEATURE_THRESHOLD = 1e-7
_EPSILON = float(np.finfo(np.float64).eps)  # a node is pure when its variance is <= this

# Floating-point flags of the kernels. Only the two that cannot change a finite result:
# "no NaN" and "no infinity" (the kernel's inputs are checked finite first), which let the
# compiler use the CPU's plain min/max. Never "reassoc", "contract", "arcp", "afn" or
# "nsz": with those the compiler may reorder sums or fuse a*b+c into one rounding
# depending on the CPU it compiles for (FMA or not, vector width), and the same data and
# seed would grow different trees on another machine (tests/test_reproducible.py checks
# a fit compiled for the host CPU against one compiled for a generic x86-64).
_FAST = {"nnan", "ninf"}


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
    n_boot = n_rows if ms is None else (int(ms) if isinstance(ms, int | np.integer) else max(1, round(float(ms) * n_rows)))
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


# ----------------------------------------------------------------------------- the kernel
try:
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; without it, scikit-learn grows the trees
    numba = None


def available() -> bool:
    """Whether the compiled builder can run here (numba imports)."""
    return numba is not None


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


def _kernel(fn: Any, **options: Any) -> Any:
    return numba.njit(**options)(fn) if numba is not None else fn


def _minmax4(R: Any, lo: int, hi: int, f0: int, f1: int, f2: int, f3: int) -> Any:
    """Min and max of four columns over rows [lo, hi), in one pass."""
    a0 = R[lo, f0]; b0 = a0; a1 = R[lo, f1]; b1 = a1; a2 = R[lo, f2]; b2 = a2; a3 = R[lo, f3]; b3 = a3  # noqa: E702
    for i in range(lo + 1, hi):
        v0 = R[i, f0]; v1 = R[i, f1]; v2 = R[i, f2]; v3 = R[i, f3]  # noqa: E702
        a0 = min(a0, v0); b0 = max(b0, v0); a1 = min(a1, v1); b1 = max(b1, v1)  # noqa: E702
        a2 = min(a2, v2); b2 = max(b2, v2); a3 = min(a3, v3); b3 = max(b3, v3)  # noqa: E702
    return a0, b0, a1, b1, a2, b2, a3, b3


def _left_sums4(R: Any, d: int, lo: int, hi: int, f0: int, f1: int, f2: int, f3: int,
                t0: float, t1: float, t2: float, t3: float, j: int, sl: Any, wl: Any, nl: Any) -> None:
    """For four (column, cut) pairs, over rows [lo, hi) with ``x <= cut``: sum of w y,
    sum of w and the row count, in one pass, into entries j..j+3 of ``sl``, ``wl``, ``nl``."""
    s0 = 0.0; s1 = 0.0; s2 = 0.0; s3 = 0.0; w0 = 0.0; w1 = 0.0; w2 = 0.0; w3 = 0.0  # noqa: E702
    n0 = 0; n1 = 0; n2 = 0; n3 = 0  # noqa: E702
    for i in range(lo, hi):
        wi = R[i, d + 2]; wy = wi * R[i, d]  # noqa: E702
        c = R[i, f0] <= t0; s0 += wy if c else 0.0; w0 += wi if c else 0.0; n0 += c  # noqa: E702
        c = R[i, f1] <= t1; s1 += wy if c else 0.0; w1 += wi if c else 0.0; n1 += c  # noqa: E702
        c = R[i, f2] <= t2; s2 += wy if c else 0.0; w2 += wi if c else 0.0; n2 += c  # noqa: E702
        c = R[i, f3] <= t3; s3 += wy if c else 0.0; w3 += wi if c else 0.0; n3 += c  # noqa: E702
    sl[j] = s0; sl[j + 1] = s1; sl[j + 2] = s2; sl[j + 3] = s3  # noqa: E702
    wl[j] = w0; wl[j + 1] = w1; wl[j + 2] = w2; wl[j + 3] = w3  # noqa: E702
    nl[j] = n0; nl[j + 1] = n1; nl[j + 2] = n2; nl[j + 3] = n3  # noqa: E702


def _left_sums4_unweighted(R: Any, d: int, lo: int, hi: int, f0: int, f1: int, f2: int, f3: int,
                           t0: float, t1: float, t2: float, t3: float, j: int, sl: Any, wl: Any, nl: Any) -> None:
    """:func:`_left_sums4` when every weight is 1 (sum of w = the row count)."""
    s0 = 0.0; s1 = 0.0; s2 = 0.0; s3 = 0.0  # noqa: E702
    n0 = 0; n1 = 0; n2 = 0; n3 = 0  # noqa: E702
    for i in range(lo, hi):
        yi = R[i, d]
        c = R[i, f0] <= t0; s0 += yi if c else 0.0; n0 += c  # noqa: E702
        c = R[i, f1] <= t1; s1 += yi if c else 0.0; n1 += c  # noqa: E702
        c = R[i, f2] <= t2; s2 += yi if c else 0.0; n2 += c  # noqa: E702
        c = R[i, f3] <= t3; s3 += yi if c else 0.0; n3 += c  # noqa: E702
    sl[j] = s0; sl[j + 1] = s1; sl[j + 2] = s2; sl[j + 3] = s3  # noqa: E702
    nl[j] = n0; nl[j + 1] = n1; nl[j + 2] = n2; nl[j + 3] = n3  # noqa: E702
    wl[j] = n0; wl[j + 1] = n1; wl[j + 2] = n2; wl[j + 3] = n3  # noqa: E702


def _varies(a: float, b: float) -> bool:
    """Whether a feature taking values ``a`` and ``b`` is not constant: max > min + 1e-7,
    evaluated in float32 as scikit-learn does (FEATURE_THRESHOLD is a float32 there)."""
    return np.float32(max(a, b)) > np.float32(min(a, b)) + np.float32(1e-7)


_varies = _kernel(_varies, inline="always")
_minmax4 = _kernel(_minmax4, inline="always", fastmath=_FAST)
_left_sums4_unweighted = _kernel(_left_sums4_unweighted, inline="always", fastmath=_FAST)
_left_sums4 = _kernel(_left_sums4, inline="always", fastmath=_FAST)


def _grow(R: Any, d: int, weighted: bool, max_features: int, min_split: int, min_leaf: int, max_depth: int,
          seed: int, ints: Any, floats: Any, cols: Any, value: Any, train_leaf: Any, record: bool) -> int:
    """Grow one tree depth-first on the rows of ``R`` (x_0..x_{d-1}, y, original index, and
    w when ``weighted``; reordered in place so that each node's rows are contiguous) into the node records
    (seen as 8-byte integers ``ints`` and floats ``floats``; ``cols``: the slots of
    left_child, right_child, feature, n_node_samples, threshold, impurity,
    weighted_n_node_samples) and ``value``; returns the node count. Node 0 is the root."""
    c_left = cols[0]; c_right = cols[1]; c_feat = cols[2]; c_n = cols[3]  # noqa: E702
    c_thr = cols[4]; c_imp = cols[5]; c_w = cols[6]  # noqa: E702
    n = R.shape[0]
    width = R.shape[1]
    np.random.seed(seed)
    blocks = (d + 3) // 4
    cand = np.empty(4 * blocks, np.int64)  # candidate features of a node (padded by repeating the last)
    cut = np.empty(4 * blocks)
    lo_x = np.empty(d)
    hi_x = np.empty(d)
    order = np.arange(d)
    sl = np.empty(4 * blocks); wl = np.empty(4 * blocks)  # noqa: E702
    nl = np.empty(4 * blocks, np.int64)
    stack = np.empty((n + 2, 4), np.int64)  # node, lo, hi, depth (depth-first: at most depth + 1 entries)
    stack[0, 0] = 0; stack[0, 1] = 0; stack[0, 2] = n; stack[0, 3] = 0  # noqa: E702
    top = 1
    count = 1
    while top > 0:
        top -= 1
        node = stack[top, 0]; lo = stack[top, 1]; hi = stack[top, 2]; depth = stack[top, 3]  # noqa: E702
        m = hi - lo
        # the node's sums afresh, as scikit-learn (no drift from the root); the variance from
        # sums of y - y_first (sp, qp): E[y^2] - mean^2 on raw y cancels catastrophically when
        # the targets are nearly equal (two rows 2.0000022 and 2.0000023: variance 1.6e-15,
        # computed as 0 or 2e-15 depending on rounding), and the purity stop reads it
        y0 = R[lo, d]
        s = 0.0; W = 0.0; sp = 0.0; qp = 0.0  # noqa: E702
        if weighted:
            for i in range(lo, hi):
                wi = R[i, d + 2]; dy = R[i, d] - y0  # noqa: E702
                s += wi * R[i, d]; W += wi; sp += wi * dy; qp += (wi * dy) * dy  # noqa: E702
        else:
            for i in range(lo, hi):
                dy = R[i, d] - y0
                s += R[i, d]; sp += dy; qp += dy * dy  # noqa: E702
            W = float(m)
        mean = s / W if W > 0 else 0.0
        value[node] = mean
        var = qp / W - (sp / W) * (sp / W) if W > 0 else 0.0
        ints[node, c_n] = m
        floats[node, c_w] = W
        floats[node, c_imp] = max(var, 0.0)
        best = -1
        if m == 2 and min_split <= 2 and min_leaf == 1 and depth < max_depth and var > 2.220446049250313e-16:
            # two rows (a third of all splits): every cut on a feature where they differ
            # separates them with the same score, so the split is on one of those
            # features uniformly (the tie-break below), at a uniform cut
            differ = 0
            for f in range(d):
                differ += _varies(R[lo, f], R[lo + 1, f])
            if differ > 0:
                pick = min(int(np.random.random() * differ), differ - 1)
                f = 0
                for g in range(d):
                    if _varies(R[lo, g], R[lo + 1, g]):
                        if pick == 0:
                            f = g
                            break
                        pick -= 1
                a_x = min(R[lo, f], R[lo + 1, f])
                b_x = max(R[lo, f], R[lo + 1, f])
                t = a_x + (b_x - a_x) * np.random.random()
                if t >= b_x:
                    t = a_x
                first = lo if R[lo, f] <= t else lo + 1
                cand[0] = f
                cut[0] = t
                wl[0] = R[first, d + 2] if weighted else 1.0
                sl[0] = wl[0] * R[first, d]
                nl[0] = 1
                best = 0
        elif m >= min_split and m >= 2 * min_leaf and depth < max_depth and var > 2.220446049250313e-16:
            for b in range(blocks):  # every feature's range on the node
                j = 4 * b
                r = _minmax4(R, lo, hi, min(j, d - 1), min(j + 1, d - 1), min(j + 2, d - 1), min(j + 3, d - 1))
                for k in range(4):
                    if j + k < d:
                        lo_x[j + k] = r[2 * k]
                        hi_x[j + k] = r[2 * k + 1]
            found = 0  # features drawn in random order until max_features drawn and one not constant
            visited = 0
            constants = 0
            every = max_features >= d  # all features drawn: their order only breaks ties (below)
            for j in range(d):
                if visited >= max_features and visited > constants:
                    break
                if every:
                    f = j
                else:
                    r_ = j + min(int(np.random.random() * (d - j)), d - j - 1)
                    f = order[r_]; order[r_] = order[j]; order[j] = f  # noqa: E702
                visited += 1
                if np.float32(hi_x[f]) <= np.float32(lo_x[f]) + np.float32(1e-7):  # in float32, as scikit-learn
                    constants += 1
                    continue
                t = lo_x[f] + (hi_x[f] - lo_x[f]) * np.random.random()
                if t >= hi_x[f]:
                    t = lo_x[f]
                cand[found] = f
                cut[found] = t
                found += 1
            if found > 0:
                for k in range(found, 4 * blocks):
                    cand[k] = cand[found - 1]
                    cut[k] = cut[found - 1]
                for b in range((found + 3) // 4):
                    j = 4 * b
                    if weighted:
                        _left_sums4(R, d, lo, hi, cand[j], cand[j + 1], cand[j + 2], cand[j + 3],
                                    cut[j], cut[j + 1], cut[j + 2], cut[j + 3], j, sl, wl, nl)
                    else:
                        _left_sums4_unweighted(R, d, lo, hi, cand[j], cand[j + 1], cand[j + 2], cand[j + 3],
                                               cut[j], cut[j + 1], cut[j + 2], cut[j + 3], j, sl, wl, nl)
                score = -1.0  # a score is >= 0
                ties = 0
                for k in range(found):
                    if nl[k] < min_leaf or m - nl[k] < min_leaf or wl[k] <= 0.0 or W - wl[k] <= 0.0:
                        continue
                    sr = s - sl[k]
                    v = sl[k] * sl[k] / wl[k] + sr * sr / (W - wl[k])
                    if v > score:
                        score = v
                        best = k
                        ties = 1
                    elif v == score:  # the first in a random order among equals: uniform (one pass)
                        ties += 1
                        if np.random.random() * ties < 1.0:
                            best = k
        if best >= 0:
            f = cand[best]
            t = cut[best]
            i = lo
            j = hi - 1
            while True:  # rows with x_f <= t first
                while i <= j and R[i, f] <= t:
                    i += 1
                while i <= j and R[j, f] > t:
                    j -= 1
                if i >= j:
                    break
                for c in range(width):
                    tmp = R[i, c]; R[i, c] = R[j, c]; R[j, c] = tmp  # noqa: E702
                i += 1
                j -= 1
            mid = lo + nl[best]
            a = count; b_ = count + 1  # noqa: E702
            count += 2
            ints[node, c_feat] = f; floats[node, c_thr] = t; ints[node, c_left] = a; ints[node, c_right] = b_  # noqa: E702
            stack[top, 0] = b_; stack[top, 1] = mid; stack[top, 2] = hi; stack[top, 3] = depth + 1  # noqa: E702
            top += 1
            stack[top, 0] = a; stack[top, 1] = lo; stack[top, 2] = mid; stack[top, 3] = depth + 1  # noqa: E702
            top += 1
            continue
        ints[node, c_feat] = -2; floats[node, c_thr] = -2.0; ints[node, c_left] = -1; ints[node, c_right] = -1  # noqa: E702
        if record:
            for i in range(lo, hi):
                train_leaf[np.int64(R[i, d + 1])] = node
    return count


_grow = _kernel(_grow, cache=True, nogil=True, fastmath=_FAST)




