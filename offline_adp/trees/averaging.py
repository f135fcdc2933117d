"""Threaded kernels of the frozen-structure averager: leaf sums and means over trees.

With a tree structure frozen, one iteration of fitted Q-iteration is two passes over
tree-major int32 leaf positions (:class:`~offline_adp.learn.frozen.FrozenTreesLearner`):

- :func:`leaf_sums`: ``sum of v_i`` over the training rows in each leaf, tree by tree
  (each tree's leaves are their own range of the output);
- :func:`tree_mean`: ``mean over trees of values[pos[t, j]]`` for every query ``j``.

Both run in ``n_jobs`` threads on kernels compiled by numba that release the GIL: the
sums split by tree, the means by query chunk. Every number is summed in the same order
whatever the number of threads (a leaf's rows in row order, as ``np.bincount``; a query's
trees in tree order, as a running numpy sum), so the result is bit-for-bit the one of
one thread and of the plain numpy reference (used where numba is missing).
:func:`thread_map` is the shared pool helper.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from offline_adp.trees.jit import available, kernel

#: fewest queries per thread of :func:`tree_mean`
MEAN_CHUNK = 16_384


def resolve_n_jobs(n_jobs: Any) -> int:
    """``n_jobs`` as a thread count, scikit-learn's way: None -> 1, -1 -> every core this
    process may run on (joblib's count: CPU affinity and cgroup quotas), -2 -> all but one."""
    if n_jobs is None:
        return 1
    from joblib import effective_n_jobs

    try:
        return max(1, int(effective_n_jobs(int(n_jobs))))
    except (TypeError, ValueError):
        return 1


def thread_map(fn: Callable[[Any], Any], items: Iterable[Any], n_jobs: int) -> list[Any]:
    """``[fn(x) for x in items]``, in ``n_jobs`` threads when that is more than one (results
    in the order of ``items``; ``fn`` must not depend on which thread runs it)."""
    items = list(items)
    if n_jobs <= 1 or len(items) <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(max_workers=min(n_jobs, len(items))) as pool:
        return list(pool.map(fn, items))


def _libc_trim() -> Any:
    try:
        import ctypes

        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):  # not glibc
        return None


_TRIM = _libc_trim()


def release_freed() -> None:
    """Return the C heap's free pages to the system (glibc's ``malloc_trim``; nothing
    elsewhere): the large temporaries freed by a structure's lookups would otherwise stay
    in the process's arenas, and each build would add to the peak of the next."""
    if _TRIM is not None:
        _TRIM(0)


def _split(n: int, parts: int, least: int = 1) -> list[tuple[int, int]]:
    """``[0, n)`` as at most ``parts`` contiguous ranges of at least ``least`` items."""
    parts = max(1, min(parts, n // max(least, 1) or 1))
    edges = np.linspace(0, n, parts + 1).astype(np.int64)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


# ----------------------------------------------------------------------------- kernels


def _sums_kernel(pos: Any, bounds: Any, v: Any, t0: int, t1: int, out: Any, zero: bool) -> None:
    """``out[bounds[t] + k] = sum of v_i over i with pos[t, i] == bounds[t] + k`` for trees
    ``t0..t1-1``, rows in order (``np.bincount``'s order); ``zero=False``: added to what
    ``out`` holds (the sums continued over more rows)."""
    n = pos.shape[1]
    for t in range(t0, t1):
        if zero:
            for k in range(bounds[t], bounds[t + 1]):
                out[k] = 0.0
        for i in range(n):
            out[pos[t, i]] += v[i]


def _sums_reuse_kernel(nxt: Any, src: Any, rest: Any, bounds: Any, v: Any, t0: int, t1: int, out: Any) -> None:
    """:func:`_sums_kernel` with row ``i``'s position read from ``nxt[t, src[i]]`` where
    ``src[i] >= 0`` and from the next column of ``rest[t]`` otherwise (rows in order)."""
    n = len(src)
    for t in range(t0, t1):
        for k in range(bounds[t], bounds[t + 1]):
            out[k] = 0.0
        j = 0
        for i in range(n):
            s = src[i]
            if s >= 0:
                out[nxt[t, s]] += v[i]
            else:
                out[rest[t, j]] += v[i]
                j += 1


def _mean_kernel(values: Any, pos: Any, j0: int, j1: int, out: Any) -> None:
    """``out[j] = (((0 + values[pos[0, j]]) + values[pos[1, j]]) + ...) / m`` for queries
    ``j0..j1-1`` (tree order, as a running numpy sum)."""
    m = pos.shape[0]
    acc = np.zeros(j1 - j0)
    for t in range(m):
        for j in range(j0, j1):
            acc[j - j0] += values[pos[t, j]]
    for j in range(j0, j1):
        out[j] = acc[j - j0] / m


_sums_kernel = kernel(_sums_kernel, cache=True, nogil=True, boundscheck=False)
_sums_reuse_kernel = kernel(_sums_reuse_kernel, cache=True, nogil=True, boundscheck=False)
_mean_kernel = kernel(_mean_kernel, cache=True, nogil=True, boundscheck=False)


def leaf_sums(pos: np.ndarray, bounds: np.ndarray, v: np.ndarray, n_jobs: int = 1,
              carry: np.ndarray | None = None) -> np.ndarray:
    """``sum of v_i`` over the rows in each leaf, for tree-major compact leaf positions
    ``pos`` (m, n) (tree ``t``'s leaves are ``[bounds[t], bounds[t + 1])``, every position
    in its tree's range); trees split over ``n_jobs`` threads. Bit-for-bit
    ``np.bincount(pos[t] - bounds[t], weights=v)`` per tree. ``carry``: sums over earlier
    rows, continued by these rows in order (so sums taken block after block are the sums
    over all the rows, bit for bit; the Dask engine's segments)."""
    m = pos.shape[0]
    bounds = np.asarray(bounds, dtype=np.int64)
    out = np.empty(int(bounds[-1])) if carry is None else np.array(carry, dtype=np.float64)
    v = np.ascontiguousarray(v, dtype=np.float64)
    if not available():
        for t in range(m):
            lo, hi = int(bounds[t]), int(bounds[t + 1])
            if carry is None:
                out[lo:hi] = np.bincount(pos[t] - lo, weights=v, minlength=hi - lo)
            else:  # in row order, continuing the carried sums (np.add.at is unbuffered, in order)
                np.add.at(out, pos[t], v)
        return out
    zero = carry is None
    thread_map(lambda r: _sums_kernel(pos, bounds, v, r[0], r[1], out, zero), _split(m, n_jobs), n_jobs)
    return out


def gather_positions(nxt: np.ndarray, src: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """The (m, len(src)) positions :func:`leaf_sums_reuse` reads: column ``i`` is
    ``nxt[:, src[i]]`` where ``src[i] >= 0``, else the next column of ``rest``."""
    out = np.empty((rest.shape[0], len(src)), dtype=rest.dtype)
    reused = src >= 0
    out[:, reused] = nxt[:, src[reused]]
    out[:, ~reused] = rest
    return out


def leaf_sums_reuse(nxt: np.ndarray, src: np.ndarray, rest: np.ndarray, bounds: np.ndarray, v: np.ndarray,
                    n_jobs: int = 1) -> np.ndarray:
    """:func:`leaf_sums` of the positions :func:`gather_positions` would make, without
    making them: row ``i``'s position in tree ``t`` is ``nxt[t, src[i]]`` where ``src[i] >= 0``
    (a training row whose leaves are those of a next-state query), else the next column of
    ``rest[t]`` (m, rows with ``src < 0``). Rows summed in order: bit-for-bit the same sums."""
    m = rest.shape[0]
    bounds = np.asarray(bounds, dtype=np.int64)
    v = np.ascontiguousarray(v, dtype=np.float64)
    src = np.ascontiguousarray(src, dtype=np.int64)
    if not available():
        return leaf_sums(gather_positions(nxt, src, rest), bounds, v, 1)
    out = np.empty(int(bounds[-1]))
    thread_map(lambda r: _sums_reuse_kernel(nxt, src, rest, bounds, v, r[0], r[1], out), _split(m, n_jobs), n_jobs)
    return out


def tree_mean(values: np.ndarray, pos: np.ndarray, n_jobs: int = 1) -> np.ndarray:
    """``values[pos].mean(axis=0)`` for tree-major ``pos`` (m, nq) without an (m, nq) float
    temporary, query chunks over ``n_jobs`` threads; the trees of a query summed in tree
    order (bit-for-bit a running numpy sum over trees, then ``/ m``). Every position must
    be in range: nothing is checked."""
    m, nq = pos.shape
    if not available():
        out, tmp = np.zeros(nq), np.empty(nq)
        for row in pos:  # "clip" skips numpy's buffered bounds check (~2x)
            values.take(row, out=tmp, mode="clip")
            out += tmp
        return out / m
    out = np.empty(nq)
    values = np.ascontiguousarray(values, dtype=np.float64)
    # one contiguous range of queries per thread, each tree's gathers over the whole range
    # (within that tree's leaves: they stay in cache across the range)
    ranges = _split(nq, n_jobs, MEAN_CHUNK)

    def run(r: tuple[int, int]) -> None:
        _mean_kernel(values, pos, r[0], r[1], out)

    thread_map(run, ranges, n_jobs)
    return out
