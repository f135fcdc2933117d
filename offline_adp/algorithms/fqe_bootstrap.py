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
from offline_adp.errors import InvalidArgumentError
from offline_adp.learn import FrozenTreesLearner
from offline_adp.trees.builder import _kernel


def _leaf_rows(pos: Any, m_ptr: Any, m_idx: Any) -> None:
    """Each leaf's training rows, in increasing order, into ``m_idx`` at ``m_ptr`` (tree-major
    ``pos``: a leaf's rows all come from its own tree, in row order)."""
    fill = m_ptr[:-1].copy()
    for t in range(pos.shape[0]):
        for i in range(pos.shape[1]):
            leaf = pos[t, i]
            m_idx[fill[leaf]] = i
            fill[leaf] += 1


def _leaf_counts(pos: Any, m_ptr: Any) -> None:
    """``m_ptr[l + 1]``: the rows before the end of leaf ``l`` (a cumulative count)."""
    for t in range(pos.shape[0]):
        for i in range(pos.shape[1]):
            m_ptr[pos[t, i] + 1] += 1
    for leaf in range(1, len(m_ptr)):
        m_ptr[leaf] += m_ptr[leaf - 1]


def _leaf_data(m_ptr: Any, m_idx: Any, w: Any, wsum: Any, data: Any) -> None:
    """``w_i / wsum[leaf]`` at each (leaf, row) entry (a leaf without weight keeps its ``wsum``)."""
    for leaf in range(len(m_ptr) - 1):
        s = wsum[leaf]
        for j in range(m_ptr[leaf], m_ptr[leaf + 1]):
            data[j] = w[m_idx[j]] / s if s > 0.0 else s


_leaf_rows = _kernel(_leaf_rows, cache=True, nogil=True, boundscheck=False)
_leaf_counts = _kernel(_leaf_counts, cache=True, nogil=True, boundscheck=False)
_leaf_data = _kernel(_leaf_data, cache=True, nogil=True, boundscheck=False)


def leaf_rows(pos: np.ndarray, L: int) -> tuple[np.ndarray, np.ndarray]:
    """``(m_ptr, m_idx)``: each of the ``L`` leaves' training rows (``pos`` (trees, n), every
    entry below ``L``), sorted, as CSR row pointers and column indices (int32 where they fit)."""
    idx = np.int32 if pos.size < 2**31 - 1 else np.int64
    m_ptr = np.zeros(L + 1, idx)
    _leaf_counts(pos, m_ptr)
    m_idx = np.empty(pos.size, idx)
    _leaf_rows(pos, m_ptr, m_idx)
    return m_ptr, m_idx


def _averaging_matrix(pos: np.ndarray, w: np.ndarray, wsum: np.ndarray, L: int) -> Any:
    """``M[leaf, i] = w_i / wsum[leaf]`` (0 where ``wsum`` is 0) as CSR, each leaf's rows in
    increasing order, built in place by compiled passes (:func:`leaf_rows`): no (n, trees)
    temporaries and no second copy in a format conversion."""
    m_ptr, m_idx = leaf_rows(pos, L)
    data = np.empty(len(m_idx))
    _leaf_data(m_ptr, m_idx, np.asarray(w, dtype=np.float64), np.asarray(wsum, dtype=np.float64), data)
    return sparse.csr_matrix((data, m_idx, m_ptr), shape=(L, pos.shape[1]))


def leaf_operator(learner: FrozenTreesLearner) -> Any:
    """The leaf-averaging operator as a sparse (leaves, n) matrix:
    ``M[leaf, i] = w_i / (sum of w in the leaf)``, so ``leaf_values = M @ y``."""
    pos = learner.pos["train"]
    w = np.ones(pos.shape[1]) if learner.weights is None else np.asarray(learner.weights, dtype=np.float64)
    wsum = getattr(learner, "weight_sums", None)  # the fit's own (another vector of the leaves' size not made)
    return _averaging_matrix(pos, w, learner.leaf_weight_sums(w) if wsum is None else wsum, len(learner.leaf_ids))


def query_operators(learner: FrozenTreesLearner, names: tuple[str, ...] | None = None) -> dict[str, Any]:
    """The query operators ``A[q, leaf] = 1 / n_trees`` as sparse matrices, for the query
    sets ``names`` (default: all, ``"train"`` included); built row by row (query ``j``'s
    leaves are ``pos[:, j]``, those with training rows), int32 indices."""
    L, out = len(learner.leaf_ids), {}
    for name, pos in learner.pos.items():
        if names is not None and name not in names:
            continue
        out[name] = _query_matrix(pos, L)
    return out


def query_rows(learner: FrozenTreesLearner, name: str, lo: int, hi: int) -> Any:
    """Rows ``lo .. hi - 1`` of ``query_operators(learner, (name,))[name]`` (its entries, in
    its order), made from those queries' positions only: the whole operator is not built."""
    return _query_matrix(learner.pos[name][:, lo:hi], len(learner.leaf_ids))


def _query_matrix(pos: np.ndarray, L: int) -> Any:
    """``A[q, leaf] = 1 / n_trees`` over the leaves ``pos[:, q]`` with training rows (< ``L``)."""
    m, nq = pos.shape
    idx = np.ascontiguousarray(pos.T)  # (nq, m), tree order (increasing leaf ids) in each row
    hit = idx < L
    indptr = np.zeros(nq + 1, np.int64)
    np.cumsum(hit.sum(axis=1), out=indptr[1:])
    indices = idx[hit]
    del idx, hit
    return sparse.csr_matrix((np.full(len(indices), 1.0 / m), indices, indptr), shape=(nq, L))


def reweighted_operators(learner: FrozenTreesLearner, weights: np.ndarray,
                         base: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
    """Leaf-averaging operator ``M`` and query operators ``A`` for other sample weights
    on the same structure. A leaf left with no weight is dropped from every query's
    average over trees (rows of ``A`` renormalised over the remaining trees; a query
    with none left keeps its original row). ``base``: the unweighted query operators
    to reweight (default: all of :func:`query_operators`, built here), so that many
    replicates build them once.

    The matrix construction a replicate's leaf-space sweeps are defined by and tested against
    (``tests/test_fqe_replicates.py``); the library applies them without making them
    (:class:`~offline_adp.algorithms.fqe_sweeps.LeafAverage`, ``PolicyRead``)."""
    L = len(learner.leaf_ids)
    w = np.asarray(weights, dtype=np.float64)
    wsum = learner.leaf_weight_sums(w)
    M = _averaging_matrix(learner.pos["train"], w, wsum, L)
    keep = wsum > 0
    A = {name: reweight_query_operator(op, keep)
         for name, op in (query_operators(learner) if base is None else base).items()}
    return M, A


def reweight_query_operator(op: Any, keep: np.ndarray) -> Any:
    """A query operator with the leaves not ``keep`` dropped from each query's average over
    trees (its row renormalised over the remaining entries; a row with none left keeps its
    original entries), entry by entry on ``op``'s sparsity (:func:`reweighted_operators`)."""
    op = op.tocsr()
    row = np.repeat(np.arange(op.shape[0]), np.diff(op.indptr))
    kept = np.where(keep[op.indices], op.data, 0.0)
    total = np.bincount(row, weights=kept, minlength=op.shape[0])
    scale = np.where(total > 0, 1.0 / np.where(total > 0, total, 1.0), 0.0)
    data = np.where((total > 0)[row], kept * scale[row], op.data)  # a row with no leaf left: unchanged
    return sparse.csr_matrix((data, op.indices, op.indptr), shape=op.shape)


def fixed_point(data: Prepared, backup: PolicyBackup, M: Any, ops: dict[str, Any], v: np.ndarray, tol: float | None,
                max_iterations: int, rtol: float = 1e-7) -> tuple[np.ndarray, int]:
    """Iterate the leaf-averaging backup ``v <- M (targets(P v))`` from ``v`` (a
    gamma-contraction) until its distance to the fixed point is at most ``tol`` (default
    ``rtol (u + max |v|)``, ``u`` the costs' size ``data.cost_unit``) or ``max_iterations``
    sweeps; returns ``(v, sweeps)``. On
    :func:`reweighted_operators`' matrices: the reference the matrix-free replicate is tested
    against.

    The policy's expectation over next actions is folded into one operator first,
    ``P = sum_a diag(pi(a|x')) A_next[a]`` (rows of actions the policy never takes
    left out), so a sweep is two sparse products; for a deterministic policy ``P`` has
    ``1/A`` of ``A_next``'s entries."""
    return averaged_fixed_point(data, M, policy_operator(data, backup, ops["next"]), v, tol, max_iterations, rtol)


def policy_operator(data: Prepared, backup: PolicyBackup, op_next: Any) -> Any:
    """``P = sum_a diag(pi(a|x')) A_next[a]`` (:func:`fixed_point`): ``V(x'_i) = sum_a
    pi(a|x'_i) Q(x'_i, a)`` as one operator on the leaf values, from the next-state query
    operator ``op_next`` (:func:`query_operators`). The settle applies it without making it
    (:class:`~offline_adp.algorithms.fqe_sweeps.PolicyRead`)."""
    n, A = data.n, data.n_actions
    pi_next = np.asarray(backup.probabilities("next", 0), dtype=np.float64)
    i, a = np.nonzero(pi_next > 0)
    pick = sparse.csr_matrix((pi_next[i, a], (i, a * n + i)), shape=(n, A * n))
    return (pick @ op_next).tocsr()


#: leaf values whose change is taken at once in :func:`averaged_fixed_point` (bounded memory)
_CHANGE_CHUNK = 1 << 20


def averaged_fixed_point(data: Prepared, M: Any, P: Any, v: np.ndarray, tol: float | None, max_iterations: int,
                         rtol: float = 1e-7, in_place: bool = False) -> tuple[np.ndarray, int]:
    """:func:`fixed_point` with the policy's operator ``P`` (:func:`policy_operator`) given,
    so that the query operator it was made from need not be held through the sweeps.

    ``v`` is never written unless ``in_place`` (a float64, writable, contiguous ``v``): each
    sweep's values are then copied into ``v`` (returned), so that the sweeps hold two vectors
    of the leaves' size, not three (the starting values, the current and the new ones); the
    numbers are the same (the copy is exact). ``v`` holds the last completed sweep's values
    if the solve is interrupted."""
    v = np.asarray(v, dtype=np.float64)
    if in_place and not (v.flags.writeable and v.flags.c_contiguous):
        raise InvalidArgumentError("averaged_fixed_point(in_place=True) needs a writable, contiguous float64 v")
    if not len(v):
        return (v if in_place else v.copy()), 1
    buf = np.empty(min(len(v), _CHANGE_CHUNK))
    for sweep in range(1, max_iterations + 1):
        v_new = M @ data.targets(P @ v)  # the loop's own targets (c^- clamp included)
        change = _sup_change(v_new, v, buf, in_place)
        if in_place:
            del v_new  # copied into v
        else:
            v = v_new
        # an averager's backup is a sup-norm gamma-contraction: |v - v*| <= change * gamma / (1 - gamma)
        bound = change * data.gamma / (1.0 - data.gamma)
        if bound <= (tol if tol is not None else rtol * (data.cost_unit + max(float(v.max()), -float(v.min())))):
            return v, sweep
    return v, max_iterations


def _sup_change(v_new: np.ndarray, v: np.ndarray, buf: np.ndarray, copy: bool) -> float:
    """``max |v_new - v|`` (NaN as the whole vector's max and min give it), taken a chunk of
    ``buf``'s size at a time (no second vector of the leaves' size); with ``copy`` each chunk
    of ``v_new`` is then copied into ``v``."""
    ends = []
    for lo in range(0, len(v), _CHANGE_CHUNK):
        hi = min(lo + _CHANGE_CHUNK, len(v))
        d = np.subtract(v_new[lo:hi], v[lo:hi], out=buf[:hi - lo])
        ends.append((d.max(), d.min()))
        if copy:
            v[lo:hi] = v_new[lo:hi]
    e = np.array(ends)
    return max(float(e[:, 0].max()), -float(e[:, 1].min()))


#: entries of the per-action read whose state distances are computed at once (bounded memory)
_DIST_CHUNK = 1 << 20


def support_operators(data: Prepared, backup: PolicyBackup, learner: FrozenTreesLearner, ops: dict[str, Any] | None,
                      min_tree_share: float = 1e-9,
                      radius: float | None = None) -> tuple[Any, np.ndarray, Any, np.ndarray]:
    """The *per-action read* of the fitted forest at the pairs the backup queries, and
    what it cannot read.

    ``Q(x, a)`` of the joint (x, a) forest averages, over trees, the leaf ``x`` and ``a``
    reach, whatever actions that leaf's rows took (with Ernst's leaves of one or two rows,
    a leaf reached by ``(x', a)`` holds a row of ``a`` in ~60% of the trees on the driving
    logs): the value of another action's rows stands in for ``a``'s. The per-action read
    averages, per query, only the trees whose reached leaf holds rows of the queried
    action (each such leaf read as the mean over those rows); a query where fewer than
    ``min_tree_share`` of the trees have one is *unsupported*: the logs hold no row of
    that action near that state, and its value is left open.

    Returns ``(P, u, P0, u0)``: ``V(x'_i) = (P y)_i + u_i B`` over the training rows'
    targets ``y`` with the unsupported part valued ``B`` (``u_i`` = the policy's
    probability mass on unsupported actions at ``x'_i``); ``P0, u0`` the same at the start
    states. ``P`` and ``P0`` are sparse (n, n) and (n_start, n). ``ops``: the query operators
    (:func:`query_operators`) if held, else None: each action's rows are made when read
    (:func:`query_rows`; the same numbers).

    ``radius``: a row of the queried action counts only when its state lies within this
    distance of the queried state (Euclidean, in units of each feature's standard
    deviation): a leaf of one row may span a large part of the state space where the data
    is thin, and a row far away says little about the queried state."""
    n, A = data.n, data.n_actions
    acts = np.asarray(data.train.actions)
    w = np.ones(n) if learner.weights is None else np.asarray(learner.weights, dtype=np.float64)
    L = len(learner.leaf_ids)
    pos = learner.pos["train"]
    pi = {"next": np.asarray(backup.probabilities("next", 0), dtype=np.float64),
          "start": np.asarray(backup.probabilities("start", 0), dtype=np.float64)}
    nq = {"next": n, "start": len(data.start_obs)}
    P = {k: sparse.csr_matrix((nq[k], n)) for k in pi}
    u = {k: np.zeros(nq[k]) for k in pi}
    queried = {"next": data.train.next_obs, "start": data.start_obs}
    scale = np.where(data.obs_std > 0, data.obs_std, 1.0)
    for b in range(A):
        wb = np.where(acts == b, w, 0.0)
        sb = learner.leaf_weight_sums(wb)
        Mb = has = counts = None
        for k in pi:
            lo, hi = b * nq[k], (b + 1) * nq[k]  # action b's rows (without ops: made alone, not the whole operator)
            if radius is not None:
                counts = leaf_counts(learner, wb > 0) if counts is None else counts
                terms, entries = query_terms(learner.pos[k], slice(lo, hi), counts, L)
            if radius is not None and terms > MAX_PAIRS_PER_ENTRY * max(entries, 1):
                # leaves of many rows of b: the product's terms streamed, only the near pairs kept
                K = near_pairs(learner.pos[k], lo, pos, queried[k], data.obs, scale, wb, sb, radius, L,
                               pi[k][:, b] > 0)
                f = np.asarray(K.sum(axis=1)).reshape(-1)
            else:
                if Mb is None:
                    Mb = _averaging_matrix(pos, wb, sb, L)  # leaf -> mean over its rows of action b (0 without any)
                    Mb.eliminate_zeros()  # other actions' rows: no terms in the product (its sums are the same)
                    has = (sb > 0).astype(np.float64)
                K, f = _product_read(ops[k][lo:hi] if ops is not None else query_rows(learner, k, lo, hi), Mb, has,
                                     radius, queried[k], data.obs, scale)
            ok = f >= min_tree_share
            r = np.where(ok, 1.0 / np.where(ok, f, 1.0), 0.0) * pi[k][:, b]
            if np.any(r > 0):
                P[k] = P[k] + sparse.diags(r) @ K
            u[k] += np.where(ok, 0.0, pi[k][:, b])
    return P["next"].tocsr(), u["next"], P["start"].tocsr(), u["start"]


def bounded_value(data: Prepared, P: Any, u: np.ndarray, P0: Any, u0: np.ndarray, B: float,
                  start_weights: np.ndarray | None = None, rtol: float = 1e-6, max_iterations: int = 10_000) -> float:
    """The start value of the fixed point ``y = targets(P y + u B)`` (see
    :func:`support_operators`): the per-action read with every unsupported pair valued
    ``B``; ``start_weights`` weight the start states (default: equal)."""
    y = data.targets(u * B)
    for _ in range(max_iterations):
        y_new = data.targets(P @ y + u * B)
        change = float(np.max(np.abs(y_new - y))) if len(y) else 0.0
        y = y_new
        if change * data.gamma / (1.0 - data.gamma) <= rtol * (data.cost_unit + float(np.max(np.abs(y), initial=0.0))):
            break
    v0 = P0 @ y + u0 * B
    if start_weights is None:
        return float(v0.mean())
    w0 = np.asarray(start_weights, dtype=np.float64)
    return float(np.sum(w0 * v0) / np.sum(w0)) if np.sum(w0) > 0 else float("nan")


def support_radius(obs: np.ndarray, actions: np.ndarray, obs_std: np.ndarray, quantile: float = 0.99,
                   max_rows: int = 20_000, seed: int = 0) -> float:
    """The data's own spacing: the ``quantile`` of the distance from a logged state to the
    nearest other logged state of the same action (Euclidean in units of each feature's
    standard deviation), read at most ``max_rows`` rows per action drawn at random, each
    against *every* row of its action. A queried state farther than this from every row of
    the queried action lies where the logs are sparser than at 99% of their own rows
    (:func:`support_operators`' ``radius``).

    Only the rows whose distance is read are sampled: nearest neighbours among a sample of
    ``m`` of ``n`` rows lie ``(n / m) ** (1 / d)`` times farther than in the data (at 1M rows
    of car-on-the-hill 0.060 against 0.012), which made the radius, and the pairs the
    support bounds keep, grow with the data instead of shrinking."""
    from sklearn.neighbors import NearestNeighbors

    scale = np.where(obs_std > 0, obs_std, 1.0)
    rng = np.random.default_rng(seed)
    dists = []
    for b in np.unique(actions):
        X = obs[actions == b] / scale
        if len(X) < 2:
            continue
        Xq = X[rng.choice(len(X), max_rows, replace=False)] if len(X) > max_rows else X
        d, _ = NearestNeighbors(n_neighbors=2).fit(X).kneighbors(Xq)
        dists.append(d[:, 1])
    return float(np.quantile(np.concatenate(dists), quantile)) if dists else float("inf")


#: :func:`support_operators` with a radius builds ``Ab diag(has) Mb`` (every (query, tree, row
#: of b in the reached leaf) term) and keeps the pairs within the radius when it has at most
#: this many terms per query entry; beyond it (leaves of many rows: structures grown on a
#: bootstrap of the rows, ``structure_max_samples``; exactly repeated states) the terms are
#: streamed query by query and only the pairs within the radius kept (:func:`near_pairs`), so
#: the terms far from the query are never held (at 10M rows with 131,072-row structures ~150
#: rows a leaf: ~10^10 terms).
MAX_PAIRS_PER_ENTRY = 4.0


def _product_read(Ab: Any, Mb: Any, has: np.ndarray, radius: float | None, Xq: np.ndarray, Xt: np.ndarray,
                  scale: np.ndarray) -> tuple[Any, np.ndarray]:
    """``(K, f)`` of :func:`support_operators` from the product ``Ab diag(has) Mb``: every row of
    b in the reached leaves (``radius`` None), or only those within ``radius`` of the queried
    state; ``f`` the share of trees whose reached leaf holds such a row."""
    if radius is None:
        return Ab @ Mb, Ab @ has
    # Ab diag(has) Mb is Ab Mb: Mb's rows are empty where has is 0 (no row of b in the leaf;
    # the caller eliminated the zeros), so the same terms in the same order, without a scaled
    # copy of Ab held beside the product. Row sums: the share of trees with a row of b.
    K = (Ab @ Mb).tocsr()
    ptr, nnz = K.indptr, K.nnz
    near = np.empty(nnz, bool)
    for c0 in range(0, nnz, _DIST_CHUNK):  # (entries, features) temporaries a chunk at a time
        c1 = min(c0 + _DIST_CHUNK, nnz)
        r_ = np.searchsorted(ptr, np.arange(c0, c1), side="right") - 1  # each entry's query
        near[c0:c1] = np.sqrt(np.sum(((Xq[r_] - Xt[K.indices[c0:c1]]) / scale) ** 2, axis=1)) <= radius
    # the near entries kept in place, in their order (no (row, col) copy of the product)
    counts = np.zeros(K.shape[0], np.int64)
    filled = np.flatnonzero(np.diff(ptr) > 0)
    if len(filled):
        counts[filled] = np.add.reduceat(near, ptr[filled], dtype=np.int64)
    K = sparse.csr_matrix((K.data[near], K.indices[near], np.r_[0, np.cumsum(counts)]), shape=K.shape)
    return K, np.asarray(K.sum(axis=1)).reshape(-1)


def query_terms(pos_q: np.ndarray, cols: Any, counts: np.ndarray, L: int) -> tuple[int, int]:
    """``(terms, entries)`` of the queries ``cols`` of ``pos_q`` (trees, queries): the entries
    reaching a training leaf (< ``L``) and the rows those leaves hold (``counts``, ``L + 1`` per
    leaf, the last 0): the size of a product of their query operator with a leaf's rows
    (:func:`support_operators`' ``Ab diag(has) Mb``, the replicates' ``P_w M_w``)."""
    terms = entries = 0
    for t in range(pos_q.shape[0]):
        leaves = np.minimum(pos_q[t, cols], L)
        terms += int(counts[leaves].sum())
        entries += int(np.count_nonzero(leaves < L))
    return terms, entries


def leaf_counts(learner: FrozenTreesLearner, rows: np.ndarray) -> np.ndarray:
    """The ``rows`` (bool, the training rows') in each leaf, with a last 0 for position ``L``
    (no training leaf): :func:`query_terms`' ``counts``."""
    return np.append(np.rint(learner.leaf_weight_sums(rows.astype(np.float64))).astype(np.int64), 0)


def _near_terms(pos_q: Any, col0: int, qs: Any, m_ptr: Any, m_idx: Any, Xq: Any, Xt: Any, scale: Any, wb: Any,
                sb: Any, radius: float, inv_m: float, L: int, seen: Any, where: Any, out_ptr: Any, out_idx: Any,
                out_dat: Any) -> int:
    """The product ``Ab diag(has) Mb`` of :func:`support_operators` at queries ``qs``, streamed:
    for each query, tree by tree, the rows of b in its reached leaf (``m_ptr``, ``m_idx``), each
    row's distance taken once (``sqrt(sum(((x'_i - x_j) / scale)^2)) <= radius``, as the product
    path tests it) and, if near, ``inv_m * (wb_j / sb_leaf)`` added to its entry, in tree order
    (the product's terms, each the same IEEE product). Writes query ``qs[u]``'s entries at
    ``out_ptr[u] .. out_ptr[u + 1]`` (rows in first-reached order); ``seen[j]`` / ``where[j]``:
    the last query that met row j and its entry (-1: far). Returns the entries written."""
    nk = 0
    out_ptr[0] = 0
    D = Xq.shape[1]
    for u in range(len(qs)):
        i = qs[u]
        for t in range(pos_q.shape[0]):
            leaf = pos_q[t, col0 + i]
            if leaf >= L:
                continue
            s = sb[leaf]
            if not s > 0.0:
                continue
            for e in range(m_ptr[leaf], m_ptr[leaf + 1]):
                j = m_idx[e]
                if seen[j] != i:
                    seen[j] = i
                    d2 = 0.0
                    for f in range(D):
                        diff = (Xq[i, f] - Xt[j, f]) / scale[f]
                        d2 += diff * diff
                    if np.sqrt(d2) <= radius:
                        where[j] = nk
                        out_idx[nk] = j
                        out_dat[nk] = 0.0
                        nk += 1
                    else:
                        where[j] = -1
                w = where[j]
                if w >= 0:
                    out_dat[w] += inv_m * (wb[j] / s)
        out_ptr[u + 1] = nk
    return nk


_near_terms = _kernel(_near_terms, cache=True, nogil=True, boundscheck=False)

#: product terms a streamed chunk of :func:`near_pairs` may hold (its entry buffers: 12 bytes a term)
_NEAR_TERMS = 1 << 23


def near_pairs(pos_q: np.ndarray, col0: int, pos_t: np.ndarray, Xq: np.ndarray, Xt: np.ndarray, scale: np.ndarray,
               wb: np.ndarray, sb: np.ndarray, radius: float, L: int, need: np.ndarray | None = None) -> Any:
    """``Ab diag(has) Mb`` of :func:`support_operators` restricted to the pairs whose states are
    within ``radius`` (``Xq``, ``Xt``: the queried and the training states, distances in units
    of ``scale``; query ``i``'s leaves ``pos_q[:, col0 + i]``, row ``j``'s ``pos_t[:, j]``), as
    sparse (queries, rows), without making the product: each query's terms are streamed
    (:func:`_near_terms`) and only the pairs within the radius kept, queries a chunk of at most
    :data:`_NEAR_TERMS` terms at a time. Each kept entry sums the product's terms in tree order
    under the same distance test (rows sorted within each query; sums over a row may differ
    from the product path's in the last bit). ``need``: the queries whose rows are wanted (the policy's probability
    is positive); the others are left empty."""
    nq, n = len(Xq), len(Xt)
    rows_b = np.flatnonzero(wb > 0)
    if not len(rows_b) or not nq:
        return sparse.csr_matrix((nq, n))
    m_ptr, m_idx = leaf_rows(np.ascontiguousarray(pos_t[:, rows_b]), L)  # each leaf's rows of b
    m_idx = rows_b.astype(m_idx.dtype)[m_idx]
    counts = np.diff(m_ptr).astype(np.int64)
    counts = np.append(counts, 0)  # position L: no training leaf
    qs_all = np.arange(nq) if need is None else np.flatnonzero(need)
    terms = np.zeros(len(qs_all), np.int64)
    for t in range(pos_q.shape[0]):
        terms += counts[np.minimum(pos_q[t, col0 + qs_all], L)]
    seen, where = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
    sbf, wbf = np.asarray(sb, dtype=np.float64), np.asarray(wb, dtype=np.float64)
    Xq, Xt = np.ascontiguousarray(Xq, dtype=np.float64), np.ascontiguousarray(Xt, dtype=np.float64)
    sc = np.ascontiguousarray(scale, dtype=np.float64)
    row_nnz, idx_parts, dat_parts = np.zeros(nq, np.int64), [np.zeros(0, np.int64)], [np.zeros(0)]
    cum, lo = np.cumsum(terms), 0
    while lo < len(qs_all):
        base = cum[lo - 1] if lo else 0
        hi = max(lo + 1, int(np.searchsorted(cum, base + _NEAR_TERMS, side="right")))
        qs = qs_all[lo:hi]
        cap = int(cum[hi - 1] - base)
        ptr, idx, dat = np.empty(len(qs) + 1, np.int64), np.empty(cap, np.int64), np.empty(cap)
        nk = _near_terms(pos_q, col0, qs, m_ptr, m_idx, Xq, Xt, sc, wbf, sbf, float(radius), 1.0 / pos_q.shape[0], L,
                         seen, where, ptr, idx, dat)
        row_nnz[qs] = np.diff(ptr)
        idx_parts.append(idx[:nk].copy())
        dat_parts.append(dat[:nk].copy())
        lo = hi
    indptr = np.zeros(nq + 1, np.int64)
    np.cumsum(row_nnz, out=indptr[1:])
    K = sparse.csr_matrix((np.concatenate(dat_parts), np.concatenate(idx_parts), indptr), shape=(nq, n))
    K.sort_indices()
    return K
