"""Policy search by dynamic programming (Bagnell, Kakade, Ng & Schneider 2003; the
chapter's Algorithm 14) and iterated PSDP (Algorithms 15 and 16).

Access model: a generative model (states are drawn from a baseline distribution mu_t
and simulated from there), or a reset model when mu_t comes from rollouts of a baseline
policy (then every simulated state was reached from a reset). Costs are minimised.

PSDP (Algorithm 14), horizon T::

    for t = T-1, ..., 0:
        s_1..s_n ~ mu_t
        for every action a:  Q_t(s_i, a) = c(s_i, a) + sum_{k > t} gamma^(k-t) c_k
                             (rollouts of the already-learned pi_{t+1}, ..., pi_{T-1},
                              m per (s_i, a), common random numbers across actions)
        pi_t = classification: a cost-sensitive classifier, label argmin_a Q_t(s_i, a),
                               weight max_a Q_t(s_i, a) - min_a Q_t(s_i, a)
               regression:     greedy in a regression fit of Q_t
    return (pi_0, ..., pi_{T-1})

Guarantee (the chapter's Theorem 2): with eps_t = E_{s ~ mu_t}[Q_t(s, pi_t(s)) -
min_a Q_t(s, a)] (estimated on held-out states from mu_t, ``history_["eps_hat"]``), for every reference policy,
``J(pi) <= J(pi_ref) + sum_t eps_t * ||mu_ref_t / mu_t||_inf`` (:func:`psdp_bound`).

Iterated PSDP (Algorithms 15, 16)::

    pi = pi_start;  J = value(pi)
    repeat:
        mu_t = state distribution of pi at each t (Monte-Carlo)
        pi' = PSDP(mu);  J' = value(pi')
        if J' < J: pi, J = pi', J'   else: stop
    return pi                         (never worse than pi_start, by construction)
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np
import pandas as pd
from sklearn.base import clone
from sklearn.utils._param_validation import HasMethods, StrOptions

from offline_adp import dp
from offline_adp.access import (
    FullModel,
    GenerativeModel,
    ResetModel,
    Simulator,
    StepResult,
    require,
)
from offline_adp.algorithms.params import (
    GAMMA,
    NON_NEGATIVE_INT,
    POSITIVE_INT,
    SEED,
    CheckedEstimator,
    check_learner,
    refuse_continuous,
)
from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import InvalidArgumentError
from offline_adp.policies import (
    ClassifierPolicy,
    GreedyPolicy,
    NonStationaryPolicy,
    Policy,
    apply_feature_map,
    attach_signature,
)
from offline_adp.qfunctions import QEncoder, RegressorQ
from offline_adp.regressors import CLASSIFIERS, REGRESSORS, make_classifier, make_regressor
from offline_adp.rollout import rollout, run_episodes, state_samples

Baseline = TransitionDataset | Policy | list | Callable[[int, int, np.random.Generator], np.ndarray]


class PSDP(CheckedEstimator):
    """Policy search by dynamic programming (Algorithm 14).

    Parameters
    ----------
    horizon : int or None
        T (default: the model's horizon).
    n_samples : int
        States drawn from mu_t at each step.
    n_rollouts : int
        Rollouts per (state, action) for the Q estimates.
    learner : {"classification", "regression"}
    classifier : str or estimator
        For classification (``lightgbm``, ``extra_trees``, ``tabular`` or any classifier).
    regressor : str or estimator
        For regression (any LEARN of :mod:`offline_adp.regressors`).
    learner_params : dict, optional
        Parameters for the registry classifier or regressor.
    feature_map : transformer or callable, optional
        What the classifier or regressor sees of a state (e.g. drop features that do
        not matter for control); applied as ``transform(obs)`` or ``feature_map(obs)``.
    q_estimator : {"rollout", "exact"}
        ``exact`` computes Q_t by dynamic programming on a full model (the test oracle).
    gamma : float or None
    n_holdout : int or None
        Fresh states drawn from mu_t at each step, not used to learn pi_t, on which
        ``eps_hat`` is measured (default ``n_samples // 4``; 0: measure on the training
        states, which is biased low).
    random_state : int

    Attributes
    ----------
    policy_ : NonStationaryPolicy
    history_ : DataFrame ``step, eps_hat, eps_train, mean_q_min, seconds``
        ``eps_hat``: the mean estimated excess cost of pi_t's choice on held-out states
        from mu_t (the eps_t of the bound); ``eps_train``: the same on the training
        states (optimistic: pi_t was fitted to them).
    samples_ : list of (states, Q estimates) per step (for diagnostics and the bound)
    simulator_steps_ : int
        Simulator transitions used.
    """

    _parameter_constraints: ClassVar[dict[str, list[Any]]] = {
        "horizon": [POSITIVE_INT, None],
        "n_samples": [POSITIVE_INT],
        "n_rollouts": [POSITIVE_INT],
        "learner": [StrOptions({"classification", "regression"})],
        "classifier": [StrOptions(set(CLASSIFIERS)), HasMethods(["fit", "predict"])],
        "regressor": [StrOptions(set(REGRESSORS)), HasMethods(["fit", "predict"])],
        "learner_params": [dict, None],
        "feature_map": [HasMethods(["transform"]), callable, None],
        "q_estimator": [StrOptions({"rollout", "exact"})],
        "gamma": [GAMMA, None],
        "n_holdout": [NON_NEGATIVE_INT, None],
        "random_state": [SEED],
    }

    def __init__(self, horizon: int | None = None, n_samples: int = 500, n_rollouts: int = 5,
                 learner: str = "classification",
                 classifier: Any = "extra_trees", regressor: Any = "extra_trees", learner_params: dict | None = None,
                 feature_map: Any = None, q_estimator: str = "rollout", gamma: float | None = None,
                 n_holdout: int | None = None, random_state: int = 0) -> None:
        self.horizon = horizon
        self.n_samples = n_samples
        self.n_rollouts = n_rollouts
        self.learner = learner
        self.classifier = classifier
        self.regressor = regressor
        self.learner_params = learner_params
        self.feature_map = feature_map
        self.q_estimator = q_estimator
        self.gamma = gamma
        self.n_holdout = n_holdout
        self.random_state = random_state

    def _check_param_combinations(self) -> None:
        """The learner in use takes ``learner_params`` (see :mod:`~offline_adp.algorithms.params`)."""
        super()._check_param_combinations()
        if self.learner == "regression":
            check_learner(self, f"the regressor {self.regressor!r}", "learner_params", make_regressor, self.regressor,
                          self.learner_params)
        else:
            check_learner(self, f"the classifier {self.classifier!r}", "learner_params", make_classifier,
                          self.classifier, self.learner_params)

    # ------------------------------------------------------------------ algorithm 14
    def fit(self, model: ResetModel, baseline: Baseline) -> PSDP:
        self.check_params()  # _parameter_constraints, then the combinations
        require(model, ResetModel if isinstance(baseline, Policy) else GenerativeModel)
        if isinstance(baseline, TransitionDataset):  # as `fit --algorithm psdp` (not its bins behind the user's back)
            refuse_continuous(type(self).__name__, baseline)
        if self.q_estimator == "exact":
            require(model, FullModel)
        T = self.horizon if self.horizon is not None else model.horizon
        if not T:
            raise InvalidArgumentError("PSDP needs a horizon")
        gamma = self.gamma if self.gamma is not None else model.gamma
        rng = np.random.default_rng(self.random_state)
        mu = self._baseline_sampler(model, baseline, T, rng)
        steps: list[Policy | None] = [None] * T
        rows, self.samples_, self.simulator_steps_ = [], [None] * T, 0
        for t in range(T - 1, -1, -1):
            t0 = time.perf_counter()
            S = mu(t, self.n_samples, rng)  # s_i ~ mu_t
            future = steps[t + 1 :]
            Q = self._exact_q(model, S, t, future, gamma,
                              T) if self.q_estimator == "exact" else self._rollout_q(model, S, t, future, gamma, T)
            steps[t] = self._learn(S, Q, model.n_actions)  # pi_t
            chosen = steps[t].act_index(S, t, rng)  # type: ignore[union-attr]
            eps_train = float(np.mean(Q[np.arange(len(S)), chosen] - Q.min(axis=1)))
            self.samples_[t] = (S, Q)
            n_out = self.n_samples // 4 if self.n_holdout is None else int(self.n_holdout)
            eps_out = eps_train
            if n_out > 0:  # eps_t on fresh states from mu_t: pi_t never saw them
                H = mu(t, n_out, rng)
                QH = self._exact_q(model, H, t, future, gamma, T) if self.q_estimator == "exact" else \
                    self._rollout_q(model, H, t, future, gamma, T, stream=1)
                ch = steps[t].act_index(H, t, rng)  # type: ignore[union-attr]
                eps_out = float(np.mean(QH[np.arange(len(H)), ch] - QH.min(axis=1)))
            rows.append({"step": t, "eps_hat": eps_out, "eps_train": eps_train,
                         "mean_q_min": float(Q.min(axis=1).mean()),
                         "seconds": time.perf_counter() - t0})
        self.policy_ = attach_signature(NonStationaryPolicy(steps), model)  # type: ignore[arg-type]
        self.history_ = pd.DataFrame(rows)
        return self

    def _baseline_sampler(self, model: ResetModel, baseline: Baseline, T: int, rng: np.random.Generator):
        if isinstance(baseline, TransitionDataset):  # mu_t = the data's states at step t
            per_t = [baseline.states_at(t) for t in range(T)]
            for t, x in enumerate(per_t):
                if not len(x):
                    raise InvalidArgumentError(f"the baseline dataset has no state at step {t}; shorten the horizon to "
                                               "the episodes' length")
            return lambda t, n, r: per_t[t][r.integers(0, len(per_t[t]), n)]
        if isinstance(baseline, Policy):  # mu_t = states of the baseline policy's rollouts
            per_t = state_samples(model, baseline, self.n_samples, T, rng)
            return lambda t, n, r: per_t[t][r.integers(0, len(per_t[t]), n)]
        if isinstance(baseline, list | tuple):
            return lambda t, n, r: np.asarray(baseline[t])[r.integers(0, len(baseline[t]), n)]
        return baseline

    def _rollout_q(self, model: ResetModel, S: np.ndarray, t: int, future: list, gamma: float, T: int,
                   stream: int = 0) -> np.ndarray:
        """Q_t(s_i, a): mean over m rollouts of the learned future policies.

        All actions advance in one batch (one policy call per step); the simulator is
        called per action block with the same seed, so the blocks see the same random
        numbers (common random numbers across actions).
        """
        n, m, A = len(S), self.n_rollouts, model.n_actions
        X0 = np.repeat(S, m, axis=0)
        B = len(X0)
        block = np.repeat(np.arange(A), B)  # block a holds rows a * B .. (a + 1) * B and starts with action a
        total = np.zeros(A * B)
        live = {"rows": np.arange(A * B)}  # the running rows, in run_episodes' order

        def act(xs: np.ndarray, j: int, rng: np.random.Generator) -> np.ndarray:
            return block.copy() if j == 0 else future[j - 1].act_index(xs, t + j, rng)

        def step(xs: np.ndarray, a: np.ndarray, rng: np.random.Generator) -> StepResult:
            seed = int(rng.integers(2**62))  # one seed per step, shared by the action blocks
            nxt, cost, term = np.empty_like(xs), np.empty(len(xs)), np.empty(len(xs), bool)
            for b in range(A):
                sel = np.flatnonzero(block[live["rows"]] == b)
                if not len(sel):
                    continue
                r = model.step_seeded(xs[sel], a[sel], seed) if isinstance(model, Simulator) else \
                    model.step(xs[sel], a[sel], np.random.default_rng(seed))
                nxt[sel], cost[sel], term[sel] = r.next_states, r.costs, r.terminated
            self.simulator_steps_ += len(xs)
            return StepResult(nxt, cost, term)

        def visit(j: int, idx: np.ndarray, xs: np.ndarray, a: np.ndarray, r: StepResult) -> None:
            total[idx] += gamma**j * r.costs
            live["rows"] = idx[~r.terminated]

        rng = np.random.default_rng([self.random_state, t] + ([stream] if stream else []))
        run_episodes(step, act, np.tile(X0, (A, 1)), T - t, rng, visit=visit)
        return total.reshape(A, n, m).mean(axis=2).T

    def _exact_q(self, model: FullModel, S: np.ndarray, t: int, future: list, gamma: float, T: int) -> np.ndarray:
        all_states = np.arange(model.n_states, dtype=np.float64)[:, None]
        V = np.zeros(model.n_states)  # V_T = 0; back up through the learned future policies
        for k in range(T - 1, t, -1):
            pk = future[k - t - 1].probabilities(all_states, k)
            Qk = model.C + gamma * np.einsum("ast,t->sa", model.P, V)
            V = (pk * Qk).sum(axis=1)
        Qt = model.C + gamma * np.einsum("ast,t->sa", model.P, V)
        return Qt[S[:, 0].astype(np.int64)]

    def _learn(self, S: np.ndarray, Q: np.ndarray, n_actions: int) -> Policy:
        if self.learner == "regression":
            fmap = self.feature_map if (self.feature_map is None
                                        or hasattr(self.feature_map, "transform")) else _Map(self.feature_map)
            enc = QEncoder(n_actions, np.eye(n_actions), feature_map=fmap)
            reg = make_regressor(self.regressor, **(self.learner_params or {}))
            reg.fit(enc.all_pairs(enc.phi(S)), Q.T.reshape(-1))
            return GreedyPolicy(RegressorQ([reg], enc))
        label = Q.argmin(axis=1)
        weight = Q.max(axis=1) - Q.min(axis=1)  # what a wrong choice can cost
        keep = weight > 0
        if not keep.any() or len(np.unique(label[keep])) == 1:
            return ClassifierPolicy(None, n_actions, constant=int(label[keep][0]) if keep.any() else 0)
        clf = make_classifier(self.classifier, **(self.learner_params or {}))
        clf.fit(apply_feature_map(self.feature_map, S[keep]), label[keep], sample_weight=weight[keep])
        return ClassifierPolicy(clf, n_actions, feature_map=self.feature_map)


class _Map:
    """A callable feature map as a transformer."""

    def __init__(self, fn: Any) -> None:
        self.fn = fn

    def transform(self, obs: np.ndarray) -> np.ndarray:
        return apply_feature_map(self.fn, obs)


def psdp_bound(eps: np.ndarray, mu_ref: np.ndarray, mu: np.ndarray) -> float:
    """``sum_t eps_t * max_s mu_ref_t(s) / mu_t(s)``.

    ``+inf`` where mu_t misses mass of mu_ref_t, even when ``eps_t = 0``: eps_t is measured
    on mu_t, so it says nothing about the states only mu_ref_t visits (0 x inf is no bound).
    """
    ratio = np.where(mu > 0, mu_ref / np.where(mu > 0, mu, 1.0), np.where(mu_ref > 0, np.inf, 0.0)).max(axis=1)
    if np.isinf(ratio).any():
        return float("inf")
    return float(np.sum(np.asarray(eps) * ratio))


class IteratedPSDP(CheckedEstimator):
    """Iterated PSDP (Algorithms 15, 16): PSDP on the state distribution of the current
    policy, kept only while the value improves; never worse than the start.

    Parameters
    ----------
    psdp : PSDP
    n_rounds : int
        Rounds at most (>= 0; 0 returns the start policy).
    n_eval_episodes : int
        Rollouts for the value estimates (fixed seed: common random numbers), unless
        ``exact_values`` on a full model.
    exact_values : bool
    random_state : int
    """

    _parameter_constraints: ClassVar[dict[str, list[Any]]] = {
        "psdp": [PSDP, None],
        "n_rounds": [NON_NEGATIVE_INT],
        "n_eval_episodes": [POSITIVE_INT],
        "exact_values": ["boolean"],
        "random_state": [SEED],
    }

    def __init__(self, psdp: PSDP | None = None, n_rounds: int = 5, n_eval_episodes: int = 500,
                 exact_values: bool = False,
                 random_state: int = 0) -> None:
        self.psdp = psdp
        self.n_rounds = n_rounds
        self.n_eval_episodes = n_eval_episodes
        self.exact_values = exact_values
        self.random_state = random_state

    def _value(self, model: Any, policy: Policy, T: int, gamma: float) -> float:
        if self.exact_values:
            require(model, FullModel)
            states = np.arange(model.n_states, dtype=np.float64)[:, None]
            pi = np.stack([policy.probabilities(states, t) for t in range(T)])
            return float(model.initial_distribution @ dp.policy_evaluation_finite(model.P, model.C, pi, T, gamma).V[0])
        return rollout(model, policy, self.n_eval_episodes, np.random.default_rng(self.random_state), horizon=T,
                       gamma=gamma).mean

    def fit(self, model: ResetModel, start_policy: Policy) -> IteratedPSDP:
        self.check_params()  # _parameter_constraints, then the combinations
        proto = self.psdp if self.psdp is not None else PSDP()
        T = proto.horizon if proto.horizon is not None else model.horizon
        gamma = proto.gamma if proto.gamma is not None else model.gamma
        rng = np.random.default_rng(self.random_state)
        pi, J = start_policy, self._value(model, start_policy, T, gamma)
        rows = [{"round": 0, "value": J, "accepted": True, "simulator_steps": 0}]
        for r in range(1, self.n_rounds + 1):
            mu = state_samples(model, pi, proto.n_samples, T, rng)  # Algorithm 15: mu_t of the current policy
            cand = clone(proto).set_params(random_state=self.random_state + r).fit(model, list(mu))
            Jc = self._value(model, cand.policy_, T, gamma)
            accepted = Jc < J
            rows.append({"round": r, "value": Jc, "accepted": accepted, "simulator_steps": cand.simulator_steps_})
            if not accepted:  # Algorithm 16: keep the best, stop when the value does not improve
                break
            pi, J = cand.policy_, Jc
        self.policy_, self.value_ = pi, J
        self.history_ = pd.DataFrame(rows)
        return self
