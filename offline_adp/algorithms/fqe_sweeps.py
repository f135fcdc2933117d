"""The settle's sweeps without their sparse matrices
(:meth:`~offline_adp.algorithms.fqe.FittedQEvaluation.settle`): the leaf-averaging operator
``M`` (:func:`~offline_adp.algorithms.fqe_bootstrap.leaf_operator`) and the policy's
operator ``P`` (:func:`~offline_adp.algorithms.fqe_bootstrap.policy_operator`) applied
from the fit's leaf positions, each product the one the CSR matrix gives bit for bit: every
output entry sums the same terms, each the same IEEE product, from 0 in the same order
(scipy's ``csr_matvec``). At 1M rows and 20 trees the two matrices are ~0.55 GiB, held
through every sweep; here only the positions the fit holds anyway are read.

A bootstrap replicate solved in leaf space (leaves of many rows, where the row space is
dense: :meth:`~offline_adp.algorithms.fqe.FittedQEvaluation.reweighted_value`) applies its
``M_w`` and ``P_w`` the same way (``LeafAverage(weights=...)``, ``PolicyRead(keep=...)``):
the numbers of :func:`~offline_adp.algorithms.fqe_bootstrap.reweighted_operators`' matrices,
none of which is made (their copies were ~5 GiB of a 1M-row evaluation's FQE task).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.learn import FrozenTreesLearner
from offline_adp.trees.averaging import _split, thread_map
from offline_adp.trees.builder import _kernel


def _average_rows(nxt: Any, src: Any, rest: Any, w: Any, wsum: Any, y: Any, t0: int, t1: int, out: Any) -> None:
    """``out[l] = sum over the rows i of leaf l, in order, of (w_i / wsum[l]) y_i`` (from 0; a
    leaf without weight: ``wsum[l] * y_i``, as :func:`~offline_adp.algorithms.fqe_bootstrap._leaf_data`
    stores it) for trees ``t0..t1-1``; row ``i``'s leaf in tree ``t`` is ``nxt[t, src[i]]``
    where ``src[i] >= 0``, else the next column of ``rest[t]``. A leaf's rows are all in its
    own tree, in increasing order: the CSR row's order."""
    n = len(src)
    for t in range(t0, t1):
        j = 0
        for i in range(n):
            s = src[i]
            if s >= 0:
                leaf = nxt[t, s]
            else:
                leaf = rest[t, j]
                j += 1
            ws = wsum[leaf]
            d = w[i] / ws if ws > 0.0 else ws
            out[leaf] += d * y[i]


def _policy_apply(pos: Any, pi: Any, n: int, L: int, inv_m: float, keep: Any, v: Any, out: Any, slot: Any) -> None:
    """``out[i] = (P v)_i`` with row ``i`` of ``P`` (:func:`~offline_adp.algorithms.fqe_bootstrap.policy_operator`)
    as scipy's product ``pick @ op_next`` builds it: its leaves in the order first reached
    (actions in order, trees in order), each summing ``pi(a|x'_i) * (1/m)`` from 0, entries
    summing to 0 left out, then summed from 0, last first reached first (scipy's order).
    ``slot[leaf]``: the row's entry of a leaf already reached, else -1 (as scipy's own
    ``csr_matmat`` finds it; reset after each row).

    ``keep`` (a bool per leaf; empty: the fit's own operator): the operator reweighted to the
    leaves kept (:func:`~offline_adp.algorithms.fqe_bootstrap.reweight_query_operator`): a
    query's entries at leaves not kept are 0, the others ``inv_m / total`` (``total``: the kept
    entries' ``inv_m`` summed in tree order, as ``np.bincount`` sums them); a query with none
    kept keeps ``inv_m`` at every leaf it reached. A dropped leaf is an explicit 0 of that
    operator, so it holds its place in the row where first reached (another action's query
    may then add a fallback's terms), as in scipy's product."""
    A, m = pi.shape[1], pos.shape[0]
    reweight = len(keep) > 0
    keys, sums = np.empty(m * A, np.int64), np.empty(m * A)
    for i in range(n):
        k = 0
        for a in range(A):
            p = pi[i, a]
            if not p > 0:
                continue
            q = a * n + i
            fall, d = True, inv_m
            if reweight:
                total = 0.0
                for t in range(m):
                    leaf = pos[t, q]
                    if leaf < L and keep[leaf]:
                        total += inv_m
                fall = not total > 0.0
                d = inv_m if fall else inv_m * (1.0 / total)
            for t in range(m):
                leaf = pos[t, q]
                if leaf >= L:
                    continue
                j = slot[leaf]
                if j < 0:
                    j = k
                    slot[leaf] = k
                    keys[k] = leaf
                    sums[k] = 0.0
                    k += 1
                sums[j] += p * (d if (fall or keep[leaf]) else 0.0)
        acc = 0.0
        for j in range(k - 1, -1, -1):
            slot[keys[j]] = -1
            if sums[j] != 0.0:
                acc += sums[j] * v[keys[j]]
        out[i] = acc


_average_rows = _kernel(_average_rows, cache=True, nogil=True, boundscheck=False)
_policy_apply = _kernel(_policy_apply, cache=True, nogil=True, boundscheck=False)


class LeafAverage:
    """``M @ y`` of :func:`~offline_adp.algorithms.fqe_bootstrap.leaf_operator` (the same
    numbers) from ``learner``'s training positions and held leaf weights, trees over its
    ``n_jobs`` threads (each leaf summed in one thread, in row order); with ``weights``, of a
    replicate's ``M_w`` (``weight_sums``: their leaf sums, when the caller has them)."""

    def __init__(self, learner: FrozenTreesLearner, weights: np.ndarray | None = None,
                 weight_sums: np.ndarray | None = None) -> None:
        nxt, src, rest, wsum = learner.reused_positions()
        self.nxt, self.rest, self.wsum = nxt, rest, wsum
        self.src = np.ascontiguousarray(src, dtype=np.int64)
        n = len(self.src)
        self.w = np.ones(n) if learner.weights is None else np.asarray(learner.weights, dtype=np.float64)
        if weights is not None:  # a replicate's M_w (fqe_bootstrap.reweighted_operators's numbers)
            self.w = np.ascontiguousarray(weights, dtype=np.float64)
            self.wsum = np.asarray(learner.leaf_weight_sums(self.w) if weight_sums is None else weight_sums,
                                   dtype=np.float64)
        self.n_jobs, self.L = learner.n_jobs, len(learner.leaf_ids)

    def __matmul__(self, y: np.ndarray) -> np.ndarray:
        y = np.ascontiguousarray(y, dtype=np.float64)
        out = np.zeros(self.L)
        m = self.rest.shape[0]
        thread_map(lambda r: _average_rows(self.nxt, self.src, self.rest, self.w, self.wsum, y, r[0], r[1], out),
                   _split(m, self.n_jobs), self.n_jobs)
        return out


class PolicyRead:
    """``P @ v`` of :func:`~offline_adp.algorithms.fqe_bootstrap.policy_operator` (the same
    numbers) from the next-state leaf positions ``pos_next`` ((trees, A n); ``L``: no training
    leaf) and the policy's probabilities there ``pi_next`` (n, A); with ``keep`` (a bool per
    leaf), of the operator reweighted to the leaves kept (a bootstrap replicate's ``P_w``)."""

    def __init__(self, pos_next: np.ndarray, pi_next: np.ndarray, L: int, keep: np.ndarray | None = None) -> None:
        self.pos, self.pi = np.ascontiguousarray(pos_next), np.ascontiguousarray(pi_next, dtype=np.float64)
        self.keep = np.zeros(0, np.bool_) if keep is None else np.ascontiguousarray(keep, dtype=np.bool_)
        self.n, self.L, self.inv_m = len(self.pi), int(L), 1.0 / pos_next.shape[0]
        self.slot = np.full(self.L, -1, np.int32)  # each leaf's entry in the row being read (4 bytes a leaf)
        if self.pi.ndim != 2 or self.pos.ndim != 2 or self.pos.shape[1] != self.pi.size:
            raise ValueError(f"PolicyRead: next-state positions {self.pos.shape} do not match the policy's "
                             f"probabilities {self.pi.shape} (trees, actions x rows)")

    def __matmul__(self, v: np.ndarray) -> np.ndarray:
        out, v = np.empty(self.n), np.ascontiguousarray(v, dtype=np.float64)
        _policy_apply(self.pos, self.pi, self.n, self.L, self.inv_m, self.keep, v, out, self.slot)
        return out
