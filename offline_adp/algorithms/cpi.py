"""Conservative policy iteration (Kakade & Langford 2002; the chapter's section 8.2).

Access model: a reset model for rollout estimates of candidate policies, or trace data
only (estimates by fitted Q evaluation, i.e. off-policy). The policy is a stochastic
mixture that keeps its components and weights::

    pi_0 = initial policy;  J_0 = estimate(pi_0)
    for k = 0, 1, ...:
        Q^{pi_k} = FQE(pi_k, D)
        pi'      = argmin_a Q^{pi_k}(x, a)                     (greedy)
        alpha    = argmin_{alpha in grid, incl. 0} estimate((1 - alpha) pi_k + alpha pi')
                   (line search; or Kakade & Langford's step
                    alpha = A / (4 R H),  A = E_{x ~ D}[V^{pi_k}(x) - Q^{pi_k}(x, pi'(x))],
                    R = max |c|,  H = 1 / (1 - gamma) (discounted) or T (gamma = 1,
                    horizon T; with both, the smaller): Kakade & Langford's (1 - gamma)
                    is 1 / H)
        pi_{k+1} = (1 - alpha) pi_k + alpha pi'
        J_{k+1}  = estimate(pi_{k+1})

Because ``alpha = 0`` is a candidate and the estimator is deterministic (common random
numbers: every rollout estimate uses the same seed), the estimated cost never increases.
For the same reason ``alpha = 0`` is a fixed point: ``pi_{k+1} = pi_k`` gets the same
evaluation, greedy policy and candidates again, so the iteration stops there with the
verdict ``converged`` (no step improves the estimate); after ``n_iterations`` steps without
it the verdict is ``still changing``.
"""

from __future__ import annotations

import time
from typing import Any, ClassVar

import numpy as np
import pandas as pd
from sklearn.base import clone
from sklearn.utils._param_validation import HasMethods, StrOptions

from offline_adp.algorithms.api import default_evaluator, uniform_over_logged
from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.algorithms.params import (
    FRACTION,
    NON_NEGATIVE_INT,
    POSITIVE_INT,
    SEED,
    CheckedEstimator,
    invalid_parameter,
    refuse_continuous,
)
from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import InvalidArgumentError
from offline_adp.policies import (
    GreedyPolicy,
    MixturePolicy,
    Policy,
    attach_signature,
)
from offline_adp.qfunctions import q_support, restrict_to_support
from offline_adp.rollout import rollout

DEFAULT_STEPS = (0.0, 0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0)


def effective_horizon(gamma: float, horizon: int | None) -> float:
    """``H`` of the Kakade-Langford step: ``1 / (1 - gamma)``, or the horizon T when gamma = 1
    (the smaller of the two when both are finite)."""
    h = 1.0 / (1.0 - gamma) if gamma < 1.0 else np.inf
    if horizon is not None:
        h = min(h, float(horizon))
    if not np.isfinite(h):
        raise InvalidArgumentError("the Kakade-Langford step needs gamma < 1 or a finite horizon")
    return h


def _verdict(rows: list[dict[str, Any]], budget: int) -> tuple[str, str]:
    """``(verdict_, verdict_message_)`` from the history rows (iteration 0 first)."""
    last = rows[-1]
    if len(rows) > 1 and last["alpha"] == 0.0:
        return "converged", (f"at iteration {last['iteration']} no step of the line search improves the estimated "
                             f"cost {last['value']:.4g} (alpha = 0): a fixed point of the iteration")
    if budget == 0:
        return "still changing", "no improvement step was run (n_iterations = 0): the initial policy"
    return "still changing", (f"the budget of {budget} iterations ended with a step alpha = {last['alpha']:g} "
                              f"(estimated cost {last['value']:.4g}): more iterations may improve it")


class ConservativePolicyIteration(CheckedEstimator):
    """Conservative policy iteration with a line search (or the Kakade-Langford step).

    Parameters
    ----------
    fqe : FittedQEvaluation, optional
        Prototype for ``Q^{pi_k}`` (and for the off-policy estimates without a model); default
        API's evaluator, FQE on FittedQIteration's tree schedule (``api.EVALUATOR_DEFAULTS``).
    n_iterations : int
        Improvement steps (>= 0; 0 returns the initial policy).
    step_rule : {"line_search", "kakade_langford"}
    step_sizes : sequence of float
        Line-search grid, each in [0, 1] (0 is always added).
    model : ResetModel, optional
        Rollout estimates when given (``n_eval_episodes`` episodes, fixed seed), else
        FQE estimates from the logs.
    n_eval_episodes : int
        (>= 1).
    initial_policy : Policy, optional
        ``pi_0``; by default uniformly random over the actions the data holds
        (:func:`~offline_adp.algorithms.api.uniform_over_logged`).
    random_state : int
        The rollout estimates' seed (>= 0).

    Attributes
    ----------
    policy_ : MixturePolicy
    history_ : DataFrame ``iteration, alpha, value, n_components, seconds``
    simulator_steps_ : int
        Transitions simulated by the rollout estimates (0 with FQE estimates).
    verdict_ : str
        ``converged`` (a step of 0 was chosen: a fixed point) or ``still changing``.
    verdict_message_ : str
    """

    _parameter_constraints: ClassVar[dict[str, list[Any]]] = {
        "fqe": [FittedQEvaluation, None],
        "n_iterations": [NON_NEGATIVE_INT],
        "step_rule": [StrOptions({"line_search", "kakade_langford"})],
        "step_sizes": [list, tuple, np.ndarray],
        "model": [HasMethods(["initial_states", "step"]), None],
        "n_eval_episodes": [POSITIVE_INT],
        "initial_policy": [HasMethods(["probabilities"]), None],
        "random_state": [SEED],
    }

    def _check_param_combinations(self) -> None:
        """Every line-search step size in [0, 1] (see :mod:`~offline_adp.algorithms.params`)."""
        super()._check_param_combinations()
        sizes = list(np.ravel(np.asarray(self.step_sizes, dtype=object)))
        if not all(FRACTION.is_satisfied_by(a) and not isinstance(a, bool) for a in sizes):
            raise invalid_parameter(self, "step_sizes", "a sequence of step sizes in [0, 1]", self.step_sizes)

    def __init__(self, fqe: FittedQEvaluation | None = None, n_iterations: int = 10, step_rule: str = "line_search",
                 step_sizes: tuple[float, ...] = DEFAULT_STEPS, model: Any = None, n_eval_episodes: int = 500,
                 initial_policy: Policy | None = None, random_state: int = 0) -> None:
        self.fqe = fqe
        self.n_iterations = n_iterations
        self.step_rule = step_rule
        self.step_sizes = step_sizes
        self.model = model
        self.n_eval_episodes = n_eval_episodes
        self.initial_policy = initial_policy
        self.random_state = random_state

    def _estimate(self, policy: Policy, data: TransitionDataset, w: np.ndarray | None) -> float:
        if self.model is not None:  # common random numbers: the same seed for every candidate
            rng = np.random.default_rng(self.random_state)
            res = rollout(self.model, policy, self.n_eval_episodes, rng,
                          horizon=self._proto().horizon or self.model.horizon)
            self.simulator_steps_ += int(res.length.sum())
            return res.mean
        return clone(self._proto()).set_params(policy=policy).fit(data, sample_weight=w).value_

    def _proto(self) -> FittedQEvaluation:
        """The evaluator: ``fqe``, else API's (:func:`~offline_adp.algorithms.api.default_evaluator`:
        FQE on FittedQIteration's tree schedule, its last structure's fixed point solved)."""
        return self.fqe if self.fqe is not None else default_evaluator()

    def fit(self, dataset: TransitionDataset, sample_weight: np.ndarray | None = None) -> ConservativePolicyIteration:
        self.check_params()  # _parameter_constraints, then the combinations
        self.simulator_steps_ = 0
        refuse_continuous(type(self).__name__, dataset)
        pi0 = self.initial_policy if self.initial_policy is not None else uniform_over_logged(dataset, sample_weight)
        pi = MixturePolicy([pi0], [1.0])
        value = self._estimate(pi, dataset, sample_weight)
        rows = [{"iteration": 0, "alpha": 0.0, "value": value, "n_components": 1, "seconds": 0.0}]
        a = dataset.arrays()
        r_max = float(np.abs(a.cost).max()) or 1.0
        for k in range(1, self.n_iterations + 1):
            t0 = time.perf_counter()
            fqe = clone(self._proto()).set_params(policy=pi).fit(dataset, sample_weight=sample_weight)  # Q^{pi_k}
            greedy = GreedyPolicy(fqe.q_function_)
            if self.step_rule == "kakade_langford":
                q = fqe.q_function_.values(a.obs, a.step)
                v = (pi.probabilities(a.obs, a.step) * q).sum(axis=1)
                # expected improvement, >= 0: Q of the greedy action (over a lookup table's logged actions)
                adv = float(np.mean(v - restrict_to_support(q, q_support(fqe.q_function_, a.obs, a.step)).min(axis=1)))
                gamma = fqe.gamma_  # resolved by the fit (offline_adp.data.discount)
                horizon = fqe.horizon_ or dataset.info.horizon or int(a.step.max()) + 1
                alphas = [0.0, float(np.clip(adv / (4 * r_max * effective_horizon(gamma, horizon)), 0.0, 1.0))]
            else:
                alphas = sorted({0.0, *self.step_sizes})
            cands = [(alpha, pi.mix(greedy, alpha) if alpha > 0 else pi) for alpha in alphas]
            scored = [(self._estimate(c, dataset, sample_weight) if alpha > 0 else value, alpha,
                       c) for alpha, c in cands]
            best_value, best_alpha, best = min(scored, key=lambda s: (s[0], s[1]))
            pi, value = best, best_value  # type: ignore[assignment]
            rows.append({"iteration": k, "alpha": best_alpha, "value": value, "n_components": len(pi.components),
                         "seconds": time.perf_counter() - t0})
            if best_alpha == 0.0:  # pi_{k+1} = pi_k: the same evaluation and candidates again (module docstring)
                break
        self.verdict_, self.verdict_message_ = _verdict(rows, self.n_iterations)
        self.policy_ = attach_signature(pi, dataset)
        self.history_ = pd.DataFrame(rows)
        return self
