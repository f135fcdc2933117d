"""The trajectory bootstrap of the importance-sampling family, read through sums over episodes.

Every estimator of :mod:`~offline_adp.evaluation.ope` is a function of a few sums over
episodes. With episode ``i`` drawn ``k_i`` times in a resample (``k_i = 1`` for the data
itself), an estimator reads ``S = sum_i k_i M_i`` for a per-episode matrix ``M`` (N, p) of its
own and returns ``f(S)``: IS is ``S / N`` with ``M_i = R_{i,T-1} G_i``; WPDIS is
``sum_t gamma^t S^{Rc}_t / S^R_t`` with ``M_i = (R_{i,t} c_{i,t}, R_{i,t})_t``; and so on
(each estimator's ``M`` and ``f`` are in :mod:`~offline_adp.evaluation.ope`).

A block of resamples is then one matrix product, ``K M`` with ``K`` (replicates x N) their
multiplicities, where indexing each resample's rows of the (N, T) matrices would copy
them once per replicate (``benchmarks/ope_bootstrap.py``). The resamples are drawn as
before, ``rng.integers(0, N, N)`` per replicate in order, so a seed gives the same
resamples; the replicates agree with the indexed ones to rounding (finite inputs: an
episode with a NaN or an infinity leaves no estimate, :func:`estimate_and_interval`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: Bytes of one block of resample multiplicities (replicates x episodes, float64).
BLOCK_BYTES = 32 * 2**20


def quantiles(reps: np.ndarray, level: float) -> tuple[float, float]:
    """The percentile interval of the finite replicates at ``level`` (NaN without any)."""
    reps = reps[np.isfinite(reps)]
    if not len(reps):
        return (float("nan"), float("nan"))
    return float(np.quantile(reps, (1 - level) / 2)), float(np.quantile(reps, (1 + level) / 2))


def nonfinite_episodes(M: np.ndarray, g: np.ndarray | None = None) -> int:
    """Episodes whose row of ``M`` (or entry of ``g``) is NaN or infinite."""
    bad = ~np.isfinite(M).all(axis=1)
    if g is not None:
        bad |= ~np.isfinite(g)
    return int(bad.sum())


def multiplicities(n: int, rng: np.random.Generator) -> np.ndarray:
    """One resample's episode multiplicities (float64, length ``n``): ``n`` episodes drawn with
    replacement as ``rng.integers(0, n, n)``, counted: the IS family's resamples and the FQE
    replicates' (:func:`~offline_adp.evaluation.ope.bootstrap_counts`) are drawn here."""
    return np.bincount(rng.integers(0, n, n), minlength=n).astype(np.float64)


def replicate_sums(M: np.ndarray, n_boot: int, rng: np.random.Generator,
                   g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """``S_b = sum_i k_{b,i} M_i`` (n_boot, p) for ``n_boot`` episode resamples with replacement
    (``k_b``: resample ``b``'s multiplicities, drawn from ``rng`` as ``rng.integers(0, N, N)``),
    and with ``g`` (N,) the same resamples' ``sum_i k_{b,i} g_i`` (n_boot,). The products run
    on one BLAS thread, so the sums do not depend on the thread count."""
    from threadpoolctl import threadpool_limits

    M = np.asarray(M, dtype=np.float64)
    n = M.shape[0]
    out = np.empty((n_boot, M.shape[1]))
    out_g = None if g is None else np.empty(n_boot)
    block = max(1, BLOCK_BYTES // (8 * max(n, 1)))
    with threadpool_limits(limits=1, user_api="blas"):
        for b0 in range(0, n_boot, block):
            K = np.stack([multiplicities(n, rng) for _ in range(b0, min(n_boot, b0 + block))])
            out[b0:b0 + len(K)] = K @ M
            if out_g is not None:
                out_g[b0:b0 + len(K)] = K @ np.asarray(g, dtype=np.float64)
    return out, out_g


def estimate_and_interval(M: np.ndarray, f: Callable[[np.ndarray], np.ndarray], n_boot: int, level: float,
                          rng: np.random.Generator, g: np.ndarray | None = None, nonfinite: int | None = None
                          ) -> tuple[float, tuple[float, float], tuple[float, float] | None]:
    """``f`` of the data's sums, and the percentile intervals of ``f`` over ``n_boot`` resamples
    and, with ``g`` (one logged cost per episode), of ``f - mean(g)`` on the same resamples
    (the paired difference). ``f`` maps sums (b, p) to b values. No interval (NaN, and no
    draws from ``rng``) with ``n_boot <= 0`` or fewer than 2 episodes; nothing at all (NaN
    everywhere, no draws) when an episode's ``M`` or ``g`` is not finite: a NaN or an
    infinity in one episode is in every resample's sums (``0 * inf`` is NaN), and the
    resamples that miss it would not estimate the same quantity. ``nonfinite``: those episodes'
    count if the caller has it (:func:`nonfinite_episodes`), else counted here."""
    M = np.asarray(M, dtype=np.float64)
    n = M.shape[0]
    nan = (float("nan"), float("nan"))
    if nonfinite_episodes(M, g) if nonfinite is None else nonfinite:
        return float("nan"), nan, (None if g is None else nan)
    est = float(f(M.sum(axis=0)[None, :])[0])
    if n_boot <= 0 or n < 2:
        return est, nan, (None if g is None else nan)
    S, Sg = replicate_sums(M, n_boot, rng, g)
    reps = f(S)
    if Sg is None:
        return est, quantiles(reps, level), None
    return est, quantiles(reps, level), quantiles(reps - Sg / n, level)


def ratio(num: np.ndarray, den: np.ndarray, fill: float = 0.0) -> np.ndarray:
    """``num / den`` where ``den > 0``, else ``fill`` (0: a step no resampled episode's weight
    reaches; NaN: a self-normalised estimate with no weight at all)."""
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), fill)
