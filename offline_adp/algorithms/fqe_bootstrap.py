"""Structure-conditional bootstrap of a frozen-structure FQE fit: its leaf-averaging and
query operators as sparse matrices, reweighted for other sample weights, and the fixed
point of the averager they define (:meth:`~offline_adp.algorithms.fqe.FittedQEvaluation.settle`,
:meth:`~offline_adp.algorithms.fqe.FittedQEvaluation.reweighted_value`).

The operators read the public leaf index of a
:class:`~offline_adp.learn.frozen.FrozenTreesLearner`: ``pos`` (per query set, tree-major
compact leaf positions; ``len(leaf_ids)`` for a leaf without training rows), ``leaf_ids``
and ``weights``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import sparse

from offline_adp.algorithms.fqi_data import PolicyBackup, Prepared
from offline_adp.learn import FrozenTreesLearner


def _averaging_matrix(pos: np.ndarray, w: np.ndarray, wsum: np.ndarray, L: int) -> Any:
    """``M[leaf, i] = w_i / wsum[leaf]`` (0 where ``wsum`` is 0) as CSR, built column by
    column (row ``i``'s ``m`` leaves are ``pos[:, i]``) with no tree-major (m * n) index
    temporaries: the data, its int32 leaf indices, then one conversion."""
    m, n = pos.shape
    idx = np.ascontiguousarray(pos.T)  # (n, m): column i's entries, tree order
    data = wsum[idx]
    np.divide(w[:, None], data, out=data, where=data > 0)  # a leaf without weight keeps its 0
    M = sparse.csc_matrix((data.reshape(-1), idx.reshape(-1), np.arange(0, n * m + 1, m, dtype=np.int64)),
                          shape=(L, n))
    del data, idx
    return M.tocsr()


def leaf_operator(learner: FrozenTreesLearner) -> Any:
    """The leaf-averaging operator as a sparse (leaves, n) matrix:
    ``M[leaf, i] = w_i / (sum of w in the leaf)``, so ``leaf_values = M @ y``."""
    pos = learner.pos["train"]
    w = np.ones(pos.shape[1]) if learner.weights is None else np.asarray(learner.weights, dtype=np.float64)
    return _averaging_matrix(pos, w, learner.leaf_weight_sums(w), len(learner.leaf_ids))


def query_operators(learner: FrozenTreesLearner, names: tuple[str, ...] | None = None) -> dict[str, Any]:
    """The query operators ``A[q, leaf] = 1 / n_trees`` as sparse matrices, for the query
    sets ``names`` (default: all, ``"train"`` included); built row by row (query ``j``'s
    leaves are ``pos[:, j]``, those with training rows), int32 indices."""
    L, out = len(learner.leaf_ids), {}
    for name, pos in learner.pos.items():
        if names is not None and name not in names:
            continue
        m, nq = pos.shape
        idx = np.ascontiguousarray(pos.T)  # (nq, m), tree order (increasing leaf ids) in each row
        hit = idx < L
        indptr = np.zeros(nq + 1, np.int64)
        np.cumsum(hit.sum(axis=1), out=indptr[1:])
        indices = idx[hit]
        del idx, hit
        out[name] = sparse.csr_matrix((np.full(len(indices), 1.0 / m), indices, indptr), shape=(nq, L))
    return out


def reweighted_operators(learner: FrozenTreesLearner, weights: np.ndarray,
                         base: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
    """Leaf-averaging operator ``M`` and query operators ``A`` for other sample weights
    on the same structure. A leaf left with no weight is dropped from every query's
    average over trees (rows of ``A`` renormalised over the remaining trees; a query
    with none left keeps its original row). ``base``: the unweighted query operators
    to reweight (default: all of :func:`query_operators`, built here), so that many
    replicates build them once."""
    L = len(learner.leaf_ids)
    w = np.asarray(weights, dtype=np.float64)
    wsum = learner.leaf_weight_sums(w)
    M = _averaging_matrix(learner.pos["train"], w, wsum, L)
    keep = wsum > 0
    A = {}
    for name, op in (query_operators(learner) if base is None else base).items():  # entry by entry, on op's sparsity
        op = op.tocsr()
        row = np.repeat(np.arange(op.shape[0]), np.diff(op.indptr))
        kept = np.where(keep[op.indices], op.data, 0.0)
        total = np.bincount(row, weights=kept, minlength=op.shape[0])
        scale = np.where(total > 0, 1.0 / np.where(total > 0, total, 1.0), 0.0)
        data = np.where((total > 0)[row], kept * scale[row], op.data)  # a row with no leaf left: unchanged
        A[name] = sparse.csr_matrix((data, op.indices, op.indptr), shape=op.shape)
    return M, A


def fixed_point(data: Prepared, backup: PolicyBackup, M: Any, ops: dict[str, Any], v: np.ndarray, tol: float | None,
                max_iterations: int, rtol: float = 1e-7) -> tuple[np.ndarray, int]:
    """Iterate the leaf-averaging backup ``v <- M (targets(P v))`` from ``v`` (a
    gamma-contraction) until its distance to the fixed point is at most ``tol`` (default
    ``rtol (1 + max |v|)``) or ``max_iterations`` sweeps; returns ``(v, sweeps)``.

    The policy's expectation over next actions is folded into one operator first,
    ``P = sum_a diag(pi(a|x')) A_next[a]`` (rows of actions the policy never takes
    left out), so a sweep is two sparse products; for a deterministic policy ``P`` has
    ``1/A`` of ``A_next``'s entries."""
    n, A = data.n, data.n_actions
    pi_next = np.asarray(backup.probabilities("next", 0), dtype=np.float64)
    i, a = np.nonzero(pi_next > 0)
    pick = sparse.csr_matrix((pi_next[i, a], (i, a * n + i)), shape=(n, A * n))
    P = (pick @ ops["next"]).tocsr()  # V(x'_i) = sum_a pi(a|x'_i) Q(x'_i, a) as one operator on the leaf values
    v = np.asarray(v, dtype=np.float64).copy()
    if not len(v):
        return v, 1
    diff = np.empty_like(v)
    for sweep in range(1, max_iterations + 1):
        v_new = M @ data.targets(P @ v)  # the loop's own targets (c^- clamp included)
        np.subtract(v_new, v, out=diff)
        change = max(float(diff.max()), -float(diff.min()))
        v = v_new
        # an averager's backup is a sup-norm gamma-contraction: |v - v*| <= change * gamma / (1 - gamma)
        bound = change * data.gamma / (1.0 - data.gamma)
        if bound <= (tol if tol is not None else rtol * (1.0 + max(float(v.max()), -float(v.min())))):
            return v, sweep
    return v, max_iterations
