"""Model rollouts of the logs: a second, model-based reading of a policy's value whose
errors are not FQE's, and a logs-only measure of how far the policy drives from the data
(docs/evaluation.md, section 2, "Model rollouts"). Access model: trace data only.

FQE values a policy through its logged next states: a query ``(x', pi(x'))`` is answered
by the rows whose states the regression puts near ``x'``. Where the policy drifts (a
steering policy that slowly leaves the lane), those rows sit closer to where the data is
dense, and the drift never shows: on the driving problem FQE read a policy that leaves the
road in 95% of its episodes at 8.3 against a truth of 19.6. A model of the *increments*
``x' - x`` does not snap back to the data: rolled out, its states drift as the policy's do.

The model (:class:`LoggedDynamics`), fitted on the logged transitions:

- increments ``(x' - x) / sd = L(x, a) + R(x, a) + e``: a ridge regression ``L`` (the part
  of the dynamics linear in the state and the action, extrapolated as such; the action
  enters as its value and one-hot) plus extra-trees ``R`` on its residuals (Geurts et al.
  2006), and noise ``e`` drawn from the out-of-fold residuals of ``L + R`` (two folds of
  episodes; they hold the model's own error too, so the noise is if anything too large);
- cost and termination ``(c, P[terminal]) = G(x, a, x')``: extra-trees on the state, the
  action and the next state (costs and failures usually depend on where the step lands);
- support: a state is *in the data* when a logged state lies within the 99.9% quantile of
  the logged states' nearest-neighbour distances to *other* episodes (features in standard
  deviations; a new trajectory has no logged episode of its own, :func:`_support_radius`);
  it is *trusted* when one lies within the data's own spacing, the same quantile of the
  distances to the nearest other logged state, own episode included (``trust_radius_``,
  at most the support radius).

The rollout (:func:`model_rollout_value`) starts ``n`` particles at logged start states
(resampled), acts with the policy, steps the model, and weighs each step's cost by the
survival probability: ``V = mean_i sum_t w_it c_it`` with ``w_it = gamma^t S_it``, the
estimate. When particle i is first at a state not trusted, at step ``tau_i``, the
model's reading from there on is taken as unknown; the **bounds** value the remaining
``L = H - tau_i`` steps at the ends of what the logged costs allow for ``L`` steps
(:func:`remainder_ranges`): ``lower = mean_i (sum_{t < tau_i} w_it c_it + w_{i tau_i}
lo(L))``, likewise ``upper``. Their interval adds the particles' Monte-Carlo error (normal,
at ``level``). They hold the value *as far as the model is right where the data is*,
which is why :func:`offpolicy.off_policy` takes the hull of them and FQE's interval rather
than either alone. ``exit_mass``, the share of the discounted survival mass
``sum_t w_it`` that lies at or after ``sigma_i >= tau_i``, the step particle i is first at
a state not in the data, is the logs-only measure of drift (and ``exit_share`` the mean
survival at ``sigma_i``). Two radii because they answer two questions: whether a policy's
states are ones a new episode of the data could reach (calibrated: fresh episodes of the
logging policy fall outside about 0.1% of the time), and where the model's reading is
close enough to the data to be taken as known (the bounds were validated with the stricter
one; with the support radius they missed, docs/evaluation.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from offline_adp.access import StepResult
from offline_adp.algorithms.fqi_data import cost_unit
from offline_adp.data.dataset import TransitionArrays, TransitionDataset
from offline_adp.errors import InvalidArgumentError
from offline_adp.evaluation import MODEL_PARTICLES_DEFAULT
from offline_adp.policies import Policy

#: A state is in the data (trusted) when a logged state is at most this quantile of the logged states'
#: distances to other episodes (to any other logged state) away, in feature standard deviations. With
#: the own-neighbour distances, 0.99 flagged 1% of the logged states themselves at every step, and
#: over a 200-step rollout nearly every particle of a policy the logs cover (path_tracking: 89%).
SUPPORT_QUANTILE = 0.999
#: folds of whole episodes for the support radius (:func:`_support_radius`), and its probe states
RADIUS_FOLDS = 5
MAX_RADIUS_PROBES = 20_000
#: rows the model is fitted on at most (a uniform sample above it), and particles per rollout
MAX_FIT_ROWS = 200_000
N_PARTICLES = MODEL_PARTICLES_DEFAULT
#: model states are kept within the logged range widened by this many standard deviations
#: (a linear part that extrapolates an unstable system would otherwise overflow)
CLIP_SD = 3.0
#: a state coordinate with at most this many distinct logged values is discrete: predicted next
#: values are snapped to the nearest logged one
MAX_LEVELS = 20
#: the exit mass from which a warning says the policy drives where the logs do not go (and the
#: headline judges it left the data's support: ``verdict.MODEL_EXIT_FRACTION``)
EXIT_FRACTION = 0.1
_NN_EPS = 1.0  #: the approximate nearest-neighbour search of the support check (LoggedDynamics.in_data)


@dataclass
class LoggedDynamics:
    """Increment, cost and termination models of the logged transitions (module docstring).

    Parameters
    ----------
    n_estimators : int
        Trees of each extra-trees model.
    min_samples_leaf : int
        Rows per leaf of the trees.
    ridge_alpha : float
        L2 penalty of the linear part (features standardised).
    noise : bool
        Draw each step's noise from the out-of-fold residuals (else the mean increment).
    random_state : int
        Seed of the trees, the fold split and the row sample.

    Attributes
    ----------
    sd_ : ndarray
        Feature standard deviations (1 where constant).
    cost_unit_ : float
        The outcome model's unit of cost (the power of two ``u <= max |c| < 2u``, ``cost_unit``).
    radius_ : float
        In-the-data distance (:data:`SUPPORT_QUANTILE` of the distances to other episodes'
        nearest states, :func:`_support_radius`): where the support judgement (exit mass)
        says a state lies past the data.
    trust_radius_ : float
        The distance within which the bounds take the model's reading as known: the
        :data:`SUPPORT_QUANTILE` of the logged states' distances to their nearest other
        logged state, own episode included (the data's own spacing; at most ``radius_``).
    residuals_ : ndarray
        Out-of-fold residuals of the increments, in standard deviations.
    start_states_ : ndarray
        The logged states at step 0.
    fit_rows_ : ndarray
        The rows fitted on (all, or a sample of :data:`MAX_FIT_ROWS`): the bootstrap's replicates
        resample their episodes (:mod:`offline_adp.evaluation.model_bootstrap`).
    """

    n_estimators: int = 20
    min_samples_leaf: int = 3
    ridge_alpha: float = 1e-3
    noise: bool = True
    random_state: int = 0

    def fit(self, ds: TransitionDataset, arrays: TransitionArrays | None = None) -> LoggedDynamics:
        """Fit on the transitions of ``ds`` (at most :data:`MAX_FIT_ROWS`, sampled);
        ``arrays``: ``ds.arrays()`` when the caller has them. States on a lattice
        (``radius_ == 0``) stop after the support radius: there is nothing to roll out."""
        from scipy.spatial import cKDTree

        a = arrays if arrays is not None else ds.arrays()
        rng = np.random.default_rng(self.random_state)
        rows = np.arange(len(a.cost)) if len(a.cost) <= MAX_FIT_ROWS else \
            np.sort(rng.choice(len(a.cost), MAX_FIT_ROWS, replace=False))
        self.fit_rows_ = rows
        obs, nxt = a.obs[rows], a.next_obs[rows]
        sd = obs.std(axis=0)
        self.sd_ = np.where(sd > 0, sd, 1.0)
        self.cost_unit_ = cost_unit(a.cost[rows])  # a power of two: c / u * u is c
        self.start_states_ = a.obs[a.step == 0]
        z = obs / self.sd_
        self.tree_ = cKDTree(z)
        spacing = _spacing_radius(z, self.tree_, rng)  # first: the draws of the rule before
        self.radius_ = _support_radius(z, a.episode[rows], spacing, rng)
        self.trust_radius_ = min(self.radius_, spacing)
        if self.radius_ <= 0:  # a lattice: nothing to roll out (model_rollouts skips), nothing more to fit
            return self
        both = np.vstack([obs, nxt])
        # coordinates with few logged values (a mode flag, a count): predictions snapped to them,
        # or every fractional prediction would lie off the data
        self.levels_ = {j: u for j in range(both.shape[1])
                        if len(u := np.unique(both[:, j])) <= MAX_LEVELS}
        self.low_, self.high_ = both.min(axis=0) - CLIP_SD * self.sd_, both.max(axis=0) + CLIP_SD * self.sd_
        values = np.asarray(ds.info.action_table.values, dtype=np.float64).reshape(ds.n_actions, -1)
        vsd = values.std(axis=0)
        self.action_features_ = np.hstack([values / np.where(vsd > 0, vsd, 1.0), np.eye(ds.n_actions)])
        F, dx = self.fit_predictors(a, rows)
        self.residuals_ = np.zeros((0, dx.shape[1]))
        self.noise_source_ = "none (noise=False)"
        if self.noise:  # out-of-fold residuals: two balanced folds of whole episodes (one episode: its halves)
            ep = a.episode[rows]
            eps = np.unique(ep)
            if len(eps) >= 2:
                fold = _episode_folds(ep, eps, 2, np.random.default_rng([self.random_state, 1]))
                self.noise_source_ = "out-of-fold residuals (two folds of episodes)"
            else:
                st = a.step[rows]
                fold = (st > np.median(st)).astype(np.int64)
                self.noise_source_ = "out-of-fold residuals (one episode: its two halves in time)"
            res = []
            for k in (0, 1):
                if (fold == k).all() or (fold != k).all():
                    continue
                lin, tree = self._increments(F[fold != k], dx[fold != k])
                Fk = F[fold == k]
                res.append(dx[fold == k] - _2d(lin.predict(Fk), dx.shape[1]) - _2d(tree.predict(Fk), dx.shape[1]))
            self.residuals_ = np.vstack(res) if res else self.residuals_
            if not res:
                self.noise_source_ = "none (too few rows to hold any out)"
        return self

    def fit_predictors(self, a: TransitionArrays, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fit the increment models (``linear_``, ``residual_``) and the cost-and-termination
        model (``outcome_``, the costs in units of ``cost_unit_``, ``~max |c|``, so that the
        terminations weigh the same in its splits at any scale of the costs) on ``rows`` of
        ``a`` (each tree model seeded with ``random_state``, so the order of the fits does not
        matter); returns the features and the scaled increments (:meth:`fit` once, the bootstrap per replicate)."""
        obs, nxt = a.obs[rows], a.next_obs[rows]
        F = self._features(obs, a.action[rows])
        dx = (nxt - obs) / self.sd_
        self.linear_, self.residual_ = self._increments(F, dx)
        G = np.column_stack([F, nxt / self.sd_])
        self.outcome_ = self._trees().fit(G, np.column_stack([a.cost[rows] / self.cost_unit_, a.terminated[rows]]))
        return F, dx

    def _trees(self) -> Any:
        from sklearn.ensemble import ExtraTreesRegressor

        return ExtraTreesRegressor(n_estimators=self.n_estimators, min_samples_leaf=self.min_samples_leaf,
                                   max_features=1.0, random_state=self.random_state, n_jobs=1)

    def _increments(self, F: np.ndarray, dx: np.ndarray) -> tuple[Any, Any]:
        from sklearn.linear_model import Ridge

        lin = Ridge(alpha=self.ridge_alpha).fit(F, dx)
        rest = dx - _2d(lin.predict(F), dx.shape[1])
        return lin, self._trees().fit(F, rest[:, 0] if rest.shape[1] == 1 else rest)

    def _features(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        return np.column_stack([obs / self.sd_, self.action_features_[np.asarray(action, dtype=np.int64)]])

    def in_data(self, states: np.ndarray, radius: float | None = None) -> np.ndarray:
        """Whether each state has a logged state within ``radius`` (default ``radius_``; feature
        standard deviations), exactly. An approximate nearest-neighbour search (``eps``: its distance is at
        most ``1 + eps`` times the true one) settles most states: within the radius is in, past ``(1 + eps)``
        times it is out; only those in between get an exact search (17 dimensions, 200k rows: ~10x faster)."""
        z = np.asarray(states, dtype=np.float64) / self.sd_
        r = self.radius_ if radius is None else float(radius)
        if r <= 0:  # a lattice: only the logged states themselves
            return self.tree_.query(z)[0] <= 0.0
        eps = _NN_EPS
        approx, _ = self.tree_.query(z, eps=eps, distance_upper_bound=r * (1.0 + eps))
        inside = approx <= r
        unsure = ~inside & np.isfinite(approx)
        if unsure.any():
            exact, _ = self.tree_.query(z[unsure])
            inside[unsure] = exact <= r
        return inside

    def step(self, states: np.ndarray, actions: np.ndarray, rng: np.random.Generator | None = None) -> StepResult:
        """One model step: next states, expected cost, termination probability (as
        ``terminated``)."""
        if not hasattr(self, "linear_"):
            raise InvalidArgumentError("LoggedDynamics.step: the model was not fitted (call fit; on states that repeat "
                                       "exactly, a lattice with radius_ == 0, fit stops before the regressions)")
        F = self._features(states, actions)
        d = states.shape[1]
        linear, residual, outcome = self._predictors()
        inc = _2d(linear(F), d) + _2d(residual(F), d)
        if rng is not None and len(self.residuals_):
            inc = inc + self.residuals_[rng.integers(0, len(self.residuals_), len(states))]
        nxt = np.clip(states + inc * self.sd_, self.low_, self.high_)
        for j, u in self.levels_.items():  # nearest logged level
            i = np.clip(np.searchsorted(u, nxt[:, j]), 1, max(len(u) - 1, 1))
            lower = u[np.maximum(i - 1, 0)]
            upper = u[np.minimum(i, len(u) - 1)]
            nxt[:, j] = np.where(np.abs(nxt[:, j] - lower) <= np.abs(upper - nxt[:, j]), lower, upper)
        out = _2d(outcome(np.column_stack([F, nxt / self.sd_])), 2)
        return StepResult(nxt, out[:, 0] * self.cost_unit_, np.clip(out[:, 1], 0.0, 1.0))

    def _predictors(self) -> tuple[Any, Any, Any]:
        """The fitted models' ``predict`` without scikit-learn's per-call validation and
        per-tree dispatch (:mod:`offline_adp.trees.forest_predict`: the same numbers), made
        once per fit; a model they do not read keeps its own ``predict``."""
        from offline_adp.trees.forest_predict import forest_predictor, linear_predictor

        key = (self.linear_, self.residual_, self.outcome_)
        cached = self.__dict__.get("_predict_cache")
        if cached is None or cached[0] != key:
            cached = (key, (linear_predictor(self.linear_) or self.linear_.predict,
                            forest_predictor(self.residual_) or self.residual_.predict,
                            forest_predictor(self.outcome_) or self.outcome_.predict))
            self.__dict__["_predict_cache"] = cached
        return cached[1]


def _episode_folds(episode: np.ndarray, episodes: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Each row's fold: ``k`` balanced folds of whole episodes in random order (``episodes``
    the distinct codes of ``episode``)."""
    fold_of = np.zeros(int(episodes.max()) + 1, np.int64)
    fold_of[rng.permutation(episodes)] = np.arange(len(episodes)) % k
    return fold_of[episode]


def _spacing_radius(z: np.ndarray, tree: Any, rng: np.random.Generator) -> float:
    """The :data:`SUPPORT_QUANTILE` of the logged states' distances to their nearest other
    logged state (own episode included; ``tree`` holds ``z``): the data's own spacing, the
    trust radius of the bounds (``LoggedDynamics.trust_radius_``). At most
    :data:`MAX_RADIUS_PROBES` states probed (a uniform sample, as the rule before)."""
    if len(z) < 2:
        return 0.0
    probe = z if len(z) <= MAX_RADIUS_PROBES else z[rng.choice(len(z), MAX_RADIUS_PROBES, replace=False)]
    d, _ = tree.query(probe, k=2)
    return float(np.quantile(d[:, 1], SUPPORT_QUANTILE))


def _support_radius(z: np.ndarray, episode: np.ndarray, spacing: float, rng: np.random.Generator) -> float:
    """The in-the-data distance: the :data:`SUPPORT_QUANTILE` of the distance from a logged
    state to the nearest state of *other* episodes (:data:`RADIUS_FOLDS` folds of whole
    episodes). A new trajectory, a particle's or a policy's, has no logged episode of its
    own, so a state's distance to its own episode's neighbours (one step apart, close) is not
    what it will see: with them, 70% of the states of fresh episodes of the logging policy
    itself fell outside in 17 dimensions (0.15% with other episodes only), 25% in 12 (0.19%),
    0.45% in 4 (0.06%; a linear system, 200 logged episodes of 100 steps, as in
    ``tests/test_model_rollouts.py``).
    The reference is the other folds, 1 - 1/RADIUS_FOLDS of the rows: the distance is
    larger than to all rows by about (1 - 1/RADIUS_FOLDS)^(-1/d), 6% in 4 dimensions.

    The quantile is taken per fold and the median over folds kept: one episode that went
    where no other did supplies the most isolated states, all in one fold, and would
    otherwise set the radius (review: 1.5 sd became 6.7 sd with one such episode among 200).
    With fewer than RADIUS_FOLDS episodes there are no folds of several episodes to stand
    for a new one: ``spacing``, the stricter rule (the nearest other state of any episode,
    :func:`_spacing_radius`). 0 on a
    lattice: when at least SUPPORT_QUANTILE of the states repeat exactly."""
    from scipy.spatial import cKDTree

    if len(z) < 2:
        return 0.0
    _, inverse, counts = np.unique(z, axis=0, return_inverse=True, return_counts=True)
    if (counts[inverse.ravel()] > 1).mean() >= SUPPORT_QUANTILE:
        return 0.0
    share = min(1.0, MAX_RADIUS_PROBES / len(z))
    eps = np.unique(episode)
    if len(eps) < RADIUS_FOLDS:
        return spacing
    fold = _episode_folds(episode, eps, RADIUS_FOLDS, rng)
    per_fold = []
    for f in range(RADIUS_FOLDS):
        held = np.flatnonzero(fold == f)
        probe = held if share >= 1.0 else held[rng.random(len(held)) < share]
        if len(probe):
            per_fold.append(float(np.quantile(cKDTree(z[fold != f]).query(z[probe])[0], SUPPORT_QUANTILE)))
    return float(np.median(per_fold))


def remainder_ranges(cost: np.ndarray, terminated: np.ndarray, gamma: float,
                     horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)``, arrays over ``L = 0 .. horizon``: the exact range of the discounted cost
    of ``L`` more steps (0 for ``L = 0``) when non-terminal costs lie in ``[c_lo, c_hi]``
    and terminating ones in ``[k_lo, k_hi]`` (the logged ranges). A path of k non-terminal
    steps then a terminating one is worth at most ``g(k) = c_hi S_k + gamma^k k_hi``
    (``S_k = sum_{j<k} gamma^j``), monotone in k (``g(k+1) - g(k) = gamma^k (c_hi - (1 -
    gamma) k_hi)``), so ``hi(L) = max(c_hi S_L, g(0), g(L - 1))`` (the terminating terms only
    when the logs hold a terminating step); ``lo(L)`` likewise; each end is some path's value.
    Any gamma, 1 included.

    Parameters
    ----------
    cost, terminated : ndarray
        The logged costs and terminal flags.
    gamma : float
    horizon : int

    Returns
    -------
    lo, hi : ndarray, shape (horizon + 1,)
    """
    cost = np.asarray(cost, dtype=np.float64)
    term = np.asarray(terminated, dtype=bool)
    L = np.arange(horizon + 1)
    g = float(gamma) ** np.arange(horizon + 1, dtype=np.float64)
    S = np.r_[0.0, np.cumsum(g[:-1])]  # S[L] = sum_{j<L} gamma^j
    c, k = cost[~term], cost[term]
    lo, hi = np.full(horizon + 1, np.inf), np.full(horizon + 1, -np.inf)
    if len(c):
        lo, hi = float(c.min()) * S, float(c.max()) * S
    if len(k):
        last = np.maximum(L - 1, 0)
        c_lo, c_hi = (float(c.min()), float(c.max())) if len(c) else (0.0, 0.0)
        lo = np.minimum(lo, np.minimum(float(k.min()), c_lo * S[last] + g[last] * float(k.min())))
        hi = np.maximum(hi, np.maximum(float(k.max()), c_hi * S[last] + g[last] * float(k.max())))
    lo[0], hi[0] = 0.0, 0.0
    return lo, hi


def _2d(y: np.ndarray, width: int) -> np.ndarray:
    """scikit-learn returns one output as a vector; always (n, width)."""
    return np.asarray(y, dtype=np.float64).reshape(len(y), width)


def _checked_ranges(n: int, horizon: int, level: float,
                    ranges: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``ranges`` as float arrays over ``0 .. horizon`` remaining steps, after checking
    :func:`model_rollout_value`'s arguments."""
    if n < 2 or horizon < 1 or not 0 < level < 1:
        raise InvalidArgumentError(f"model rollouts need at least 2 particles, a horizon >= 1 and a level in (0, 1); "
                                   f"got n={n}, horizon={horizon}, level={level}")
    lo_r, hi_r = (np.asarray(r, dtype=np.float64) for r in ranges)
    if lo_r.shape != (horizon + 1,) or hi_r.shape != (horizon + 1,):
        raise InvalidArgumentError(f"ranges must be two arrays over 0 .. {horizon} remaining steps "
                                   f"(remainder_ranges), got shapes {lo_r.shape} and {hi_r.shape}")
    return lo_r, hi_r


def _bounds_summary(value: np.ndarray, lower: np.ndarray, upper: np.ndarray, level: float) -> dict[str, Any]:
    """Means over the particles of their value and bounds, and the interval
    ``[mean(lower) - z se(lower), mean(upper) + z se(upper)]`` (``z`` the normal quantile at
    ``level``) around the bounds."""
    from scipy.stats import norm

    n = len(value)
    z = float(norm.ppf(0.5 + level / 2))

    def se(v: np.ndarray) -> float:
        return float(v.std(ddof=1) / np.sqrt(n))

    return {"estimate": float(value.mean()), "lower": float(lower.mean()), "upper": float(upper.mean()),
            "interval": [float(lower.mean() - z * se(lower)), float(upper.mean() + z * se(upper))]}


def _within(model: Any, x: np.ndarray, check: np.ndarray, radius: float) -> np.ndarray:
    """Whether each state is within ``radius`` of the data; only the ``check`` ones (particles
    still within and alive) get the (costly) search, the others read False."""
    out = np.zeros(len(x), bool)
    if check.any():
        out[check] = model.in_data(x[check], radius)
    return out


def model_rollout_value(model: Any, policy: Policy, horizon: int, gamma: float,
                        ranges: tuple[np.ndarray, np.ndarray], *, n: int = N_PARTICLES, level: float = 0.95,
                        seed: int = 0, on_step: Any = None) -> dict[str, Any]:
    """The policy's ``horizon``-step discounted cost under ``model`` and its bounds (module docstring).

    ``model``: a :class:`LoggedDynamics`, or any object with ``start_states_``, ``radius_`` (and optionally
    ``trust_radius_``, default ``radius_``), ``step(states, actions, rng)`` (a ``StepResult``) and
    ``in_data(states, radius)`` (bool per state). ``ranges``: ``lo[L], hi[L]`` for ``L = 0 .. horizon`` remaining
    steps (:func:`remainder_ranges`). ``n`` particles; ``level`` of the Monte-Carlo interval around the bounds.

    Returns ``estimate``, ``lower``, ``upper`` (the bounds' means), ``interval``, ``exit_mass`` (share of the
    discounted survival mass at or after leaving the data), ``exit_share`` (the expected share of episodes that
    leave the data before they end: the mean survival probability at leaving), ``past_data_cost`` (the
    reading's part read past the data: ``mean_i sum_{t >= sigma_i} w_it |c_it|``), ``n_particles``, ``radius``
    (support), ``trust_radius`` (the bounds') and ``support_quantile``. ``on_step()``: called after each step.
    """
    lo_r, hi_r = _checked_ranges(n, horizon, level, ranges)
    rng = np.random.default_rng([seed, 7])
    starts = model.start_states_
    x = starts[rng.integers(0, len(starts), n)].astype(np.float64)
    alive = np.ones(n)
    inside, trusted = np.ones(n, bool), np.ones(n, bool)
    value, kept, mass, mass_out, past = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    lo_tail, hi_tail = np.zeros(n), np.zeros(n)
    alive_at_exit = np.zeros(n)
    trust = min(float(getattr(model, "trust_radius_", model.radius_)), float(model.radius_))

    for t in range(horizon):
        if not alive.any():
            break
        act = policy.act_index(x, t, rng)
        live = alive > 0
        in_data, in_trust = _within(model, x, inside & live, model.radius_), _within(model, x, trusted & live, trust)
        r = model.step(x, act, rng)
        w = alive * gamma**t
        left = inside & ~in_data
        alive_at_exit[left] = alive[left]
        inside &= in_data
        untrusted = trusted & ~in_trust  # the bounds stop reading the model here
        lo_tail[untrusted] = w[untrusted] * lo_r[horizon - t]
        hi_tail[untrusted] = w[untrusted] * hi_r[horizon - t]
        trusted &= in_trust
        value += w * r.costs
        kept += np.where(trusted, w * r.costs, 0.0)
        mass += w
        mass_out += np.where(inside, 0.0, w)
        past += np.where(inside, 0.0, w * np.abs(r.costs))
        alive = alive * (1.0 - r.terminated)
        x = r.next_states
        if on_step is not None:
            on_step()
    return {**_bounds_summary(value, kept + lo_tail, kept + hi_tail, level),
            "exit_mass": float(mass_out.sum() / mass.sum()) if mass.sum() > 0 else 0.0,
            "exit_share": float(alive_at_exit.mean()), "past_data_cost": float(past.mean()),
            "n_particles": int(n), "radius": float(model.radius_),
            "trust_radius": trust, "support_quantile": SUPPORT_QUANTILE}


def model_rollouts(ds: TransitionDataset, policy: Policy, horizon: int, gamma: float, *, n: int = N_PARTICLES,
                   level: float = 0.95, seed: int = 0, arrays: TransitionArrays | None = None,
                   on_step: Any = None, bootstrap: Any = None) -> dict[str, Any]:
    """Fit :class:`LoggedDynamics` on ``ds`` and roll ``policy`` out in it
    (:func:`model_rollout_value`) with the logged costs' :func:`remainder_ranges`; adds
    ``noise`` and ``method``. ``bootstrap(model, arrays, ranges, estimate)``: the model's own
    interval, kept as ``bootstrap`` (:func:`offline_adp.evaluation.model_bootstrap.bootstrap_reading`).
    ``{"skipped": reason}`` where it does not apply: no episode logged from step 0, or states on
    a lattice (repeated exactly: the support radius is 0, and a regression's next state is never
    exactly on the lattice)."""
    a = arrays if arrays is not None else ds.arrays()
    if not (a.step == 0).any():
        return {"skipped": "no episode is logged from step 0: no start states to roll out from"}
    model = LoggedDynamics(random_state=seed).fit(ds, a)
    if model.radius_ <= 0:
        return {"skipped": "the logged states repeat exactly (a lattice): a model's next states are never on it; "
                           "FQE reads such logs without extrapolating between states"}
    ranges = remainder_ranges(a.cost, a.terminated, gamma, horizon)
    out = model_rollout_value(model, policy, horizon, gamma, ranges, n=n, level=level, seed=seed, on_step=on_step)
    if bootstrap is not None:
        out["bootstrap"] = bootstrap(model, a, ranges, out["estimate"])
    return {**out, "noise": model.noise_source_,  # no timings: metrics.json is deterministic
            "method": f"{n} rollouts of a model fitted on the logs (increments: ridge + extra-trees on its residuals "
                      "+ out-of-fold residual noise; cost and termination: extra-trees on state, action, next state), "
                      "each particle's remaining steps valued at the ends of the logged costs' range once it is "
                      "farther from the logged states than they are from each other"}
