"""Approximate policy iteration (the chapter's section 8.2).

Access model: trace data only; optionally a reset or generative model to add episodes
of the current policy between iterations. Evaluate with fitted Q evaluation, improve
greedily, repeat::

    pi_0 = initial policy (uniform by default)
    for k = 0, 1, ...:
        Q^{pi_k} = FQE(pi_k, D)                            # approximate evaluation
        pi_{k+1}(x, t) = argmin_a Q^{pi_k}(x, a, t)        # greedy improvement
        stop if pi_{k+1} = pi_k on every state of D, or after the budget
        (optional) D = D + episodes of pi_{k+1}

Over continuous commands (a dataset whose action table is ``continuous``, the evaluator's
``commands="auto"``): FQE evaluates the deterministic command policy (``Q(x', pi(x'))``),
the improvement minimises over ``C(x)``, the commands logged at the evaluator's
``n_candidates`` nearest logged states (as FittedQIteration's backup), so no policy ever
commands what the logs did not try near ``x``; ``pi_0`` is the command logged at the
nearest logged state, and "changed" counts states whose command vector changed.
"""

from __future__ import annotations

import time
from typing import Any, ClassVar

import numpy as np
import pandas as pd
from sklearn.base import clone
from sklearn.utils._param_validation import HasMethods

from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.algorithms.fqi_data import command_representatives, logged_commands
from offline_adp.algorithms.params import (
    NON_NEGATIVE_INT,
    POSITIVE_INT,
    SEED,
    CheckedEstimator,
    invalid_parameter,
)
from offline_adp.data.dataset import TransitionDataset
from offline_adp.policies import (
    GreedyCommandPolicy,
    GreedyPolicy,
    NearestCommandPolicy,
    Policy,
    UniformPolicy,
    attach_signature,
)
from offline_adp.qfunctions import NeighbourCommands, with_candidates


def _greedy_actions(policy: Policy, obs: np.ndarray, horizon: int | None) -> np.ndarray:
    steps = range(horizon) if horizon else [0]
    if getattr(policy, "continuous", False):  # the commands themselves
        return np.stack([policy.commands(obs, t) for t in steps])  # type: ignore[attr-defined]
    return np.stack([policy.probabilities(obs, t).argmax(axis=1) for t in steps])


def _continuous(proto: FittedQEvaluation, dataset: TransitionDataset) -> bool:
    """Whether the iteration runs over continuous commands: the evaluator's ``commands``,
    with ``"auto"`` resolved by the dataset's action table."""
    return proto.commands == "continuous" or (proto.commands == "auto" and dataset.info.action_table.continuous)


def _improve(q: Any, candidates: Any) -> Policy:
    """``pi_{k+1} = argmin_a Q^{pi_k}(x, a)``; over continuous commands the minimum runs over
    the commands logged at the nearest logged states (FittedQIteration's candidate set)."""
    if candidates is None:
        return GreedyPolicy(q)
    return GreedyCommandPolicy(with_candidates(q, candidates))


class ApproximatePolicyIteration(CheckedEstimator):
    """Approximate policy iteration with FQE as the evaluation step.

    Parameters
    ----------
    fqe : FittedQEvaluation
        Prototype of the evaluator (cloned each iteration with the current policy).
    n_iterations : int
        Budget of improvement steps (>= 1).
    initial_policy : Policy, optional
        ``pi_0``; uniformly random by default.
    model : ResetModel, optional
        If given, ``episodes_per_iteration`` episodes of each new policy are added.
    episodes_per_iteration : int
        (>= 0).
    random_state : int
        Seeds the collection of new episodes (>= 0).

    Attributes
    ----------
    policy_ : GreedyPolicy  (the last improved policy)
    q_function_ : the last evaluation's Q
    history_ : DataFrame ``iteration, value, changed, n_transitions, fit_seconds``
        ``value`` is FQE's estimate of the evaluated policy's expected cost from the
        data's start states; ``changed`` the fraction of data states whose greedy action
        changed.
    """

    _parameter_constraints: ClassVar[dict[str, list[Any]]] = {
        "fqe": [FittedQEvaluation, None],
        "n_iterations": [POSITIVE_INT],
        "initial_policy": [HasMethods(["probabilities"]), None],
        "model": [HasMethods(["initial_states", "step"]), None],
        "episodes_per_iteration": [NON_NEGATIVE_INT],
        "random_state": [SEED],
    }

    def __init__(self, fqe: FittedQEvaluation | None = None, n_iterations: int = 10,
                 initial_policy: Policy | None = None,
                 model: Any = None, episodes_per_iteration: int = 0, random_state: int = 0) -> None:
        self.fqe = fqe
        self.n_iterations = n_iterations
        self.initial_policy = initial_policy
        self.model = model
        self.episodes_per_iteration = episodes_per_iteration
        self.random_state = random_state

    def fit(self, dataset: TransitionDataset, sample_weight: np.ndarray | None = None) -> ApproximatePolicyIteration:
        self.check_params()  # _parameter_constraints, then the combinations
        proto = self.fqe if self.fqe is not None else FittedQEvaluation()
        cands = None
        if _continuous(proto, dataset):  # C(x): the commands logged at the nearest logged states
            u = logged_commands(dataset, type(self).__name__)
            cands = NeighbourCommands.from_data(dataset.arrays().obs, u, proto.n_candidates,
                                                command_representatives(u, proto.n_representatives))
            if proto.feature_map is not None:
                raise invalid_parameter(self, "fqe", "an evaluator without feature_map over continuous commands",
                                        proto)
        start = UniformPolicy(dataset.n_actions) if cands is None else NearestCommandPolicy(cands)
        pi: Policy = self.initial_policy if self.initial_policy is not None else start
        if cands is not None:
            attach_signature(pi, dataset)
        rng = np.random.default_rng(self.random_state)
        data, w = dataset, sample_weight
        rows: list[dict[str, Any]] = []
        prev_actions = None
        for k in range(self.n_iterations):
            t0 = time.perf_counter()
            fqe = clone(proto).set_params(policy=pi).fit(data, sample_weight=w)  # Q^{pi_k}
            improved = _improve(fqe.q_function_, cands)  # pi_{k+1} = argmin_a Q^{pi_k}
            attach_signature(improved, dataset)
            states = np.vstack([data.arrays().obs, data.arrays().next_obs])
            actions = _greedy_actions(improved, states, proto.horizon)
            same = actions == prev_actions if prev_actions is not None and prev_actions.shape == actions.shape else None
            changed = 1.0 if same is None else float(1.0 - (same.all(axis=-1) if cands is not None else same).mean())
            rows.append({"iteration": k, "value": fqe.value_, "changed": changed, "n_transitions": len(data),
                         "fit_seconds": time.perf_counter() - t0})
            # over commands, the Q kept is the one the improvement read (over the neighbours' commands)
            q_kept = improved.q if cands is not None else fqe.q_function_  # type: ignore[attr-defined]
            self.q_function_, self.policy_, self.fqe_ = q_kept, improved, fqe
            if changed == 0.0:
                break
            prev_actions, pi = actions, improved
            if self.model is not None and self.episodes_per_iteration:
                from offline_adp.rollout import collect

                new = collect(self.model, improved, self.episodes_per_iteration, rng, source="policy",
                              episode_prefix=f"api{k:03d}")
                data = TransitionDataset.concat([data, new])
                w = None if w is None else np.r_[w, np.ones(len(new))]
        self.history_ = pd.DataFrame(rows)
        attach_signature(self.policy_, dataset)
        return self
