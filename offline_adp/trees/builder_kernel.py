"""The compiled kernel of the extra-trees builder (:mod:`offline_adp.trees.builder`): one tree
grown depth-first in place (:func:`_grow`) with its inlined helpers (min and max, left-side
sums of four cuts in one pass, the float32 constancy test), compiled by numba with the only
floating-point flags that cannot change a finite result, and whether numba is here.
"""

from __future__ import annotations

from typing import Any

import numpy as np

try:
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; without it, scikit-learn grows the trees
    numba = None

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


def available() -> bool:
    """Whether the compiled builder can run here (numba imports)."""
    return numba is not None


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
