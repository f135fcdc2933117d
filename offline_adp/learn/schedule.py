"""When a frozen-structure LEARN step builds, and how many trees each build grows.

:class:`FrozenSchedule` configures :class:`~offline_adp.learn.frozen.FrozenTreesLearner`:
the iterations that build a structure, the row fraction each build is grown on, an
optional screen (:class:`TreeScreen`: a few trees first, the whole forest only when the
greedy targets need it) and optional early builds (:class:`EarlyBuilds`: fewer trees for
builds whose error is damped before the fit ends). Measurements: docs/fqi-modes.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from offline_adp.errors import InvalidArgumentError
from offline_adp.learn.settle import Settle


@dataclass(frozen=True)
class TreeScreen:
    """How many trees a frozen build of fitted Q-iteration grows (:class:`FrozenTreesLearner`).

    A build first grows ``trees`` trees. It grows the regressor's full count only when
    :func:`screen_bias` -- the extra downward bias of the greedy targets
    ``min_a' Q(x', a')`` from averaging fewer trees, carried through the horizon
    ``1 / (1 - gamma)``, relative to ``std(y)`` -- exceeds ``tol`` (or is NaN). ``rows``
    marks the next states whose value enters the targets (None: all). No screen (the whole
    forest at once) with ``tol = 0``, ``gamma >= 1``, one action, a forest of at most
    ``trees`` trees, or a regressor without ``warm_start``.
    """

    trees: int
    tol: float
    gamma: float
    rows: np.ndarray | None = None


@dataclass(frozen=True)
class EarlyBuilds:
    """How many trees a frozen build grows when little of its error reaches the final Q.

    The error of fitted Q-iteration's last iterate is bounded by the errors of its LEARN
    steps, each carried by ``gamma`` per later iteration: ``sup|Q_K - Q*| <= sum_j
    gamma^(K - j) eps_j + gamma^K sup|Q_0 - Q*|`` (the chapter's approximate value iteration
    bound). A frozen structure built at ``s`` serves the iterations ``s .. e`` up to the
    next build, so its weight in that bound is ``W(s, e) = sum_{j=s..e} gamma^(K - j)``.
    A build whose weight is less than ``ratio`` of the last build's
    (:func:`build_weight`) grows ``trees`` trees instead of the whole forest: its Monte
    Carlo error is damped before the fit ends. The last build always grows the whole
    forest. ``n_iterations`` is K. Opt-in (``FittedQIteration(early_build_trees=...)``):
    the bound damps an early structure's error in the values, but not in the later
    structures, which are grown on the targets it produced; it did not hold the score
    on every problem (docs/fqi-modes.md).
    """

    trees: int
    gamma: float
    n_iterations: int
    ratio: float = 0.5
    #: instead of the weights: every build before the last scheduled one (the settling
    #: schedule of ``n_iterations="auto"``, whose last structure is solved to its own fixed point)
    before_last: bool = False


def build_weight(k: int, schedule: Sequence[int], gamma: float, n_iterations: int) -> float:
    """``W(k, e) / W(s_last, K)``: how much of the error of a structure built at iteration
    ``k`` (serving up to ``e``, the iteration before the next scheduled build, or ``K``)
    reaches the final Q, relative to the last scheduled build's, where ``W(s, e) =
    sum_{j=s..e} gamma^(K - j)`` (see :class:`EarlyBuilds`). 1 for a build at or after the
    last scheduled one."""
    K = int(n_iterations)
    sched = sorted(int(s) for s in schedule)
    later = [s for s in sched if s > k]
    if not later or k >= K:
        return 1.0

    def W(s: int, e: int) -> float:
        j = np.arange(s, e + 1, dtype=np.float64)
        return float(np.sum(gamma ** (K - j)))

    return W(k, later[0] - 1) / W(min(sched[-1], K), K)


def greedy_min_bias(gap: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """``min(mu_a, mu_b) - E[min(X_a, X_b)] >= 0`` when ``X_b - X_a ~ N(gap, tau^2)``, ``gap >= 0``:
    how far a min over two noisy estimates falls below the min of their means,
    ``tau * pdf(gap / tau) - gap * cdf(-gap / tau)`` (0 where ``tau = 0``).

    This is the bias a greedy backup ``min_a' Q(x', a')`` picks up from Monte Carlo noise in
    ``Q`` (the downward counterpart of Q-learning's max bias); a forest of ``m`` trees whose
    per-tree gaps spread by ``sd`` has ``tau = sd / sqrt(m)``.
    """
    from scipy.special import ndtr

    gap, tau = np.asarray(gap, dtype=np.float64), np.asarray(tau, dtype=np.float64)
    safe = np.where(tau > 0, tau, 1.0)
    z = gap / safe
    out = safe * np.exp(-0.5 * z * z) / np.sqrt(2.0 * np.pi) - gap * ndtr(-z)
    return np.where(tau > 0, np.maximum(out, 0.0), 0.0)


def screen_bias(screen: TreeScreen, next_pos: np.ndarray, leaf_means: np.ndarray, n_actions: int,
                weights: np.ndarray | None, y: np.ndarray, full: int) -> float:
    """How much the greedy targets would lose by keeping the screen's trees instead of
    all ``full``: at every bootstrapped next state, :func:`greedy_min_bias` of the best
    action (under the screen's trees) against each other action, from their per-tree
    gaps, summed over the other actions (a union bound: exact with two actions, an upper
    bound with more); averaged with the sample weights, carried through the horizon
    ``1 / (1 - gamma)`` and divided by the (weighted) standard deviation of ``y``.

    ``next_pos``: the next-state queries' compact leaf positions, tree-major (m, n_actions * n,
    action-major), position ``len(leaf_means)`` for a leaf without training rows;
    ``leaf_means``: the (weighted) mean of ``y`` in each compact leaf."""
    s = screen
    P, A = next_pos, n_actions
    m, n = P.shape[0], P.shape[1] // A
    vals = np.r_[leaf_means, 0.0]
    rows = np.arange(n) if s.rows is None else np.flatnonzero(s.rows)
    w = np.ones(n) if weights is None else weights
    total = 0.0
    for lo in range(0, len(rows), 32_768):  # bounded temporaries at any size
        r = rows[lo:lo + 32_768]
        per_tree = vals[P[:, (np.arange(A)[:, None] * n + r).ravel()]].reshape(m, A, len(r))  # action-major queries
        j = np.arange(len(r))
        best = np.argmin(per_tree.mean(axis=0), axis=0)
        shortfall = np.zeros(len(r))
        for other in range(A):
            d = per_tree[:, other, j] - per_tree[:, best, j]  # per-tree gap (0 where other is the best)
            gap, sd = d.mean(axis=0), d.std(axis=0, ddof=1)
            shortfall += greedy_min_bias(gap, sd / np.sqrt(m)) - greedy_min_bias(gap, sd / np.sqrt(full))
        total += float(shortfall @ w[r])
    wr = w[rows]
    mean = float(np.average(y, weights=w))
    std = float(np.sqrt(np.average((y - mean) ** 2, weights=w)))
    scale = std * (1.0 - s.gamma) * float(wr.sum())
    return total / scale if scale > 0 else 0.0


def check_structure_fractions(value: Any) -> None:
    """Raise ValueError unless ``value`` is a row fraction in (0, 1], None, or a list of those
    (the frozen structures' ``max_samples``)."""
    fractions = list(value) if isinstance(value, list | tuple) else [value]
    if not all(f is None or (isinstance(f, int | float) and not isinstance(f, bool) and 0.0 < float(f) <= 1.0)
               for f in fractions):
        raise InvalidArgumentError(f"structure_max_samples must be 'auto', a fraction in (0, 1], None, or a list of "
                         f"fractions/None, got {value!r}")


@dataclass(frozen=True)
class FrozenSchedule:
    """How :class:`~offline_adp.learn.frozen.FrozenTreesLearner` builds its structures.

    Parameters
    ----------
    restructure_at : tuple of int
        Iterations that build a structure (iteration 1 always does).
    max_samples : float, sequence of (float or None), or None
        Row fraction each structure is grown on (a bootstrap sample; None: all rows), or
        one per scheduled build.
    screen : TreeScreen, optional
    early : EarlyBuilds, optional
    settle : Settle, optional
        Extrapolate the final structure's iteration (:mod:`offline_adp.learn.settle`).
    builder : {"auto", "sklearn"}
        ``"auto"``: the compiled builder (:mod:`offline_adp.trees.builder`) where it
        implements the regressor's settings; ``"sklearn"``: always scikit-learn.
    target_unit : float
        The size of the costs (:attr:`~offline_adp.algorithms.fqi_data.Prepared.cost_unit`):
        the unit of the tie jitter, ``1e-6 (target_unit + std(y))``.
    """

    restructure_at: tuple[int, ...] = (1,)
    max_samples: float | Sequence[float | None] | None = None
    screen: TreeScreen | None = None
    early: EarlyBuilds | None = None
    builder: str = "auto"
    settle: Settle | None = None
    target_unit: float = 1.0

    def __post_init__(self) -> None:
        if not (0.0 < self.target_unit < np.inf):
            raise InvalidArgumentError(f"target_unit must be positive and finite, got {self.target_unit!r}")
        if self.builder not in ("auto", "sklearn"):
            raise InvalidArgumentError(f"tree_builder must be 'auto' or 'sklearn', got {self.builder!r}")
        check_structure_fractions(self.max_samples)

    @property
    def builds(self) -> frozenset[int]:
        """The scheduled build iterations (always including 1)."""
        return frozenset(self.restructure_at) | {1}

    def fraction(self, k: int) -> float | None:
        """The row fraction the structure built at iteration ``k`` is grown on (None: all):
        ``max_samples``, or its entry for the last scheduled build at or before ``k``."""
        if not isinstance(self.max_samples, list | tuple):
            return self.max_samples
        j = sum(1 for s in sorted(self.builds) if s <= k) - 1
        return self.max_samples[min(max(j, 0), len(self.max_samples) - 1)] if self.max_samples else None


