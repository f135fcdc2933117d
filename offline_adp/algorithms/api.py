"""Approximate policy iteration (the chapter's section 8.2).

Access model: trace data only; optionally a reset or generative model to add episodes
of the current policy between iterations. Evaluate with fitted Q evaluation, improve
greedily, repeat::

    pi_0 = initial policy (by default uniform over the actions D holds)
    for k = 0, 1, ...:
        Q^{pi_k} = FQE(pi_k, D)                                         # approximate evaluation
        J_k = mean over D's start states x_0 of Q^{pi_k}(x_0, pi_k)       # its estimated cost
        stop if J_k > min_{j<k} J_j: return the pi_j of the minimum     # (j >= 1 for the default pi_0)
        pi_{k+1}(x, t) = argmin_a Q^{pi_k}(x, a, t)                     # greedy improvement
        stop if pi_{k+1} = pi_k on every state of S                     # a fixed point: converged
        stop if pi_{k+1} = pi_j on every state of S for some j < k      # a cycle
        stop after the budget
        (optional) D = D + episodes of pi_{k+1}

``S``: the states at which FQE reads the policy, the next states ``x'_i`` of D (its
backups) and D's start states (its estimate ``J``); the policy anywhere else does not
change its evaluation. ``pi_{k+1} = pi_k`` on ``S`` is the fixed-point condition of
policy iteration there: ``pi_k`` greedy with respect to its own evaluation.

The stops. With exact evaluations policy iteration strictly improves until
``pi_{k+1} = pi_k`` (then ``pi_k`` is optimal), so ``J_k`` never rises and no policy comes
back (Puterman 1994, section 6.4). With approximate ones it only reaches a neighbourhood
of the optimum (Bertsekas & Tsitsiklis 1996, section 6.2: ``limsup ||J^{pi_k} - J*|| <=
2 gamma eps / (1 - gamma)^2`` for an evaluation error ``eps``), where the evaluation errors
decide the greedy actions. A rise of ``J_k`` (beyond rounding) and a repeated policy both
say it is there: the evaluations' errors (their iterations' tolerance, the structures'
approximation) now outweigh the improvement, and more iterations would only move about in
it. After a rise the policy of the lowest estimate is returned; on data that grows with
new episodes the estimates are of other data and are not compared. ``verdict_`` says which
stop ended the fit: ``"converged"`` only at a fixed point whose evaluation converged
(FQE's own verdict), else ``"still changing"`` with the reason (a rise, a cycle, the
budget, or the evaluation not converged), or ``"diverging"`` (the evaluation's).

The evaluator is by default FittedQEvaluation with FittedQIteration's tree schedule
(:data:`EVALUATOR_DEFAULTS`: a frozen structure built at geometrically spaced iterations,
a fifth of the forest before the last build, the last structure's fixed point solved;
docs/fqi-modes.md). What it costs against FQI, and what else was tried (evaluations
started from the last one's Q, a single build), is measured in docs/algorithms.md.
The greedy actions the stops compare are the ones the next evaluation's backups read:
computed once for both, at the next states from the values the evaluation's frozen
structure already looked up there.

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
from offline_adp.errors import IncompatibleError
from offline_adp.learn import FrozenTreesLearner
from offline_adp.policies import (
    GreedyCommandPolicy,
    GreedyPolicy,
    NearestCommandPolicy,
    Policy,
    UniformPolicy,
    attach_signature,
)
from offline_adp.qfunctions import NeighbourCommands, with_candidates


def uniform_over_logged(dataset: TransitionDataset, sample_weight: np.ndarray | None = None) -> UniformPolicy:
    """The default start of policy iteration (API, CPI): uniform over the actions the logs
    take (with positive weight). An action they never take is valued by extrapolation (a
    lookup table's fill value 0, an optimistic cost), and a start that takes it reads
    better than it is (an audit: API returned such a start at 1.399 over its successor's
    1.116, exact values)."""
    held = np.bincount(dataset.arrays().action, minlength=dataset.n_actions,
                       weights=None if sample_weight is None else np.asarray(sample_weight, np.float64)) > 0
    return UniformPolicy(dataset.n_actions, None if held.all() or not held.any() else np.flatnonzero(held).tolist())


#: The evaluator's settings where API's differ from FittedQEvaluation's own defaults: those of
#: FittedQIteration (a frozen tree structure where it applies, built at geometrically spaced
#: iterations, a fifth of the forest in the builds before the last, the last one's fixed point
#: solved: docs/fqi-modes.md), measured for API in
#: docs/algorithms.md (FQE's own defaults refit the forest at every one of its iterations).
EVALUATOR_DEFAULTS: dict[str, Any] = {"mode": "auto", "n_structures": None, "structure_max_samples": "auto",
                                      "early_build_trees": "auto"}


def default_evaluator(**params: Any) -> FittedQEvaluation:
    """API's evaluator: ``FittedQEvaluation(**params)`` with :data:`EVALUATOR_DEFAULTS` for
    the keys ``params`` does not set (the CLI's ``[api.fqe]`` table)."""
    return FittedQEvaluation(**{**EVALUATOR_DEFAULTS, **params})


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


def _changed(actions: np.ndarray, other: np.ndarray | None, commands: bool) -> float:
    """The fraction of (state, step) pairs whose greedy action (command vector) differs."""
    if other is None or other.shape != actions.shape:
        return 1.0
    same = actions == other
    return float(1.0 - (same.all(axis=-1) if commands else same).mean())


def _verdict(rows: list[dict[str, Any]], fqe: FittedQEvaluation, stop: str, j: int | None) -> tuple[str, str]:
    """``(verdict_, verdict_message_)`` of the fit (module docstring); ``j``: the policy
    repeated (a cycle) or returned (no improvement)."""
    k = rows[-1]["iteration"]
    where = "the data's next states and start states"
    ev, ev_msg = getattr(fqe, "verdict_", None), getattr(fqe, "verdict_message_", "")
    if stop == "no improvement":  # fqe: pi_j's evaluation
        v = [r["value"] for r in rows]
        return "still changing", (f"the estimated cost of pi_{k} ({v[-1]:.4g}) is above that of pi_{j} ({v[j]:.4g}), "
                                  "the lowest so far: with exact evaluations it could not rise, so their errors now "
                                  f"outweigh the improvement; pi_{j} returned (greedy actions still changed at "
                                  f"{rows[-1]['changed']:.1%} of {where}); the evaluation of pi_{j}: {ev} ({ev_msg})")
    evaluation = f"the evaluation of pi_{k}: {ev} ({ev_msg})" if ev else f"the evaluation of pi_{k} gave no verdict"
    recent = ", ".join(f"{r['changed']:.1%}" for r in rows[-3:])
    if ev == "diverging":
        return "diverging", evaluation
    if stop == "fixed point":
        fixed = f"the greedy policy of pi_{k}'s evaluation is pi_{k} at all {where}"
        if ev in ("converged", "completed"):
            return "converged", f"after {k + 1} evaluations {fixed} (a fixed point of policy iteration); {evaluation}"
        return "still changing", f"{fixed}, but {evaluation}"
    if stop == "cycle":
        return "still changing", (f"the policies cycle: pi_{k + 1} (the greedy policy of pi_{k}'s evaluation) is "
                                  f"pi_{j} at all {where}, so more iterations would repeat pi_{j}..pi_{k} (with "
                                  "exact evaluations policy iteration never revisits a policy: here the evaluations' "
                                  f"errors decide between them); greedy actions changed at {recent} of them in the "
                                  "last iterations")
    return "still changing", (f"after the budget of {k + 1} iterations the greedy action still changed at {recent} "
                              f"of {where} in the last iterations (n_iterations)")


def _next_state_q(fqe: FittedQEvaluation, next_obs: np.ndarray) -> np.ndarray | None:
    """``Q^{pi_k}(x'_i, .)`` at every row's next state as the evaluation's frozen structure
    last computed them (a lookup already made: the same trees and leaf values as its
    ``q_function_``, summed in another order, so equal up to rounding; checked on the first
    rows), or None where the evaluation holds no such array (another learner, a validation
    split, other data)."""
    fit = getattr(fqe, "fit_state_", None)
    learner = getattr(fit, "learner", None)
    if not isinstance(learner, FrozenTreesLearner) or fit.data.valid is not None:
        return None
    q = np.asarray(learner.predict("next"))
    if q.shape != (len(next_obs), fqe.q_function_.n_actions) or not np.array_equal(fit.data.train.next_obs, next_obs):
        return None
    probe = fqe.q_function_.values(next_obs[:64])
    return q if np.allclose(q[:64], probe, rtol=1e-9, atol=1e-9 * (1.0 + np.abs(probe).max())) else None


class _Known(Policy):
    """``policy`` with its greedy actions at ``states`` already known: the stops compute them,
    and the next evaluation's backups read the same (``probabilities`` at exactly those
    rows, or at the leading or trailing block of them, is a table look-up)."""

    def __init__(self, policy: Policy, states: np.ndarray, actions: np.ndarray) -> None:
        self.policy, self.states, self.actions = policy, states, actions
        self.n_actions = policy.n_actions
        self.time_varying = False

    def probabilities(self, obs: np.ndarray, t: Any = 0) -> np.ndarray:
        x = np.asarray(obs, dtype=np.float64)
        n = len(x)
        for rows in (slice(0, n), slice(len(self.states) - n, None)):
            if x.shape[1:] == self.states.shape[1:] and np.array_equal(x, self.states[rows]):
                return np.eye(self.n_actions)[self.actions[rows]]
        return self.policy.probabilities(x, t)


class ApproximatePolicyIteration(CheckedEstimator):
    """Approximate policy iteration with FQE as the evaluation step (module docstring).

    Parameters
    ----------
    fqe : FittedQEvaluation, optional
        Prototype of the evaluator (cloned each iteration with the current policy); by
        default :func:`default_evaluator` (FittedQEvaluation with FittedQIteration's tree
        schedule, :data:`EVALUATOR_DEFAULTS`).
    n_iterations : int
        Budget of evaluations (>= 1); the iteration stops earlier at a fixed point, a rise
        of the estimated cost or a cycle of the greedy policies (module docstring).
    initial_policy : Policy, optional
        ``pi_0``; by default uniformly random over the actions the data holds
        (:func:`uniform_over_logged`), whose estimate is then no candidate for the answer:
        the policy returned is a greedy one.
    model : ResetModel, optional
        If given, ``episodes_per_iteration`` episodes of each new policy are added.
    episodes_per_iteration : int
        (>= 0).
    random_state : int
        Seeds the collection of new episodes (>= 0).

    Attributes
    ----------
    policy_ : GreedyPolicy
        The last improved policy; after a rise of the estimated cost, the policy of the
        lowest estimate (module docstring).
    q_function_ : QFunction
        The evaluation's Q that ``policy_`` is greedy over (the initial policy's own, if
        that is the one returned).
    value_ : float or None
        FQE's estimate of ``policy_``'s cost from the data's start states where ``policy_``
        was evaluated (a fixed point, a cycle, a rise); None after the budget (the last
        improved policy is not evaluated).
    fqe_ : FittedQEvaluation
        The last evaluation kept: ``Q^{pi_k}``'s, whose greedy policy is ``policy_``;
        after a rise, the returned policy's own.
    history_ : DataFrame ``iteration, value, changed, evaluation, n_transitions, fit_seconds, cpu_seconds``
        ``value`` is FQE's estimate of the evaluated policy's expected cost from the
        data's start states; ``changed`` the fraction of the data's next states and start
        states (``S``, module docstring) whose greedy action changed; ``evaluation`` FQE's
        verdict on that evaluation; ``cpu_seconds`` the process CPU of the evaluation and
        improvement.
    verdict_ : str
        ``"converged"``, ``"still changing"`` or ``"diverging"`` (module docstring).
    verdict_message_ : str
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
        proto = self.fqe if self.fqe is not None else default_evaluator()
        cands = None
        if _continuous(proto, dataset):  # C(x): the commands logged at the nearest logged states
            if proto.horizon is not None:  # its improved policy varies with t: FQE refuses it after a first round
                raise IncompatibleError(f"{type(self).__name__} over continuous commands needs an evaluator with "
                                        f"horizon=None (given {proto.horizon}): the policy it improves over a "
                                        "finite-horizon Q varies with the step, and a time-varying continuous "
                                        "policy cannot be evaluated yet; drop the horizon, or fit FQI with it")
            u = logged_commands(dataset, type(self).__name__)
            cands = NeighbourCommands.from_data(dataset.arrays().obs, u, proto.n_candidates,
                                                command_representatives(u, proto.n_representatives))
            if proto.feature_map is not None:
                raise invalid_parameter(self, "fqe", "an evaluator without feature_map over continuous commands",
                                        proto)
        start = uniform_over_logged(dataset, sample_weight) if cands is None else NearestCommandPolicy(cands)
        pi: Policy = self.initial_policy if self.initial_policy is not None else start
        if cands is not None:
            attach_signature(pi, dataset)
        rng = np.random.default_rng(self.random_state)
        data, w = dataset, sample_weight
        rows: list[dict[str, Any]] = []
        a = dataset.arrays()
        # where policies are compared: where an evaluation reads them (the backup's next states, the start states)
        states = np.vstack([a.next_obs, a.obs[a.step == 0]])
        seen: list[np.ndarray] = []  # the greedy actions of pi_1, pi_2, ... there
        stop, repeat, q_prev, best, known = "budget", None, None, None, pi
        self.value_ = None  # the returned policy's estimate, where it was evaluated
        for k in range(self.n_iterations):
            t0, c0 = time.perf_counter(), time.process_time()
            fqe = clone(proto).set_params(policy=known).fit(data, sample_weight=w)  # Q^{pi_k}
            fqe.policy = fqe.policy_ = pi  # (not its table)
            improved = _improve(fqe.q_function_, cands)  # pi_{k+1} = argmin_a Q^{pi_k}
            attach_signature(improved, dataset)
            H = getattr(fqe, "horizon_", None) or proto.horizon  # the evaluator's horizon, also one from the data
            q_next = _next_state_q(fqe, a.next_obs) if cands is None and not H else None
            actions = (_greedy_actions(improved, states, H) if q_next is None else  # (1, |S|)
                       np.r_[q_next.argmin(axis=1), _greedy_actions(improved, states[len(q_next):], None)[0]][None])
            changed = _changed(actions, seen[-1] if seen else None, cands is not None)
            rows.append({"iteration": k, "value": fqe.value_, "changed": changed,
                         "evaluation": getattr(fqe, "verdict_", None), "n_transitions": len(data),
                         "fit_seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0})
            if (best is not None and len(data) == len(dataset)
                    and fqe.value_ > best[0] + 1e-9 * abs(best[0])):  # J(pi_k) > min_j J(pi_j)
                stop = "no improvement"
                self.value_, _, self.policy_, self.q_function_, self.fqe_ = best
                break
            # over commands, the Q kept is the one the improvement read (over the neighbours' commands)
            q_kept = improved.q if cands is not None else fqe.q_function_  # type: ignore[attr-defined]
            # pi_k, the Q it is greedy over, its evaluation; not the default start (uniform, so it takes
            # actions where the logs may hold none: its estimate reads the evaluation's extrapolation there)
            if (k or self.initial_policy is not None) and (best is None or fqe.value_ < best[0]):
                best = (fqe.value_, k, pi, q_prev if k else fqe.q_function_, fqe)
            self.q_function_, self.policy_, self.fqe_ = q_kept, improved, fqe
            if changed == 0.0:  # pi_{k+1} = pi_k
                stop, self.value_ = "fixed point", fqe.value_
                break
            repeat = next((j + 1 for j, s in enumerate(seen[:-1]) if _changed(actions, s, cands is not None) == 0.0),
                          None)
            if repeat is not None:  # pi_{k+1} = pi_j, j < k
                stop, self.value_ = "cycle", rows[repeat]["value"]
                break
            seen.append(actions)
            pi, q_prev = improved, q_kept
            known = pi if cands is not None or H else _Known(pi, states, actions[0])
            if self.model is not None and self.episodes_per_iteration:
                from offline_adp.rollout import collect

                new = collect(self.model, improved, self.episodes_per_iteration, rng, source="policy",
                              episode_prefix=f"api{k:03d}")
                data = TransitionDataset.concat([data, new])
                w = None if w is None else np.r_[w, np.ones(len(new))]
        self.history_ = pd.DataFrame(rows)
        self.verdict_, self.verdict_message_ = _verdict(rows, self.fqe_, stop, repeat if stop == "cycle" else
                                                        best[1] if best is not None else None)
        attach_signature(self.policy_, dataset)
        return self
