"""A structure-conditional bootstrap replicate's fixed point, solved in the space of the
training rows (:meth:`~offline_adp.algorithms.fqe.FittedQEvaluation.reweighted_value`).

The replicate with row weights ``w`` is the fixed point of the leaf-averaging backup
``v = M_w targets(P_w v)`` over the leaf values ``v`` (:mod:`~offline_adp.algorithms.fqe_bootstrap`:
``M_w[l, i] = w_i / W_l`` averages leaf ``l``'s rows, ``W_l`` their weight; ``P_w`` reads
``sum_a' pi(a'|x'_i) Q(x'_i, a')`` as an average over the trees whose reached leaf kept
weight). With ``y = targets(P_w v)`` the same fixed point reads, over the rows,

    y = targets(K_w y),   K_w = P_w M_w,   v = M_w y,

and ``K_w`` is small: Ernst's leaves hold one or two rows, and the trees' leaves reached by
a query ``(x'_i, a')`` mostly hold the same few rows (``x_{i+1}`` among them), so on the
driving logs ``K_w`` has 4.4 entries a row against the 2 x 20 of ``M_w`` and ``P_w`` (20
trees), and ``y`` (n) is a twentieth of ``v`` (20 n leaves).

The rows are swept Gauss-Seidel, each row's new value used at once, in reverse row order
(the dataset's rows run through each episode in time, so each episode is swept from its
end: a value travels back along an episode in one sweep instead of one step a sweep; on
the driving logs 41-61 sweeps instead of 84-176). ``K_w`` has nonnegative rows summing to at
most 1 and ``targets`` is ``gamma``-Lipschitz, so a sweep ``y -> G(y)`` is a sup-norm
``gamma``-contraction with the fixed point's ``y*``, and ``|G(y) - y*| <= gamma / (1 -
gamma) |G(y) - y|``; ``M_w`` averages, so the leaf values ``v = M_w G(y)`` are as close to
``v*``. The sweeps stop when that bound is within the tolerance asked (``tol``, else
``rtol (u + max |v|)``, ``u`` the costs' size): the stopping rule of the leaf-space iteration
(:func:`~offline_adp.algorithms.fqe_bootstrap.fixed_point`), for the same fixed point.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from offline_adp.algorithms.fqe_bootstrap import leaf_counts, leaf_rows, query_terms, reweight_query_operator
from offline_adp.trees.builder import _kernel


def _row_scales(q_ptr: Any, q_dat: Any, We: Any, scale: Any, fb: Any) -> None:
    """Per query row: ``1 / (its entries' sum over the leaves that kept weight)`` (0 when none
    did, ``fb`` then True: the row keeps its entries); ``We``: each entry's leaf weight."""
    for r in range(len(q_ptr) - 1):
        total = 0.0
        for e in range(q_ptr[r], q_ptr[r + 1]):
            if We[e] > 0.0:
                total += q_dat[e]
        fb[r] = not total > 0.0
        scale[r] = 1.0 / total if total > 0.0 else 0.0


def _k_data(q_ptr: Any, q_dat: Any, q_pi: Any, t_ptr: Any, t_col: Any, We: Any, w: Any, scale: Any, fb: Any,
            slots: Any, kdat: Any) -> None:
    """``K_w``'s entries: ``sum over (query row r of row i, its entry e at leaf l, row i' of l)
    of pi_r p_re w_i' / W_l`` into ``kdat[slot of (i, i')]`` (entry ``e``'s triples are
    ``t_ptr[e] .. t_ptr[e + 1]``: their rows ``t_col`` and slots ``slots``)."""
    kdat[:] = 0.0
    for r in range(len(q_ptr) - 1):
        for e in range(q_ptr[r], q_ptr[r + 1]):
            Wl = We[e]
            if Wl > 0.0:  # a leaf without weight averages to 0
                coef = q_pi[r] * (q_dat[e] if fb[r] else q_dat[e] * scale[r]) / Wl
                for t in range(t_ptr[e], t_ptr[e + 1]):
                    kdat[slots[t]] += coef * w[t_col[t]]


def _p_times(n: int, q_ptr: Any, q_dat: Any, q_pi: Any, q_row: Any, We: Any, ve: Any, scale: Any, fb: Any) -> Any:
    """``P_w v`` (n,): each row's policy-weighted read of the leaf values (``ve``: each
    entry's leaf value)."""
    out = np.zeros(n)
    for r in range(len(q_ptr) - 1):
        acc = 0.0
        for e in range(q_ptr[r], q_ptr[r + 1]):
            if fb[r]:
                acc += q_dat[e] * ve[e]
            elif We[e] > 0.0:
                acc += q_dat[e] * scale[r] * ve[e]
        out[q_row[r]] += q_pi[r] * acc
    return out


def _sweeps(order: Any, k_ptr: Any, k_idx: Any, k_dat: Any, cost: Any, no_boot: Any, gamma: float, cap: float,
            has_cap: bool, tol: float, rtol: float, unit: float, max_sweeps: int, y: Any) -> Any:
    """Gauss-Seidel sweeps ``y_i <- targets((K y)_i)`` over the rows in ``order`` until
    ``max|change| gamma / (1 - gamma) <= tol`` (``tol < 0``: ``rtol (unit + max|y|)``) or
    ``max_sweeps``; returns ``(sweeps, the last sweep's max|change|)``."""
    change = np.inf
    for sweep in range(1, max_sweeps + 1):
        change, ymax = 0.0, 0.0
        for k in range(len(order)):
            i = order[k]
            s = 0.0
            for jj in range(k_ptr[i], k_ptr[i + 1]):
                s += k_dat[jj] * y[k_idx[jj]]
            t = cost[i] + gamma * (0.0 if no_boot[i] else s)
            if has_cap and t > cap:
                t = cap
            change = max(change, abs(t - y[i]))
            ymax = max(ymax, abs(t))
            y[i] = t
        if change * gamma / (1.0 - gamma) <= (tol if tol >= 0.0 else rtol * (unit + ymax)):
            return sweep, change
    return max_sweeps, change


def _leaf_means(m_ptr: Any, m_idx: Any, W: Any, w: Any, y: Any) -> Any:
    """``M_w y``: each leaf's ``w``-weighted mean of its rows' ``y`` (0 without weight)."""
    L = len(m_ptr) - 1
    v = np.zeros(L)
    for leaf in range(L):
        Wl = W[leaf]
        if Wl > 0.0:
            acc = 0.0
            for jj in range(m_ptr[leaf], m_ptr[leaf + 1]):
                acc += (w[m_idx[jj]] / Wl) * y[m_idx[jj]]
            v[leaf] = acc
    return v


_row_scales = _kernel(_row_scales, cache=True, nogil=True, boundscheck=False)
_k_data = _kernel(_k_data, cache=True, nogil=True, boundscheck=False)
_p_times = _kernel(_p_times, cache=True, nogil=True, boundscheck=False)
_sweeps = _kernel(_sweeps, cache=True, nogil=True, boundscheck=False)
_leaf_means = _kernel(_leaf_means, cache=True, nogil=True, boundscheck=False)


@dataclass(frozen=True)
class RowSpace:
    """What every replicate of one fit shares: the query rows the policy reads (``pi > 0``;
    their row, probability and leaf entries), the leaves' rows, and ``K``'s sparsity with
    each (query row, leaf, row) triple's slot in it."""

    q_ptr: np.ndarray
    q_leaf: np.ndarray
    q_dat: np.ndarray
    q_pi: np.ndarray
    q_row: np.ndarray
    m_ptr: np.ndarray
    m_idx: np.ndarray
    k_ptr: np.ndarray
    k_idx: np.ndarray
    t_ptr: np.ndarray
    t_col: np.ndarray
    slots: np.ndarray
    order: np.ndarray


#: ``K_w`` is built when its (query, leaf, row) triples are at most this many times the
#: entries of the leaf-space operators; leaves of many rows (states that repeat exactly, a
#: lattice; large ``min_samples_leaf``) make it dense, and the leaf-space sweeps are cheaper.
MAX_TRIPLES_RATIO = 4.0


def _k_pattern(q_ptr: Any, q_leaf: Any, q_row: Any, m_ptr: Any, m_idx: Any, t_ptr: Any, t_col: Any, slots: Any,
               k_ptr: Any, k_idx: Any) -> int:
    """The (query row, leaf, row) triples' rows ``t_col`` (entry by entry, each leaf's rows in
    order), ``K``'s sparsity (``k_ptr``, ``k_idx``: each row's distinct triple rows, sorted)
    and each triple's ``slots`` in it, one row's query rows at a time (``q_row`` ascending);
    returns ``K``'s entries."""
    nq, nk, r = len(q_ptr) - 1, 0, 0
    k_ptr[0] = 0
    for i in range(len(k_ptr) - 1):
        r0 = r
        while r < nq and q_row[r] == i:
            r += 1
        ta, tb = t_ptr[q_ptr[r0]], t_ptr[q_ptr[r]]
        for e in range(q_ptr[r0], q_ptr[r]):
            lo = m_ptr[q_leaf[e]]
            for t in range(t_ptr[e], t_ptr[e + 1]):
                t_col[t] = m_idx[lo + t - t_ptr[e]]
        if tb > ta:
            cols = np.sort(t_col[ta:tb])
            k_idx[nk] = cols[0]
            u = 1
            for j in range(1, len(cols)):
                if cols[j] != cols[j - 1]:
                    k_idx[nk + u] = cols[j]
                    u += 1
            for t in range(ta, tb):
                slots[t] = nk + np.searchsorted(k_idx[nk:nk + u], t_col[t])
            nk += u
        k_ptr[i + 1] = nk
    return nk


_k_pattern = _kernel(_k_pattern, cache=True, nogil=True, boundscheck=False)


def row_space_sparse(learner: Any, pi_next: np.ndarray) -> bool:
    """Whether :func:`row_space` would build ``K_w`` (:data:`MAX_TRIPLES_RATIO`), read from the
    leaf positions alone (the next-state query operator is not made where it would not be)."""
    L = len(learner.leaf_ids)
    pos = learner.pos["next"]  # (trees, A n)
    n = pi_next.shape[0]
    read = np.flatnonzero((pi_next > 0).T.ravel())  # query columns a n + i the policy reads
    n_triples, nnz = query_terms(pos, read, leaf_counts(learner, np.ones(n, bool)), L)
    return n_triples <= MAX_TRIPLES_RATIO * (nnz + n * pos.shape[0])


def row_space(learner: Any, op_next: Any, pi_next: np.ndarray) -> RowSpace | None:
    """The shared structure of a fit (:class:`RowSpace`): ``op_next`` the next-state query
    operator (rows ``a n + i``), ``pi_next`` (n, A) the policy at the next states. None when
    ``K_w`` would not be sparse (:data:`MAX_TRIPLES_RATIO`): then solve in leaf space.
    Indices are int32 where they fit and no (triples,) int64 temporary is made (1M rows, 20
    trees: ~20M triples; the structure held is ~0.8 GB)."""
    n = pi_next.shape[0]
    i_, a_ = np.nonzero(pi_next > 0)  # row-major: query rows in increasing row order
    sub = op_next[a_ * n + i_].tocsr()
    L = len(learner.leaf_ids)
    pos = learner.pos["train"]  # (trees, n): each row's leaf in each tree
    m_ptr, m_idx = leaf_rows(pos, L)
    del pos
    counts = np.diff(m_ptr)[sub.indices]  # rows of each entry's leaf
    n_triples = int(counts.sum(dtype=np.int64))
    if n_triples > MAX_TRIPLES_RATIO * (sub.nnz + len(m_idx)):
        return None
    idx = np.int32 if max(n_triples, len(m_idx), sub.nnz, n) < 2**31 - 1 else np.int64
    t_ptr = np.zeros(len(counts) + 1, idx)
    np.cumsum(counts, out=t_ptr[1:])
    del counts
    m_ptr, q_ptr, q_leaf = m_ptr.astype(idx), np.asarray(sub.indptr, idx), np.asarray(sub.indices, idx)
    t_col, slots, k_idx = np.empty(n_triples, idx), np.empty(n_triples, idx), np.empty(n_triples, idx)
    k_ptr = np.empty(n + 1, idx)
    nk = _k_pattern(q_ptr, q_leaf, i_.astype(idx), m_ptr, m_idx, t_ptr, t_col, slots, k_ptr, k_idx)
    return RowSpace(q_ptr, q_leaf, np.asarray(sub.data, dtype=np.float64), pi_next[i_, a_].astype(np.float64),
                    i_.astype(idx), m_ptr, m_idx, k_ptr, k_idx[:nk].copy(), t_ptr, t_col, slots,
                    np.arange(n - 1, -1, -1, dtype=idx))


def replicate_value(rs: RowSpace, data: Any, learner: Any, op_start: Any, pi_start: np.ndarray, w: np.ndarray,
                    tol: float | None, rtol: float, max_sweeps: int, ve: np.ndarray | None = None) -> float:
    """The replicate's start value for row weights ``w`` (module docstring): ``y`` from
    ``targets(P_w v)`` at the fitted leaf values (``ve``: theirs at each query entry, when
    the caller keeps them), swept to the stopping rule, then ``v = M_w y`` and the start
    states' ``w``-weighted ``sum_a pi(a|x0) (A_start v)(x0, a)``."""
    W = np.asarray(learner.leaf_weight_sums(w), dtype=np.float64)
    We = W[rs.q_leaf]  # each query entry's leaf weight, gathered once
    nq = len(rs.q_ptr) - 1
    scale, fb = np.empty(nq), np.empty(nq, np.bool_)
    _row_scales(rs.q_ptr, rs.q_dat, We, scale, fb)
    kdat = np.empty(len(rs.k_idx))
    _k_data(rs.q_ptr, rs.q_dat, rs.q_pi, rs.t_ptr, rs.t_col, We, w, scale, fb, rs.slots, kdat)
    ve = np.asarray(learner.leaf_values, dtype=np.float64)[rs.q_leaf] if ve is None else ve
    y = data.targets(_p_times(data.n, rs.q_ptr, rs.q_dat, rs.q_pi, rs.q_row, We, ve, scale, fb))
    cost = np.asarray(data.train.cost, dtype=np.float64)
    no_boot = np.asarray(data.train.no_boot, dtype=np.bool_)
    cap = data.infeasible_cost
    limit, done = (float(tol) if tol is not None else -1.0), 0
    while True:
        sweeps, change = _sweeps(rs.order, rs.k_ptr, rs.k_idx, kdat, cost, no_boot, float(data.gamma),
                                 float(cap) if cap is not None else 0.0, cap is not None, limit, float(rtol),
                                 float(data.cost_unit), max(1, max_sweeps - done), y)
        done += sweeps
        v = _leaf_means(rs.m_ptr, rs.m_idx, W, w, y)
        need = tol if tol is not None else rtol * (data.cost_unit + float(np.max(np.abs(v), initial=0.0)))
        if change * data.gamma / (1.0 - data.gamma) <= need or done >= max_sweeps:
            break
        limit = need  # max|v| <= max|y|: hold the rule to the leaf values' scale
    q0 = (reweight_query_operator(op_start, W > 0) @ v).reshape(data.n_actions, -1).T
    v_start = (pi_start * q0).sum(axis=1)
    w0 = w[data.start_rows]
    return float(np.sum(w0 * v_start) / np.sum(w0)) if np.sum(w0) > 0 else float("nan")
