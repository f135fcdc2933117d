"""How one fitted-Q step ``Q_k = LEARN({(x_i, a_i), y_i})`` is carried out.

Fitted Q-iteration and fitted Q evaluation share the same inner step; what differs is
the targets. A *learner* owns the regression inputs of the training pairs and of every
query set the algorithm needs (next states for the targets, start states, held-out
pairs) and answers ``fit(y)`` then ``predict(name)``:

- :class:`RefitLearner` (the naive loop): clone and fit the regressor on every
  iteration; prediction is one batched call per query set.
- :class:`FrozenTreesLearner` (Ernst et al. 2005, section 4.3): fit a tree ensemble's
  *structure* once (and again on demand), precompute the leaf reached by every training
  and query input, and thereafter only re-average leaf values: an O(n * trees) gather,
  no tree fitting or traversal. With a fixed structure the update is a kernel averager,
  hence a gamma-contraction: it converges.
- :class:`LightGBMWarmStartLearner`: each iteration adds a few boosted trees fitted to
  the change in targets, with the previous Q's predictions on the fixed training and
  query inputs cached, so only the new trees are evaluated.

Query sets are ``(phi, actions)`` pairs: ``actions=None`` asks for all actions
(result (m, n_actions)), otherwise for the given action per row (result (m,)).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np
from sklearn.base import clone

from offline_adp import extra_trees
from offline_adp.qfunctions import (
    QEncoder,
    QFunction,
    RegressorQ,
    TreeEnsemble,
    TreeQ,
    predict_model,
    sklearn_tree,
    sklearn_tree_from_records,
)

Query = tuple[np.ndarray, np.ndarray | None]


def _seeded(model: Any, seed: int) -> Any:
    if "random_state" in model.get_params():
        model.set_params(random_state=seed)
    return model


def _fit(model: Any, X: np.ndarray, y: np.ndarray, w: np.ndarray | None) -> Any:
    if w is None:
        return model.fit(X, y)
    try:
        return model.fit(X, y, sample_weight=w)
    except TypeError:  # pipelines route weights by step name
        last = model.steps[-1][0]
        return model.fit(X, y, **{f"{last}__sample_weight": w})


class Learner:
    """Base: training pairs ``(phi, actions)``, weights, and named query sets."""

    def __init__(self, regressor: Any, encoder: QEncoder, phi: np.ndarray, actions: np.ndarray,
                 queries: dict[str, Query], weights: np.ndarray | None = None, seed: int = 0) -> None:
        self.regressor, self.encoder = regressor, encoder
        self.phi, self.actions, self.weights, self.seed = phi, np.asarray(actions, dtype=np.int64), weights, seed
        self.queries = {"train": (phi, self.actions), **queries}

    def fit(self, y: np.ndarray, k: int) -> None:
        """``Q_k = LEARN({((x_i, a_i), y_i)})``; iteration ``k``'s randomness depends on ``k`` only."""
        raise NotImplementedError

    def predict(self, name: str) -> np.ndarray:
        raise NotImplementedError

    def snapshot(self) -> QFunction:
        """The current Q as a standalone Q-function."""
        raise NotImplementedError

    def restore(self, q: QFunction, iteration: int, rows: list[dict[str, Any]] | None = None) -> None:
        """Continue from a saved ``Q_k`` (iteration ``k`` done; ``rows``: the history 1..k)."""
        raise NotImplementedError(f"{type(self).__name__} cannot resume")

    def state(self) -> dict[str, Any]:
        """Extra per-iteration facts for the history row (e.g. the structures built)."""
        return {}

    @staticmethod
    def _select(q_all: np.ndarray, actions: np.ndarray | None) -> np.ndarray:
        return q_all if actions is None else q_all[np.arange(len(actions)), actions]


class RefitLearner(Learner):
    """Clone and refit LEARN on every iteration (any scikit-learn regressor).

    Per iteration the loop needs ``Q_k`` at every next state for every action (the next
    targets); that is the one large prediction, as in any FQI. The diagnostics also read
    ``Q_k`` on the training pairs and at the start states, but logged transitions mostly
    continue each other (``x_i == x'_j`` for some j, usually ``j = i - 1``, in any row
    order), so those values are *read* from the next-state predictions wherever the
    regression input is bitwise the same, and only the remaining distinct inputs (episode
    starts, mostly) are predicted, for all actions at once: ~1-2% extra rows instead of
    +50% (one value per training pair). Predictions are cached per iteration.
    Registry forests (``extra_trees``, ``random_forest``) fit on all cores but predict on
    one thread unless ``n_jobs`` was given (:mod:`offline_adp.regressors`): the fitted
    models' ``n_jobs`` is set to 1.
    """

    _DERIVED = ("train", "start")  # query sets read from the next-state predictions where possible

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._cache: dict[str, np.ndarray] = {}
        self._predict_jobs = getattr(self.regressor, "_oadp_predict_jobs", None)  # see regressors._predict_on_one_thread
        self._source: dict[str, np.ndarray] = {}  # query -> row of [next; extra] holding each row's input
        if "next" not in self.queries:
            return
        base = self.queries["next"][0]
        derived = [n for n in self._DERIVED if n in self.queries and self.queries[n][0].shape[1:] == base.shape[1:]]
        if not derived:
            return
        idx, extra = _row_sources(base, [self.queries[n][0] for n in derived])
        self._source = dict(zip(derived, idx, strict=True))
        self.queries["extra"] = (extra, None)  # distinct inputs not among the next states

    def fit(self, y: np.ndarray, k: int) -> None:
        seed = self.seed + k
        if self.encoder.per_action:
            models = []
            for a in range(self.encoder.n_actions):
                rows = self.actions == a
                m = _seeded(clone(self.regressor), seed)
                if not rows.any():
                    raise ValueError(f"action {a} never occurs in the data: a per-action model cannot be fitted")
                models.append(_fit(m, self.phi[rows], y[rows], None if self.weights is None else self.weights[rows]))
        else:
            m = _seeded(clone(self.regressor), seed)
            models = [_fit(m, self.encoder.pairs(self.phi, self.actions), y, self.weights)]
        if self._predict_jobs is not None:
            for m in models:
                if hasattr(m, "estimators_") and hasattr(m, "n_jobs"):
                    m.n_jobs = self._predict_jobs
        self.q = RegressorQ(models, self.encoder)
        self._cache = {}

    def predict(self, name: str) -> np.ndarray:
        if name not in self._cache:
            phi, actions = self.queries[name]
            if name in self._source:  # all actions of each row, read from [Q(next); Q(extra)]
                if "_table" not in self._cache:
                    self._cache["_table"] = np.concatenate([self.predict("next"), self.predict("extra")])
                self._cache[name] = self._select(self._cache["_table"][self._source[name]], actions)
            elif len(phi) == 0:
                self._cache[name] = np.zeros((0, self.encoder.n_actions)) if actions is None else np.zeros(0)
            elif actions is not None and not self.encoder.per_action:
                self._cache[name] = predict_model(self.q.models[0], self.encoder.pairs(phi, actions))
            else:
                self._cache[name] = self._select(self.q.values_phi(phi), actions)
        return self._cache[name]

    def snapshot(self) -> QFunction:
        return self.q

    def restore(self, q: QFunction, iteration: int, rows: list[dict[str, Any]] | None = None) -> None:
        self.q, self._cache = q, {}  # type: ignore[assignment]


def _row_sources(base: np.ndarray, sets: list[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """For each row of each array in ``sets``: its index in ``[base; extra]`` where that
    row is bitwise equal to the input there; ``extra`` holds the distinct rows found in
    no ``base`` row (one sort over all rows, once per fit)."""
    d = base.shape[1] if base.ndim == 2 else 1
    rows = np.ascontiguousarray(np.concatenate([base.reshape(len(base), d), *(s.reshape(len(s), d) for s in sets)]),
                                dtype=np.float64)
    keys = rows.view(np.dtype((np.void, 8 * d))).ravel()
    _, first, inv = np.unique(keys, return_index=True, return_inverse=True)
    n = len(base)
    in_base = first < n  # np.unique's first occurrence: a base row whenever the key is in base
    new = np.flatnonzero(~in_base)  # distinct keys found only in the other sets
    where = first.copy()
    where[new] = n + np.arange(len(new))
    extra = rows[first[new]]
    out, lo = [], n
    for s in sets:
        out.append(where[inv[lo:lo + len(s)]])
        lo += len(s)
    return out, extra.reshape((len(extra),) + base.shape[1:])


@dataclass(frozen=True)
class TreeScreen:
    """How many trees a frozen build of fitted Q-iteration grows (:class:`FrozenTreesLearner`).

    A build first grows ``trees`` trees. It grows the regressor's full count only when
    :meth:`FrozenTreesLearner._screen_bias` -- the extra downward bias of the greedy targets
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
    structures, which are grown on the targets it produced; CartPole-v1 at gamma 0.95
    lost score with it (docs/fqi-modes.md).
    """

    trees: int
    gamma: float
    n_iterations: int
    ratio: float = 0.5


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


class FrozenTreesLearner(Learner):
    """Fixed tree structure, leaf values re-averaged each iteration (joint encoding only).

    Ernst, Geurts & Wehenkel (2005), "Tree-based batch mode reinforcement learning",
    JMLR 6, section 4.3: with the tree structure frozen, fitted Q-iteration is a kernel
    averager and converges. Update rule, with the structure built at iteration ``s``::

        structure_s = LEARN({((x_i, a_i), y_s,i)})         (at s in restructure_at)
        v_k = M @ y_k              M[leaf, i] = w_i / (sum of w of the training rows in the leaf)
        Q_k(query) = mean over trees of v_k[leaf of the query in that tree]

    The structure is (re)built at the iterations in ``restructure_at`` (and at the next
    iteration whenever the targets were constant, e.g. the first targets of a problem with
    one cost per step: LEARN on constant targets is that constant, represented by one-leaf
    trees, and says nothing about where to split). A build grows the ensemble on that
    iteration's targets (plus a tiny jitter, std ``1e-6 * (1 + std(y))``, only when the
    targets have ties, so that tied nodes still split (scikit-learn's trees do not always:
    see :mod:`offline_adp.extra_trees`); without ties a build on all rows by scikit-learn,
    ``builder="sklearn"``, is exactly the refit step; the default compiled
    builder, :mod:`offline_adp.extra_trees`, grows the same algorithm's trees from other
    random draws) -- each tree on a bootstrap sample of ``max_samples`` of
    the rows if given -- and looks up the leaf of every training and query input once
    (training rows that continue the previous row reuse the next-state lookups). Leaves
    are then *honest*: each leaf's value is the weighted mean target over **all** training
    rows falling in it, not only the rows its tree was grown on. The scikit-learn forest is
    dropped after the lookups (the arrays of :class:`~offline_adp.qfunctions.TreeEnsemble`
    remain). With a ``screen`` (:class:`TreeScreen`; opt-in, ``FittedQIteration(screen_trees=...)``) a build
    first grows ``screen.trees`` trees and grows the rest of the forest (scikit-learn's warm
    start: the same trees a one-shot fit grows) only when the greedy targets would be
    measurably biased by the smaller forest (:func:`greedy_min_bias`, carried through
    ``1 / (1 - gamma)``, above ``screen.tol * std(y)``). With ``early``
    (:class:`EarlyBuilds`; opt-in) a build whose error is damped before the fit ends
    (:func:`build_weight` below ``early.ratio``) grows only ``early.trees`` trees.
    An iteration is one bincount per tree over the tree-major (trees, n) leaf
    matrix and one gather per tree (each within that tree's leaves, so cache-sized): no
    tree fitting, no traversal.
    With a fixed structure the update is a gamma-contraction, so it converges -- to the
    fixed point of *that* averager, which is only as good as the structure: a structure
    fitted to early targets cannot represent what later targets need.

    Measured (``benchmarks/fqi_suite.py``, see the ``mode`` notes of
    :class:`~offline_adp.algorithms.fqi.FittedQIteration`): 4 evenly spaced builds on all
    rows hold the refit score on car-on-the-hill, Acrobot and path tracking at ~1/10 of its
    CPU but not on CartPole with 10k transitions (~210-240 vs ~380-440). Structures grown
    on 1/8 of the rows (``max_samples=0.125``, 8-16 builds) bring CartPole to ~350-390 at
    the same CPU but lose Acrobot (~-200 vs -131) and path tracking (-11.7 vs -5.8): leaves
    averaging ~8 rows are too coarse there. Cheap early builds with the last ones on all
    rows (``max_samples=[0.125] * 7 + [1.0] * 3``, 10 builds) held all four at 10k
    transitions, at 0.11-0.14 of refit's CPU; at 50k transitions CartPole scored 466 +- 20
    (4 builds on all rows: 452 +- 57) against refit's 496 +- 7, at 0.06-0.07 of its CPU; 8 builds on all rows (the default
    schedule of ``FittedQIteration``, one per 12.5 iterations) 498 +- 3 at ~0.10.
    """

    def __init__(self, *args: Any, restructure_at: tuple[int, ...] = (1,),
                 max_samples: float | Sequence[float | None] | None = None, screen: TreeScreen | None = None,
                 early: EarlyBuilds | None = None, builder: str = "auto", **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if builder not in ("auto", "sklearn"):
            raise ValueError(f"tree_builder must be 'auto' or 'sklearn', got {builder!r}")
        self.builder = builder
        self.grown_by: str | None = None  # who grew the last build: "compiled", "scikit-learn" (None: constant)
        if self.encoder.per_action:
            raise ValueError("the frozen-structure mode needs action_encoding='joint'")
        check_structure_fractions(max_samples)
        self.restructure_at = frozenset(restructure_at) | {1}
        self.max_samples = max_samples
        self.screen = screen
        self.early = early
        self.screen_value: float | None = None  # the last build's screen (None: not screened)
        self._pending = True  # no structure yet
        self.structures = 0
        self.built_on_constant = False
        phi_next = self.queries["next"][0] if "next" in self.queries else None
        same = np.zeros(len(self.phi), bool)
        if phi_next is not None and len(self.phi) > 1 and phi_next.shape == self.phi.shape:
            same[1:] = (self.phi[1:] == phi_next[:-1]).all(axis=1)
        self.reuse = np.flatnonzero(same)  # training row i's input is next-query row i - 1's (with a_i)
        self._cache: dict[str, np.ndarray] = {}

    def fraction(self, k: int) -> float | None:
        """The row fraction the structure built at iteration ``k`` is grown on (None: all):
        ``max_samples``, or its entry for the last scheduled build at or before ``k``."""
        if not isinstance(self.max_samples, list | tuple):
            return self.max_samples
        j = sum(1 for s in sorted(self.restructure_at) if s <= k) - 1
        return self.max_samples[min(max(j, 0), len(self.max_samples) - 1)] if self.max_samples else None

    def _structure_model(self, k: int) -> Any:
        model = _seeded(clone(self.regressor), self.seed + k)
        f = self.fraction(k)
        if f is not None and f < 1.0:
            if "max_samples" not in model.get_params():
                raise ValueError(f"structure max_samples needs a bagging tree ensemble (extra_trees, random_forest), "
                                 f"not {type(model).__name__}")
            model.set_params(bootstrap=True, max_samples=float(f))
        return model

    def _build(self, y: np.ndarray, k: int) -> None:
        X = self.encoder.pairs(self.phi, self.actions)
        self.structures += 1
        self.built_on_constant = bool(np.ptp(y) == 0.0)
        self.screen_value = None
        if self.built_on_constant:  # LEARN on constant targets is that constant: one leaf per tree
            self.grown_by = None
            self._set_ensemble(_constant_ensemble(float(y[0]), self.regressor))
            self.ensemble.n_features_in_ = int(X.shape[1])  # type: ignore[attr-defined]
            self._operators(self._ensemble_per_tree(self.ensemble))
            return
        grow = y
        if len(np.unique(y)) < len(y):  # ties would stop a node from splitting: break them
            grow = y + np.random.default_rng([self.seed, k, 7]).normal(0.0, 1e-6 * (1.0 + float(np.std(y))), len(y))
        model = self._structure_model(k)
        params = model.get_params()
        full = int(params.get("n_estimators") or 0)
        e = self.early
        early = (e is not None and e.gamma < 1.0 and 0 < e.trees < full
                 and build_weight(k, tuple(self.restructure_at), e.gamma, e.n_iterations) < e.ratio)
        if early:  # its error is damped before the end: the forest's first trees only, unscreened
            model.set_params(n_estimators=e.trees)
        s = self.screen
        screen = (not early and s is not None and s.tol > 0 and s.gamma < 1.0 and self.encoder.n_actions > 1
                  and "warm_start" in params and full > s.trees)
        native = (extra_trees.native_params(model, len(X), X.shape[1])
                  if self.builder == "auto" and extra_trees.available() and _sklearn_trees_known() else None)
        self.grown_by = "compiled" if native is not None else "scikit-learn"
        if native is not None:  # the same algorithm, compiled; tree t depends on (seed, t) only
            first = native.n_estimators if not screen else s.trees  # type: ignore[union-attr]
            self._adopt_grown(self._grow(X, grow, native, range(first)), X.shape[1])
            if screen:
                assert s is not None
                self.screen_value = self._screen_bias(np.asarray(y, dtype=np.float64), full)
                if not self.screen_value <= s.tol:
                    self._adopt_grown(self._grow(X, grow, native, range(s.trees, full)), X.shape[1], start=s.trees)
            return
        if not screen:
            self._adopt(_fit(model, X, grow, self.weights))
            return
        assert s is not None
        model.set_params(n_estimators=s.trees, warm_start=True)  # its trees are the full forest's first ones
        self._adopt(_fit(model, X, grow, self.weights))
        self.screen_value = self._screen_bias(np.asarray(y, dtype=np.float64), full)
        if not self.screen_value <= s.tol:  # the greedy targets need the whole forest (NaN: to be safe)
            model.set_params(n_estimators=full)
            self._adopt(_fit(model, X, grow, self.weights), start=s.trees)

    def _adopt(self, forest: Any, start: int = 0, train_leaves: list[np.ndarray] | None = None) -> None:
        """Take ``forest`` as the structure: look up every training and query input in it
        (from tree ``start`` on: the earlier trees' lookups are held, see :meth:`_operators`)."""
        if not hasattr(forest, "estimators_") or not hasattr(forest.estimators_[0], "tree_"):
            raise ValueError("the frozen-structure mode needs a scikit-learn tree ensemble (extra_trees, random_forest)")
        # the forest's arrays are exported (TreeEnsemble) only when a Q is asked for
        # (snapshot: a checkpoint, the end of the fit), not at every build
        sizes = np.array([e.tree_.node_count for e in forest.estimators_], dtype=np.int64)
        self.ensemble, self._forest = None, forest
        self._roots, self._n_nodes = np.r_[0, np.cumsum(sizes)[:-1]], int(sizes.sum())
        trees = [e.tree_ for e in forest.estimators_]
        if train_leaves is not None:  # local ids -> global
            train_leaves = [leaf.astype(np.int64) + int(r) for leaf, r in zip(train_leaves, self._roots[start:], strict=True)]
        self._operators(self._compiled_per_tree(trees[start:], self._roots[start:]), start=start,
                        train_leaves=train_leaves)

    def _grow(self, X: np.ndarray, y: np.ndarray, native: extra_trees.TreeParams,
              trees: range) -> list[tuple[Any, np.ndarray | None]]:
        """Trees ``trees`` from the compiled builder, each as a scikit-learn ``Tree`` (made
        in the builder's thread, so its full-size buffers go at once) and its training
        rows' leaves (None unless every row is in the tree)."""
        d = X.shape[1]

        def finish(t: extra_trees.GrownTree) -> tuple[Any, np.ndarray | None]:  # copies: the arrays are reused
            leaf = t.train_leaf.copy() if t.train_leaf is not None and int(t.train_leaf.min(initial=0)) >= 0 else None
            return sklearn_tree_from_records(t.nodes, t.value, d), leaf

        every = not native.bootstrap and (self.weights is None or bool((np.asarray(self.weights) > 0).all()))
        return extra_trees.grow_trees(X, y, self.weights, native, trees, finish=finish, record_leaves=every)

    def _adopt_grown(self, trees: list[tuple[Any, np.ndarray | None]], n_features: int, start: int = 0) -> None:
        """As :meth:`_adopt`, for trees from the compiled builder (:meth:`_grow`): held as
        scikit-learn ``Tree`` objects set from their records (its compiled lookups, and the
        export), with each training row's leaf where every row is in the tree.
        ``start > 0``: they follow the ``start`` trees held, as a screened build grows
        its forest."""
        held = self._forest.estimators_[:start] if start else []
        new = [SimpleNamespace(tree_=tree) for tree, _ in trees]
        # every training row in every tree (no bootstrap, no zero weight): its leaf is known
        known = all(leaf is not None for _, leaf in trees)
        self._adopt(SimpleNamespace(estimators_=held + new, n_features_in_=int(n_features)), start=start,
                    train_leaves=[leaf for _, leaf in trees] if known else None)

    def _screen_bias(self, y: np.ndarray, full: int) -> float:
        """How much the greedy targets would lose by keeping the screen's trees instead of
        all ``full``: at every bootstrapped next state, :func:`greedy_min_bias` of the best
        action (under the screen's trees) against each other action, from their per-tree
        gaps, summed over the other actions (a union bound: exact with two actions, an upper
        bound with more); averaged with the sample weights, carried through the horizon
        ``1 / (1 - gamma)`` and divided by the (weighted) standard deviation of ``y``."""
        s = self.screen
        assert s is not None
        P, A = self.pos["next"], self.encoder.n_actions
        m, n = P.shape[0], P.shape[1] // A
        vals = np.r_[self._leaf_sums(y if self._w is None else self._w * y) / self._wsum, 0.0]
        rows = np.arange(n) if s.rows is None else np.flatnonzero(s.rows)
        w = np.ones(n) if self._w is None else self._w
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

    def _set_ensemble(self, ensemble: TreeEnsemble) -> None:
        self.ensemble, self._forest = ensemble, None
        self._roots, self._n_nodes = np.asarray(ensemble.roots), len(ensemble.value)

    def _exported(self) -> TreeEnsemble:
        """The structure as arrays, exported from the forest on first use (then the forest,
        whose node arrays are as large again, is dropped)."""
        if self.ensemble is None:
            forest, self._forest = self._forest, None
            trees = [e.tree_ for e in forest.estimators_]
            forest.estimators_ = []  # ours (a clone): each tree is freed as soon as it is copied
            ens = TreeEnsemble._from_trees(trees, consume=True)
            ens.n_features_in_ = int(forest.n_features_in_)  # type: ignore[attr-defined]
            self._set_ensemble(ens)
        return self.ensemble

    def _operators(self, tree_leaves: Any, start: int = 0, train_leaves: list[np.ndarray] | None = None) -> None:
        """The training leaf matrix, the leaf weights and the query operators (leaf positions),
        tree by tree: ``tree_leaves(X)`` yields, for each tree in order, the global leaf id of
        every row of ``X``. Training rows that continue the previous row (``x_i == x'_{i-1}``)
        take their leaves from the next-state lookup (a third of the lookups with two
        actions). Everything is tree-major int32 and no (rows, trees) int64 matrix is ever
        held: one tree's lookups at a time. ``start > 0``: the first ``start`` trees are
        those whose lookups are held already (a screened build growing its forest); their
        positions are kept and ``tree_leaves`` yields the later trees only.

        ``train_leaves`` (the compiled builder's, one array per tree from ``start`` on, global
        ids): every training row's leaf is known, so nothing is looked up for the training
        rows, and the next-state queries they repeat are not looked up either: half of them
        with two actions."""
        n, m = len(self.phi), len(self._roots)
        names = [q for q in self.queries if q != "train"]
        inputs = {q: self._joint(*self.queries[q]) for q in names}
        reuse = self.reuse if len(self.reuse) and "next" in inputs else np.zeros(0, np.int64)
        rest = np.ones(n, bool)
        rest[reuse] = False
        from_next = self.actions[reuse] * n + reuse - 1  # row i continues row i - 1: its leaf is x'_{i-1}'s with a_i
        looked = None  # the next-state queries looked up (the others are training rows' leaves)
        if train_leaves is not None and len(reuse):
            looked = np.ones(len(inputs["next"]), bool)
            looked[from_next] = False
            inputs = {**inputs, "next": inputs["next"][looked]}
        gens = {q: tree_leaves(inputs[q]) for q in names}
        if rest.any() and train_leaves is None:
            gens[""] = tree_leaves(self.encoder.pairs(self.phi[rest], self.actions[rest]))
        if looked is not None:
            inputs["next"] = np.empty((len(looked), 0))  # only its length is read below
        ends = np.r_[self._roots[1:], self._n_nodes]
        held, held_bounds, held_ids = (self.pos, self._bounds, self.leaf_ids) if start else ({}, None, None)
        self.pos: dict[str, np.ndarray] = {q: np.empty((m, len(inputs[q])), np.int32) for q in names}
        train = np.empty((m, n), np.int32)
        ids, bounds = [], [0]
        if start:  # the same trees, the same compact leaves; "no training leaf" is re-marked below
            for q, p in [*self.pos.items(), ("train", train)]:
                p[:start] = held[q][:start]
                p[:start][p[:start] == len(held_ids)] = -1
            ids, bounds = [held_ids], [int(b) for b in held_bounds[:start + 1]]
            del held
        for t in range(start, m):
            raw = {q: next(g) for q, g in gens.items()}
            root, lo = int(self._roots[t]), bounds[-1]
            if train_leaves is not None:
                leaf = train_leaves[t - start]
                if looked is not None:
                    full = np.empty(len(looked), np.int64)
                    full[looked] = raw["next"]
                    full[from_next] = leaf[reuse]
                    raw["next"] = full
            else:
                leaf = np.empty(n, np.int64)
                leaf[rest] = raw.pop("", None) if rest.any() else 0
                if len(reuse):
                    leaf[reuse] = raw["next"][from_next]
            used = np.zeros(int(ends[t]) - root, bool)
            used[leaf - root] = True
            local = np.flatnonzero(used)  # this tree's leaves holding training samples
            lookup = np.full(len(used), -1, np.int32)
            lookup[local] = lo + np.arange(len(local), dtype=np.int32)
            train[t] = lookup[leaf - root]
            for q in names:
                self.pos[q][t] = lookup[raw[q] - root]  # -1: a leaf without training samples
            ids.append(local + root)
            bounds.append(lo + len(local))
        self.leaf_ids = np.concatenate(ids)  # compact index: tree t's leaves are [bounds[t], bounds[t + 1])
        L = len(self.leaf_ids)
        for q in names:  # a leaf without training weight reads value L (0)
            p = self.pos[q]
            p[p < 0] = L
        for q, p in [*self.pos.items(), ("train", train)]:  # _tree_mean gathers with mode="clip": keep them in range
            if p.size and (int(p.min()) < 0 or int(p.max()) > L):
                raise RuntimeError(f"frozen structure: leaf positions of {q!r} outside [0, {L}]")
        self._bounds, self._m = np.asarray(bounds), m
        self._w = None if self.weights is None else np.asarray(self.weights, dtype=np.float64)
        self.pos["train"] = train  # every training leaf holds its own sample
        self._wsum = self._leaf_sums(np.ones(n) if self._w is None else self._w)
        self._rest = None  # tree-major positions of the training rows that are not reused (cached)

    @staticmethod
    def _per_tree(leaves_of: Any) -> Any:
        """``tree_leaves`` from a whole-ensemble lookup ``leaves_of(X) -> (len(X), n_trees)``."""
        def gen(X: np.ndarray) -> Any:
            full = FrozenTreesLearner._leaves(leaves_of, X)
            for t in range(full.shape[1]):
                yield np.asarray(full[:, t], dtype=np.int64)
        return gen

    def _ensemble_per_tree(self, ens: TreeEnsemble) -> Any:
        """``tree_leaves`` for a structure held as arrays (a restored checkpoint, the
        constant-target structure): scikit-learn's compiled trees rebuilt from the arrays,
        tree by tree (no (rows, trees) lookup matrix), after checking that every feature a
        split reads is among our inputs; the numpy traversal where they cannot be rebuilt."""
        ens.check_inputs(self.encoder.pairs(self.phi[:1], self.actions[:1]))  # before any compiled lookup
        trees = ens._compiled_trees()
        return self._per_tree(ens.apply) if trees is None else self._compiled_per_tree(trees, np.asarray(ens.roots))

    @staticmethod
    def _compiled_per_tree(trees: list[Any], roots: np.ndarray) -> Any:
        """``tree_leaves`` for compiled scikit-learn ``Tree`` objects: each tree's ``apply`` on
        float32 inputs, one tree at a time (no (rows, trees) matrix)."""
        def gen(X: np.ndarray) -> Any:
            X32 = np.ascontiguousarray(X, dtype=np.float32)
            first = np.asarray(trees[0].apply(X32), dtype=np.int64)
            yield first + int(roots[0])
            # rows in the order of their leaf in the first tree (depth-first ids): neighbours
            # in space descend the other trees together, so their nodes stay in cache
            # (measured: ~40% less CPU on 100k CartPole lookups into 50-deep trees)
            order = np.argsort(first, kind="stable")
            Xs = np.ascontiguousarray(X32[order])
            out = np.empty(len(X32), np.int64)
            for tree, root in zip(trees[1:], roots[1:], strict=True):
                out[order] = tree.apply(Xs)
                yield out + int(root)
        return gen

    @property
    def _compact(self) -> np.ndarray:
        """The training rows' compact leaves, flat tree-major: entry ``t * n + i``."""
        return self.pos["train"].reshape(-1)

    def _leaf_sums(self, v: np.ndarray) -> np.ndarray:
        """``sum of v_i`` over the training rows in each leaf (compact index)."""
        pos, out = self.pos["train"], np.empty(len(self.leaf_ids))
        for t, (lo, hi) in enumerate(zip(self._bounds[:-1], self._bounds[1:], strict=True)):
            out[lo:hi] = np.bincount(pos[t] - lo, weights=v, minlength=hi - lo)
        return out

    @property
    def M(self) -> Any:
        """The leaf-averaging operator as a sparse (leaves, n) matrix (built on demand):
        ``M[leaf, i] = w_i / (sum of w in the leaf)``, so ``leaf_values = M @ y``."""
        from scipy import sparse

        m, n = self.pos["train"].shape
        w = np.ones(n) if self._w is None else self._w
        flat = self._compact
        return sparse.csr_matrix((np.tile(w, m) / self._wsum[flat], (flat, np.tile(np.arange(n), m))),
                                 shape=(len(self.leaf_ids), n))

    @staticmethod
    def _leaves(leaves_of: Any, X: np.ndarray, chunk: int = 262_144) -> np.ndarray:
        """Leaf lookups in row chunks (bounded temporaries)."""
        first = leaves_of(X[:chunk])
        if len(X) <= chunk:
            return first
        out = np.empty((len(X), first.shape[1]), first.dtype)
        out[:chunk] = first
        for lo in range(chunk, len(X), chunk):
            out[lo:lo + chunk] = leaves_of(X[lo:lo + chunk])
        return out

    @property
    def A(self) -> dict[str, Any]:
        """The query operators as sparse matrices ``A[q, leaf] = 1 / n_trees`` (built on demand)."""
        return self.query_operators()

    def query_operators(self, names: tuple[str, ...] | None = None) -> dict[str, Any]:
        """``A`` for the query sets ``names`` only (default: all)."""
        from scipy import sparse

        L, out = len(self.leaf_ids), {}
        for name, pos in self.pos.items():
            if names is not None and name not in names:
                continue
            m, nq = pos.shape
            flat = pos.reshape(-1)  # tree-major
            hit = flat < L
            qrows = np.tile(np.arange(nq, dtype=np.int64), m)[hit]
            out[name] = sparse.csr_matrix((np.full(int(hit.sum()), 1.0 / m), (qrows, flat[hit])), shape=(nq, L))
        return out

    def reweighted_operators(self, weights: np.ndarray, base: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        """Leaf-averaging operator ``M`` and query operators ``A`` for other sample weights
        on the same structure. A leaf left with no weight is dropped from every query's
        average over trees (rows of ``A`` renormalised over the remaining trees; a query
        with none left keeps its original row). ``base``: the unweighted query operators
        to reweight (default: all of :attr:`A`, built here), so that many replicates
        build them once."""
        from scipy import sparse

        m, n = self.pos["train"].shape
        compact = self._compact  # flat tree-major
        rows = np.tile(np.arange(n), m)
        w = np.asarray(weights, dtype=np.float64)[rows]
        wsum = np.bincount(compact, weights=w, minlength=len(self.leaf_ids))
        vals = w / np.where(wsum[compact] > 0, wsum[compact], 1.0)
        M = sparse.csr_matrix((vals, (compact, rows)), shape=(len(self.leaf_ids), n))
        keep = wsum > 0
        A = {}
        for name, op in (self.A if base is None else base).items():  # entry by entry, on op's own sparsity
            op = op.tocsr()
            row = np.repeat(np.arange(op.shape[0]), np.diff(op.indptr))
            kept = np.where(keep[op.indices], op.data, 0.0)
            total = np.bincount(row, weights=kept, minlength=op.shape[0])
            scale = np.where(total > 0, 1.0 / np.where(total > 0, total, 1.0), 0.0)
            data = np.where((total > 0)[row], kept * scale[row], op.data)  # a row with no leaf left: unchanged
            A[name] = sparse.csr_matrix((data, op.indices, op.indptr), shape=op.shape)
        return M, A

    def fit(self, y: np.ndarray, k: int) -> None:
        if self._pending or k in self.restructure_at:
            self._build(y, k)
        self._pending = self.built_on_constant  # constant targets say nothing about where to split
        y = np.asarray(y, dtype=np.float64)
        self.leaf_values = self._leaf_sums(y if self._w is None else self._w * y) / self._wsum  # leaf means of y_k
        self._cache = {}

    def state(self) -> dict[str, Any]:
        return {"structure": self.structures, "structure_on_constant": self.built_on_constant,
                "structure_trees": int(self._m), "structure_screen": self.screen_value,
                "structure_builder": self.grown_by}

    def _joint(self, phi: np.ndarray, actions: np.ndarray | None) -> np.ndarray:
        return self.encoder.all_pairs(phi) if actions is None else self.encoder.pairs(phi, actions)

    def predict(self, name: str) -> np.ndarray:
        if name in self._cache:
            return self._cache[name]
        phi, actions = self.queries[name]
        values = self._cache.get("")  # leaf values and a 0 for "no training leaf", once per iteration
        if values is None:
            values = self._cache[""] = np.r_[self.leaf_values, 0.0]
        if name == "train" and len(self.reuse) and "next" in self.pos:  # the same leaves: the same numbers
            v = np.empty(len(phi))
            rest = np.ones(len(phi), bool)
            rest[self.reuse] = False
            if self._rest is None:
                self._rest = np.ascontiguousarray(self.pos[name][:, rest])
            v[rest] = _tree_mean(values, self._rest)
            v[self.reuse] = self.predict("next")[self.reuse - 1, self.actions[self.reuse]]
        else:
            v = _tree_mean(values, self.pos[name])  # mean over trees of the reached leaves
        self._cache[name] = v if actions is not None else v.reshape(self.encoder.n_actions, len(phi)).T
        return self._cache[name]

    def snapshot(self) -> QFunction:
        ens = self._exported()
        value = ens.value.copy()
        value[self.leaf_ids] = self.leaf_values
        return TreeQ([ens.with_values(value)], self.encoder)

    def restore(self, q: QFunction, iteration: int, rows: list[dict[str, Any]] | None = None) -> None:
        """The saved ``Q_k`` carries its structure: recompute the leaves of the training and
        query inputs with it (the same leaves the structure's forest gave) and read the
        leaf values back."""
        self._set_ensemble(q.models[0])  # a TreeQ, or the RegressorQ of TreeEnsembles load_q returns  # type: ignore[attr-defined]
        self._operators(self._ensemble_per_tree(self.ensemble))
        self.leaf_values = np.asarray(self.ensemble.value[self.leaf_ids], dtype=np.float64)
        self._cache = {}
        last = (rows or [{}])[-1]
        self.structures = int(last.get("structure") or 1)
        self.built_on_constant = bool(last.get("structure_on_constant") or False)
        screened = last.get("structure_screen")
        self.screen_value = None if screened is None or screened != screened else float(screened)  # NaN: none
        by = last.get("structure_builder")
        self.grown_by = by if isinstance(by, str) else None
        self._pending = self.built_on_constant


def _sklearn_trees_known() -> bool:
    """Whether scikit-learn ``Tree`` objects can be set from arrays here (the compiled
    builder's trees are looked up through them)."""
    z = np.zeros(1, np.int64)
    return sklearn_tree(z - 1, z - 1, z - 2, np.full(1, -2.0), np.zeros(1), 1) is not None


def check_structure_fractions(value: Any) -> None:
    """Raise ValueError unless ``value`` is a row fraction in (0, 1], None, or a list of those
    (the frozen structures' ``max_samples``)."""
    fractions = list(value) if isinstance(value, list | tuple) else [value]
    if not all(f is None or (isinstance(f, int | float) and not isinstance(f, bool) and 0.0 < float(f) <= 1.0)
               for f in fractions):
        raise ValueError(f"structure_max_samples must be 'auto', a fraction in (0, 1], None, or a list of "
                         f"fractions/None, got {value!r}")


def _constant_ensemble(value: float, regressor: Any) -> TreeEnsemble:
    """An ensemble of one-leaf trees predicting ``value`` (as many trees as the regressor has)."""
    m = int(regressor.get_params().get("n_estimators", 1))
    minus = np.full(m, -1, np.int64)
    return TreeEnsemble(left=minus, right=minus.copy(), feature=np.full(m, -2, np.int64), threshold=np.full(m, -2.0),
                        value=np.full(m, value), roots=np.arange(m, dtype=np.int64))


def _tree_mean(values: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """``values[pos].mean(axis=0)`` for tree-major ``pos`` (m, nq), one gather per tree (each
    within that tree's leaf range), no (m, nq) float temporary."""
    out, tmp = np.zeros(pos.shape[1]), np.empty(pos.shape[1])
    for row in pos:  # positions are ours, all in range: "clip" skips numpy's buffered bounds check (~2x)
        values.take(row, out=tmp, mode="clip")
        out += tmp
    return out / len(pos)


class BoostedSumQ(QFunction):
    """Q = sum of LightGBM boosters' raw scores on joint inputs."""

    def __init__(self, boosters: list[Any], encoder: QEncoder) -> None:
        self.boosters, self.encoder, self.n_actions = boosters, encoder, encoder.n_actions

    def values(self, obs: np.ndarray, t: Any = 0) -> np.ndarray:
        X = self.encoder.all_pairs(self.encoder.phi(obs))
        s = sum(b.predict(X, raw_score=True) for b in self.boosters)
        return np.asarray(s, dtype=np.float64).reshape(self.n_actions, len(obs)).T


class LightGBMWarmStartLearner(Learner):
    """Warm-started boosting: each iteration adds ``trees_per_iteration`` trees fitted to
    the residual ``y_k - Q_{k-1}`` on the training pairs, boosted from its (weighted)
    mean, so ``Q_k = Q_{k-1} + mean residual + new trees``: a constant change of the
    targets (every logged cost the same) is learned, not lost. Cached predictions make
    each step cost only the new trees. Joint encoding only. LightGBM parameters come from
    a LightGBM regressor; any other regressor gets ``num_leaves=63, learning_rate=0.3``
    (10 trees then go ~97% of the way to each iteration's targets).
    """

    def __init__(self, *args: Any, trees_per_iteration: int = 10, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.encoder.per_action:
            raise ValueError("the LightGBM warm-start mode needs action_encoding='joint'")
        import lightgbm as lgb

        self.lgb = lgb
        self.params = self.booster_params(self.regressor, self.seed)
        self.trees_per_iteration = trees_per_iteration
        self.X = {name: self._joint(phi, a) for name, (phi, a) in self.queries.items()}
        self.cache = {name: np.zeros(len(X)) for name, X in self.X.items()}
        self.boosters: list[Any] = []
        self.data = self.lgb.Dataset(self.X["train"], label=np.zeros(len(self.X["train"])), weight=self.weights,
                                     free_raw_data=False, params={"verbose": -1})

    @staticmethod
    def booster_params(regressor: Any, seed: int) -> dict[str, Any]:
        """``lightgbm.train`` parameters of one iteration's trees (also the Dask engine's)."""
        p = regressor.get_params() if type(regressor).__name__.startswith("LGBM") else {}
        return {
            "objective": "regression",
            "num_leaves": p.get("num_leaves", 63),
            "learning_rate": p.get("learning_rate") if p.get("learning_rate") is not None else 0.3,
            "min_data_in_leaf": p.get("min_child_samples", 20),
            "verbose": -1,
            # one thread unless the regressor asks for more: on a loaded machine LightGBM's
            # spinning OpenMP threads burned 5-50x the CPU of a single thread at 10k-50k rows
            "num_threads": p.get("n_jobs") if (p.get("n_jobs") or 0) > 0 else 1,
            "seed": seed,
            "deterministic": True,
            "boost_from_average": True,
        }

    def _joint(self, phi: np.ndarray, actions: np.ndarray | None) -> np.ndarray:
        return self.encoder.all_pairs(phi) if actions is None else self.encoder.pairs(phi, actions)

    def fit(self, y: np.ndarray, k: int) -> None:
        self.data.set_label(y - self.cache["train"])  # the residual; its mean goes into the first tree
        booster = self.lgb.train({**self.params, "seed": self.seed + k}, self.data, num_boost_round=self.trees_per_iteration)
        self.boosters.append(booster)
        for name, X in self.X.items():  # only the new trees are evaluated
            self.cache[name] = self.cache[name] + booster.predict(X, raw_score=True)

    def predict(self, name: str) -> np.ndarray:
        phi, actions = self.queries[name]
        v = self.cache[name]
        return v if actions is not None else v.reshape(self.encoder.n_actions, len(phi)).T

    def snapshot(self) -> QFunction:
        return BoostedSumQ(list(self.boosters), self.encoder)

    def restore(self, q: QFunction, iteration: int, rows: list[dict[str, Any]] | None = None) -> None:
        self.boosters = [getattr(b, "booster", b) for b in q.boosters]  # type: ignore[attr-defined]
        for name, X in self.X.items():  # the same sums, in the same order, as when fitting
            c = np.zeros(len(X))
            for b in self.boosters:
                c = c + b.predict(X, raw_score=True)
            self.cache[name] = c
