"""Model rollouts of the logs: a second, model-based reading of a policy's value whose
errors are not FQE's, and a logs-only measure of how far the policy drives from the data
(docs/evaluation.md, section 2, "Model rollouts").

FQE values a policy through its logged next states: a query ``(x', pi(x'))`` is answered
by the rows whose states the regression puts near ``x'``. Where the policy drifts (a
steering policy that slowly leaves the lane), those rows sit closer to where the data is
dense, and the drift never shows: on the driving problem FQE read a policy that leaves the
road in 95% of its episodes at 8.3 against a truth of 19.6. A model of the *increments*
``x' - x`` does not snap back to the data: rolled out, its states drift as the policy's do.

The model (:class:`LoggedDynamics`), fitted on the logged transitions only (access model:
trace data):

- increments ``(x' - x) / sd = L(x, a) + R(x, a)``: a ridge regression ``L`` (the part of
  the dynamics that is linear in the state and the action's value, extrapolated as such)
  plus extra-trees ``R`` on its residuals (Geurts et al. 2006; what is not linear);
- cost and termination ``(c, P[terminal]) = G(x, a, x')``: extra-trees on the state, the
  action and the next state (costs and failures usually depend on where the step lands);
- support: a state is *in the data* when a logged state lies within the 99.9% quantile of
  the logged states' own nearest-neighbour distances (features in standard deviations).

The rollout (:func:`model_rollout_value`) starts ``n`` particles at logged start states
(resampled), acts with the policy, steps the model, and weighs each step's cost by the
particle's survival probability: ``V = mean_i sum_t gamma^t S_it c_it``, the estimate.
When a particle first reaches a state not in the data, at step ``t``, the model's reading
from there on is an extrapolation; the **bounds** value that rest at the ends of the value
range the logged costs allow for the steps left (``[V_lo, V_hi]``, :func:`remainder_range`), so ``lower = mean_i (sum_{t < t_i} gamma^t S_it c_it + gamma^{t_i}
S_{it_i} V_lo)`` and likewise ``upper``. The interval adds the particles' Monte-Carlo error
(normal, at ``level``). It is a bound on the policy's value *if the model is right where the
data is*; it contains neither the model's error there nor the logs' sampling noise, which
is why :func:`offpolicy.off_policy` takes the hull of it and FQE's interval rather than
either alone. The discounted mass that leaves the data (``exit_mass``) is the logs-only
measure of drift.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from offline_adp.access import StepResult
from offline_adp.data.dataset import TransitionDataset
from offline_adp.policies import Policy

#: A state is in the data when a logged state is at most this quantile of the logged states'
#: own nearest-neighbour distances away (in feature standard deviations). 0.99 flags 1% of
#: the logged states themselves at every step, and over a 200-step rollout nearly every
#: particle of a policy the logs cover (measured on path_tracking: 89% of the default fit's).
SUPPORT_QUANTILE = 0.999
#: rows the model is fitted on at most (a uniform sample above it), and particles per rollout
MAX_FIT_ROWS = 200_000
N_PARTICLES = 1000


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
    random_state : int
    """

    n_estimators: int = 20
    min_samples_leaf: int = 3
    ridge_alpha: float = 1e-3
    random_state: int = 0

    def fit(self, ds: TransitionDataset) -> LoggedDynamics:
        """Fit on every transition of ``ds`` (at most :data:`MAX_FIT_ROWS`, sampled)."""
        from scipy.spatial import cKDTree
        from sklearn.ensemble import ExtraTreesRegressor
        from sklearn.linear_model import Ridge

        a = ds.arrays()
        rng = np.random.default_rng(self.random_state)
        rows = np.arange(len(a.cost)) if len(a.cost) <= MAX_FIT_ROWS else \
            np.sort(rng.choice(len(a.cost), MAX_FIT_ROWS, replace=False))
        obs, nxt = a.obs[rows], a.next_obs[rows]
        self.sd_ = np.where(obs.std(axis=0) > 0, obs.std(axis=0), 1.0)
        values = np.asarray(ds.info.action_table.values, dtype=np.float64).reshape(ds.n_actions, -1)
        vsd = values.std(axis=0)
        self.action_features_ = values / np.where(vsd > 0, vsd, 1.0)
        F = self._features(obs, a.action[rows])
        dx = (nxt - obs) / self.sd_
        trees = {"n_estimators": self.n_estimators, "min_samples_leaf": self.min_samples_leaf, "max_features": 1.0,
                 "random_state": self.random_state, "n_jobs": 1}
        self.linear_ = Ridge(alpha=self.ridge_alpha).fit(F, dx)
        self.residual_ = ExtraTreesRegressor(**trees).fit(F, dx - _2d(self.linear_.predict(F), dx.shape[1]))
        G = np.column_stack([F, nxt / self.sd_])
        self.outcome_ = ExtraTreesRegressor(**trees).fit(G, np.column_stack([a.cost[rows], a.terminated[rows]]))
        z = obs / self.sd_
        self.tree_ = cKDTree(z)
        probe = z if len(z) <= 20_000 else z[rng.choice(len(z), 20_000, replace=False)]
        d, _ = self.tree_.query(probe, k=2)
        self.radius_ = float(np.quantile(d[:, 1], SUPPORT_QUANTILE))
        first = a.step == 0
        if not first.any():  # episodes logged from a later step on: their first rows
            first = np.zeros(len(a.step), bool)
            first[np.unique(a.episode, return_index=True)[1]] = True
        self.start_states_ = a.obs[first]
        return self

    def _features(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        return np.column_stack([obs / self.sd_, self.action_features_[np.asarray(action, dtype=np.int64)]])

    def step(self, states: np.ndarray, actions: np.ndarray) -> tuple[StepResult, np.ndarray]:
        """One model step: (next states, expected cost, termination probability as
        ``terminated``), and whether each *current* state is in the data."""
        F = self._features(states, actions)
        d = states.shape[1]
        nxt = states + (_2d(self.linear_.predict(F), d) + _2d(self.residual_.predict(F), d)) * self.sd_
        out = _2d(self.outcome_.predict(np.column_stack([F, nxt / self.sd_])), 2)
        dist, _ = self.tree_.query(states / self.sd_)
        return StepResult(nxt, out[:, 0], np.clip(out[:, 1], 0.0, 1.0)), dist <= self.radius_


def remainder_range(cost: np.ndarray, terminated: np.ndarray, gamma: float, horizon: int) -> tuple[float, float]:
    """Bounds on the discounted cost of at most ``horizon`` more steps if unseen costs lie
    in the logged ranges: non-terminal costs in ``[c_lo, c_hi]``, terminating ones in
    ``[k_lo, k_hi]``, and 0 once an episode ends. A path of k non-terminal steps then a
    terminating one is worth at most ``g(k) = c_hi S_k + gamma^k k_hi`` (``S_k = sum_{j<k}
    gamma^j``), monotone in k (``g(k+1) - g(k) = gamma^k (c_hi - (1 - gamma) k_hi)``), so the
    upper end is ``max(0, c_hi S_T, g(0), g(T - 1))``; the lower end likewise. Any gamma,
    1 included."""
    cost = np.asarray(cost, dtype=np.float64)
    term = np.asarray(terminated, dtype=bool)

    def S(k: int) -> float:
        return float(np.sum(gamma ** np.arange(k)))

    lo, hi = 0.0, 0.0
    c, k = cost[~term], cost[term]
    c_lo, c_hi = (float(c.min()), float(c.max())) if len(c) else (0.0, 0.0)
    if len(c):
        lo, hi = min(lo, c_lo * S(horizon)), max(hi, c_hi * S(horizon))
    if len(k):
        last = max(horizon - 1, 0)
        hi = max(hi, float(k.max()), c_hi * S(last) + gamma**last * float(k.max()))
        lo = min(lo, float(k.min()), c_lo * S(last) + gamma**last * float(k.min()))
    return lo, hi


def _2d(y: np.ndarray, width: int) -> np.ndarray:
    """scikit-learn returns one output as a vector; always (n, width)."""
    return np.asarray(y, dtype=np.float64).reshape(len(y), width)


def model_rollout_value(model: LoggedDynamics, policy: Policy, horizon: int, gamma: float,
                        value_range: tuple[float, float], *, n: int = N_PARTICLES, level: float = 0.95,
                        seed: int = 0) -> dict[str, Any]:
    """The policy's ``horizon``-step discounted cost under ``model``, with the bounds that
    value each particle's remainder at the ends of ``value_range`` once it leaves the data
    (module docstring). Returns ``estimate``, ``lower``, ``upper`` (bounds' means),
    ``interval`` (with the particles' Monte-Carlo error at ``level``), ``exit_mass`` (mean
    discounted survival weight at leaving the data), ``exit_share`` (share of particles
    that leave), ``n_particles``, ``radius``."""
    from scipy.stats import norm

    rng = np.random.default_rng([seed, 7])
    starts = model.start_states_
    x = starts[rng.integers(0, len(starts), n)].astype(np.float64)
    alive = np.ones(n)
    inside = np.ones(n, bool)
    value = np.zeros(n)
    kept = np.zeros(n)  # cost accrued while in the data
    lo_tail, hi_tail = np.zeros(n), np.zeros(n)
    exit_mass = np.zeros(n)
    v_lo, v_hi = value_range
    for t in range(horizon):
        if not alive.any():
            break
        act = policy.act_index(x, t, rng)
        r, in_data = model.step(x, act)
        left = inside & ~in_data
        w = alive * gamma**t
        lo_tail[left] = w[left] * v_lo
        hi_tail[left] = w[left] * v_hi
        exit_mass[left] = w[left]
        inside &= in_data
        value += w * r.costs
        kept += np.where(inside, w * r.costs, 0.0)
        alive = alive * (1.0 - r.terminated)
        x = r.next_states
    lower, upper = kept + lo_tail, kept + hi_tail
    z = float(norm.ppf(0.5 + level / 2))
    def se(v: np.ndarray) -> float:
        return float(v.std(ddof=1) / np.sqrt(n)) if n > 1 else 0.0

    return {"estimate": float(value.mean()), "lower": float(lower.mean()), "upper": float(upper.mean()),
            "interval": [float(lower.mean() - z * se(lower)), float(upper.mean() + z * se(upper))],
            "exit_mass": float(exit_mass.mean()), "exit_share": float(np.mean(~inside)), "n_particles": int(n),
            "radius": model.radius_, "support_quantile": SUPPORT_QUANTILE}


def model_rollouts(ds: TransitionDataset, policy: Policy, horizon: int, gamma: float,
                   value_range: tuple[float, float], *, n: int = N_PARTICLES, level: float = 0.95,
                   seed: int = 0) -> dict[str, Any]:
    """Fit :class:`LoggedDynamics` on ``ds`` and roll ``policy`` out in it
    (:func:`model_rollout_value`); adds ``cpu_seconds`` and ``method``."""
    t0 = time.process_time()
    model = LoggedDynamics(random_state=seed).fit(ds)
    out = model_rollout_value(model, policy, horizon, gamma, value_range, n=n, level=level, seed=seed)
    return {**out, "value_range": [float(value_range[0]), float(value_range[1])],
            "cpu_seconds": time.process_time() - t0,
            "method": f"{n} rollouts of a model fitted on the logs (increments: ridge + extra-trees on its residuals; "
                      "cost and termination: extra-trees on state, action, next state), each particle's remainder "
                      "valued at the cost range's ends once it leaves the logged states"}


def widen_fqe(fq: Any, mr: dict[str, Any]) -> None:
    """Widen FQE's interval (an ``ope.OPEResult``) to the hull of it and the model
    rollouts' interval, and say where the two readings part: the interval then holds
    the value if either reading is right, and a verdict drawn from it needs both."""
    fq.model_rollouts = mr
    lo_m, hi_m = mr["interval"]
    if not (np.all(np.isfinite(fq.interval)) and np.isfinite(lo_m) and np.isfinite(hi_m)):
        return
    lo_i, hi_i = fq.interval
    fq.interval = (min(lo_i, lo_m), max(hi_i, hi_m))
    fq.interval_method += (f"; widened to the model rollouts' bounds [{lo_m:.4g}, {hi_m:.4g}] (a model of the logged "
                           "increments rolled out, valued at the cost range's ends where it leaves the data)")
    if not lo_i <= mr["estimate"] <= hi_i:
        fq.warnings.append(f"model rollouts of the logs read {mr['estimate']:.4g}, outside FQE's interval "
                           f"[{lo_i:.4g}, {hi_i:.4g}]: the two readings disagree and the interval holds both")
    if mr["exit_mass"] >= 0.05:
        fq.warnings.append(f"the policy drives where the logs do not go: {mr['exit_mass']:.0%} of its discounted "
                           f"model-rollout mass ({mr['exit_share']:.0%} of the rollouts) leaves the logged states")
