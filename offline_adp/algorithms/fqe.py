"""Approximate policy evaluation: fitted Q evaluation (the chapter's Algorithms 12, 13).

Access model: trace data only. Evaluates a given policy pi (deterministic or stochastic,
stationary or time-varying) from logged transitions; costs are minimised.

Finite horizon T (Algorithm 12)::

    Q^pi_T = 0
    for t = T-1, ..., 0:
        y_i = c_i + gamma * (1 - terminated_i) * sum_a' pi(a' | x'_i, t+1) Q^pi_{t+1}(x'_i, a')
        Q^pi_t = LEARN({((x_i, a_i), y_i)})

Infinite horizon (Algorithm 13): the same backup with one Q^pi, iterated.

Per-sample weights (``fit(..., sample_weight=w)``) make LEARN a weighted regression;
*on-policy weighting* (``w_i`` = expected time pi spends in ``x_i``, see
:func:`on_policy_weights`) is the chapter's remedy for the divergence of linear
evaluation (the two-state example, :mod:`offline_adp.examples.two_state`).
It is the loop of :func:`~offline_adp.algorithms.fqi_loop.fitted_q_loop` with the policy's
backup (:class:`~offline_adp.algorithms.fqi_data.PolicyBackup`); everything else
(learners, monitor, modes, resume) is shared with
:class:`~offline_adp.algorithms.fqi.FittedQIteration`. A finite horizon ``T`` works with
any ``gamma`` (e.g. a T-step evaluation on discounted logs): ``Q^pi_t`` for t = 0..T-1,
the backup at step t using ``pi(. | x', t+1)`` (time-varying policies honoured).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from sklearn.utils._param_validation import HasMethods

from offline_adp.algorithms.fqe_bootstrap import (
    averaged_fixed_point,
    bounded_value,
    query_operators,
    reweight_query_operator,
    support_operators,
)
from offline_adp.algorithms.fqe_sweeps import LeafAverage, PolicyRead
from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.algorithms.fqi_data import CommandBackup, PolicyBackup, Prepared
from offline_adp.algorithms.fqi_loop import FitState
from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import InvalidArgumentError, InvalidTypeError, NotFittedError
from offline_adp.learn import FrozenTreesLearner
from offline_adp.policies import Policy, is_stationary
from offline_adp.qfunctions import PolicyCommands, QFunction
from offline_adp.trees.averaging import release_freed


def check_command_policy(est: Any, dataset: TransitionDataset) -> None:
    """A continuous policy can be evaluated on ``dataset``: it carries exact commands of
    the policy's width, and the policy is stationary (its command does not depend on t)."""
    if est.commands == "binned":
        raise InvalidArgumentError(f"{type(est).__name__}: the policy commands continuous values; "
                                   "commands='binned' cannot evaluate it (use 'auto' or 'continuous')")
    u = dataset.commands()
    if u is None:
        raise InvalidArgumentError(f"{type(est).__name__}: the policy commands continuous values, the dataset "
                                   f"carries no exact commands ({dataset.info.action_table.command_columns})")
    x = dataset.arrays().obs[:64]
    probe = np.asarray(est.policy.commands(x[:1], 0))
    varies = probe.shape == (1, u.shape[1]) and any(
        not np.array_equal(est.policy.commands(x, t), est.policy.commands(x, 0)) for t in (1, 7, 50, 500))
    if getattr(est.policy, "time_varying", False) or varies:
        raise InvalidArgumentError(f"{type(est).__name__}: a time-varying continuous policy cannot be evaluated yet "
                                   "(its command depends on the step)")
    if probe.shape != (1, u.shape[1]):
        raise InvalidArgumentError(f"{type(est).__name__}: the policy's commands have shape {probe.shape[1:]}, the "
                                   f"dataset's {u.shape[1]} components {list(dataset.info.action_table.dims)}")


class FittedQEvaluation(FittedQIteration):
    """Fitted Q evaluation of ``policy``.

    Parameters
    ----------
    policy : Policy
        The policy to evaluate (deterministic or stochastic, stationary or time-varying);
        required by ``fit``.
    horizon, gamma, regressor, regressor_params, action_encoding, action_input, feature_map, \
n_iterations, tol, rtol, trees_per_iteration, infeasible_cost, target_noise, next_state_noise, \
validation_fraction, on_divergence, patience, divergence_slack, initial_q, random_state, tree_builder, \
commands, n_candidates, n_representatives
        As :class:`~offline_adp.algorithms.fqi.FittedQIteration`'s, with the same
        defaults and allowed values (``tests/test_estimator_checks.py`` holds them
        equal); the loop backs up ``sum_a' pi(a' | x') Q(x', a')`` instead of the minimum.
        A deterministic continuous policy (``policy.commands``) on a dataset of exact
        commands is evaluated over commands (``commands="auto"``): ``Q(x, u)`` on the
        logged commands, the backup ``Q(x', pi(x'))``; ``n_candidates`` is not used.
    mode : {"refit", "auto", "frozen", "warm_start"}, default "refit"
        As FittedQIteration's; **the default differs** (FittedQIteration: ``"auto"``).
    n_structures : int or None, default 4
        As FittedQIteration's; **the default differs** (FittedQIteration: None, builds at
        1, 4, 16, 64 with ``n_iterations="auto"`` at gamma 0.99, one per 12.5 with a count).
    structure_max_samples : float, list of (float or None), "auto" or None, default None
        As FittedQIteration's; **the default differs** (FittedQIteration: ``"auto"``, a
        bootstrap of 131,072 rows beyond that many; None: the regressor's own sampling,
        all rows for the default extra-trees).
    early_build_trees : int, "auto" or None, default None
        As FittedQIteration's; **the default differs** (FittedQIteration: ``"auto"``, a
        fifth of the forest in the builds before the last of ``n_iterations="auto"``'s
        schedule). None: every frozen build grows the whole forest. Approximate policy
        iteration's evaluator sets ``"auto"`` (measured there: docs/algorithms.md).

    Why the first three differ: they are FittedQIteration's defaults from before its
    ``mode="auto"``. FittedQIteration moved to ``mode="auto"`` with one build per 12.5
    iterations and to ``structure_max_samples="auto"`` on the evidence of
    the FQI benchmark suite (docs/fqi-modes.md), which scores the greedy policies
    FQI returns, not policy evaluations; FQE's were not moved with them, so an FQE
    estimate did not change. The evaluation reports choose their own settings
    (:data:`offline_adp.evaluation.fqe_interval.DEFAULT_FQE`: ``mode="frozen"``).

    ``early_build_trees`` differs because the early builds were measured on FQI's greedy
    policies, not on policy evaluations, so an FQE estimate does not change unless asked.

    FittedQIteration's ``screen_trees`` and ``screen_tol`` are not parameters here (always
    None). The screen bounds the bias of a greedy backup's minimum over actions, and FQE's
    backup takes no minimum (docs/fqi-modes.md).

    Attributes
    ----------
    q_function_ : QFunction
        ``Q^pi`` (or a TimeIndexedQ for a finite horizon).
    policy_ : Policy
        The evaluated policy.
    value_ : float
        ``mean over start states of sum_a pi(a | x_0, 0) Q^pi(x_0, a)``: the estimated
        expected cost of pi from the data's start distribution.
    """

    _parameter_constraints: ClassVar[dict[str, list[Any]]] = {
        **{k: v for k, v in FittedQIteration._parameter_constraints.items()
           if k not in ("screen_trees", "screen_tol")},
        "policy": [HasMethods(["probabilities"]), None],
    }

    def __init__(self, policy: Policy | None = None, horizon: int | None = None, gamma: float | None = None,
                 regressor: Any = "extra_trees", regressor_params: dict | None = None, action_encoding: str = "joint",
                 action_input: str = "value", feature_map: Any = None, n_iterations: int | str = "auto",
                 tol: float | None = None,
                 rtol: float = 0.01,
                 mode: str = "refit", trees_per_iteration: int = 10, infeasible_cost: float | None = None,
                 target_noise: float = 0.0, next_state_noise: float = 0.0, validation_fraction: float = 0.0,
                 on_divergence: str = "warn", patience: int = 10, divergence_slack: float = 0.1,
                 initial_q: QFunction | None = None, random_state: int = 0, n_structures: int = 4,
                 structure_max_samples: float | list[float | None] | str | None = None, tree_builder: str = "auto",
                 commands: str = "auto", n_candidates: int = 8, n_representatives: int = 16,
                 early_build_trees: int | str | None = None) -> None:
        self.policy = policy
        super().__init__(horizon=horizon, gamma=gamma, regressor=regressor, regressor_params=regressor_params,
                         action_encoding=action_encoding, action_input=action_input, feature_map=feature_map,
                         n_iterations=n_iterations, tol=tol, rtol=rtol, mode=mode,
                         trees_per_iteration=trees_per_iteration,
                         infeasible_cost=infeasible_cost, target_noise=target_noise, next_state_noise=next_state_noise,
                         validation_fraction=validation_fraction, on_divergence=on_divergence, patience=patience,
                         divergence_slack=divergence_slack, initial_q=initial_q, random_state=random_state,
                         n_structures=n_structures, structure_max_samples=structure_max_samples,
                         screen_trees=None,  # the screen is about a greedy backup's min
                         early_build_trees=early_build_trees,
                         tree_builder=tree_builder, commands=commands, n_candidates=n_candidates,
                         n_representatives=n_representatives)

    def fit_iter(self, dataset: TransitionDataset, sample_weight: np.ndarray | None = None, resume: dict | None = None,
                 *, deferred: bool = False):
        """As :meth:`FittedQIteration.fit_iter`, with the policy's backup; sets ``value_`` at the end."""
        if self.policy is None:
            raise InvalidArgumentError("FittedQEvaluation needs the policy to evaluate (policy=...)")
        if not isinstance(dataset, TransitionDataset):
            raise InvalidTypeError(f"FittedQEvaluation.fit needs a TransitionDataset, got {type(dataset).__name__}")
        continuous = getattr(self.policy, "continuous", False)
        if continuous:
            check_command_policy(self, dataset)
        elif self.policy.n_actions != dataset.n_actions:
            raise InvalidArgumentError(f"the policy has {self.policy.n_actions} actions, the dataset "
                                       f"{dataset.n_actions}")
        yield from self.run_fitted_q(dataset, sample_weight, resume, self._backup, deferred=deferred)
        a = dataset.arrays()
        start = a.step == 0
        x0 = a.obs[start] if start.any() else a.obs[:1]
        if getattr(self, "commands_", None) == "continuous":  # Q(x0, pi(x0)): the one candidate
            self.value_ = float(self.q_function_.values(x0, 0)[:, 0].mean())
        else:
            self.value_ = float((self.policy.probabilities(x0, 0) * self.q_function_.values(x0, 0)).sum(axis=1).mean())

    def _policy_commands(self) -> Any:
        """Over continuous commands the backup's candidate is the policy's command,
        ``V(x') = Q(x', pi(x'))`` (Algorithm 13 for a deterministic continuous policy)."""
        return PolicyCommands(self.policy) if getattr(self.policy, "continuous", False) else None

    def _backup(self, data: Prepared) -> Any:
        if data.encoder.continuous:  # one candidate per state, the policy's command: its value
            sizes = {"next": len(data.train.next_obs), "start": len(data.start_obs)}
            if data.valid is not None:
                sizes["valid_next"] = len(data.valid.next_obs)
            return CommandBackup(sizes)
        sets = {"next": data.train.next_obs, "start": data.start_obs}
        if data.valid is not None:
            sets["valid_next"] = data.valid.next_obs
        # a stationary policy's probabilities at the query sets are computed once, not once per
        # step: a finite-horizon FQE of a greedy policy re-ran the policy's whole model T times
        stationary = is_stationary(self.policy, data.train.next_obs, getattr(self, "horizon_", self.horizon))
        return PolicyBackup(self.policy, sets, stationary)

    def settle(self, tol: float | None = None, max_iterations: int = 10_000) -> int:
        """Iterate the fitted tree structure's leaf averaging to its fixed point
        (``mode="frozen"``, discounted only) and refresh ``q_function_`` and ``value_``.

        A frozen fit stops after ``n_iterations`` in all, so its last structure may have
        had only a few averaging sweeps (with 4 structures over 60 iterations, 15: the
        value has moved by ``gamma^15`` of its distance to the fixed point). This runs
        ``v <- M (c + gamma (1 - term) * sum_a' pi(a'|x') A_next v)`` (a sup-norm
        gamma-contraction: the leaf and query operators average) until the distance to
        the fixed point is at most ``tol`` (``gamma / (1 - gamma)`` times the last sweep's
        change; default ``1e-7 (u + max |v|)``, ``u`` the power of two ``u <= max |c| < 2u``): the estimate is then
        the fixed point of the averager the structure defines, the same quantity
        :meth:`reweighted_value` computes for other weights, so bootstrap replicates are
        centred on it. Returns the number of sweeps run (also in ``settled_iterations_``).
        """
        fit = self._check_conditional()
        d, learner = fit.data, fit.learner
        self.q_function_ = None  # type: ignore[assignment]  # its node values not held through the solve
        sweeps = None
        try:  # M and P applied from the fit's leaf positions (fqe_sweeps: their matrices' numbers, not made)
            v = learner.leaf_values  # solved in place (the fit's buffer): no second copy held through the sweeps
            if not (v.dtype == np.float64 and v.flags.writeable and v.flags.c_contiguous):
                v = learner.leaf_values = np.array(v, dtype=np.float64)
            P = PolicyRead(learner.pos["next"], np.asarray(fit.backup.probabilities("next", 0), dtype=np.float64),
                           len(learner.leaf_ids))
            sweeps = averaged_fixed_point(d, LeafAverage(learner), P, v, tol, max_iterations, in_place=True)[1]
        finally:  # the values moved (on an exception: to the sweeps' last values): Q and value_ read them
            learner._cache = {}
            self._forget_replicate_values()
            if self.q_function_ is None:
                self.q_function_ = learner.snapshot()
            a0 = d.start_obs  # the backup's start probabilities: the policy's (its one command, over commands)
            self.value_ = float((fit.backup.probabilities("start", 0) * self.q_function_.values(a0, 0)).sum(axis=1)
                                .mean())
            self.settled_iterations_ = sweeps
        release_freed()  # the solve's operators
        return sweeps

    def reweighted_value(self, sample_weight: np.ndarray, n_iterations: int | None = None, tol: float | None = None,
                         rtol: float = 1e-7) -> float:
        """The value estimate for other per-row weights, *keeping the fitted tree structure*
        (``mode="frozen"``, discounted only): the fixed point of
        ``v <- M_w (c + gamma (1 - term) * sum_a' pi(a'|x') A_next v)`` with the leaf
        averaging operator ``M_w`` of the new weights (leaves left without weight are
        dropped from the average over trees), to within ``tol`` of the fixed point (default
        ``rtol (u + max |v|)``, as :meth:`settle`) or ``n_iterations`` sweeps. It is solved
        over the training rows (:mod:`~offline_adp.algorithms.fqe_replicates`: ``y =
        targets(P_w M_w y)``, Gauss-Seidel sweeps back through each episode, the same
        stopping bound) where ``P_w M_w`` is sparse, else by sweeps over the leaf values
        (:func:`~offline_adp.algorithms.fqe_bootstrap.fixed_point`), from the fitted leaf
        values. This is
        a structure-conditional bootstrap replicate: it captures the noise of the data
        through the leaves but not the variability of the tree structure itself. With
        all weights 1 it is the fixed point :meth:`settle` reaches. Rows must be the
        training rows (no ``validation_fraction``).
        """
        from offline_adp.algorithms.fqe_replicates import replicate_value

        fit = self._check_conditional()
        if not rtol > 0:
            raise InvalidArgumentError(f"rtol must be > 0, got {rtol!r}")
        d = fit.data
        w = np.asarray(sample_weight, dtype=np.float64)
        if w.shape != (d.n,):
            raise InvalidArgumentError(f"sample_weight has shape {w.shape}; the fit has {d.n} training rows")
        rs, ve = self._row_space()
        if rs is None:  # leaves of many rows: the leaf-space sweeps (fqe_bootstrap.fixed_point's numbers)
            learner = fit.learner
            W = np.asarray(learner.leaf_weight_sums(w), dtype=np.float64)
            P = PolicyRead(learner.pos["next"], np.asarray(fit.backup.probabilities("next", 0), dtype=np.float64),
                           len(learner.leaf_ids), keep=W > 0)  # P_w and M_w applied, not made
            v, _ = averaged_fixed_point(d, LeafAverage(learner, weights=w, weight_sums=W), P, learner.leaf_values,
                                        tol, n_iterations or 10_000, rtol)
            q0 = (reweight_query_operator(self._query_operators(("start",))["start"], W > 0) @ v)
            q0 = q0.reshape(d.n_actions, -1).T
            v0 = (fit.backup.probabilities("start", 0) * q0).sum(axis=1)
            w0 = w[d.start_rows]
            return float(np.sum(w0 * v0) / np.sum(w0)) if np.sum(w0) > 0 else float("nan")
        return replicate_value(rs, d, fit.learner, self._query_operators(("start",))["start"],
                               np.asarray(fit.backup.probabilities("start", 0), dtype=np.float64), w, tol, rtol,
                               n_iterations or 10_000, ve)

    def drop_trees(self) -> None:
        """Free what only reads Q at new inputs: ``q_function_`` (None after this) and the
        learner's tree arrays and compiled lookups (20 trees on 1M rows: ~2.4 GB), keeping
        ``value_`` and the leaf positions and values :meth:`reweighted_value` and
        :meth:`support_bounds` read (their numbers do not change). For a caller that has
        read every Q it needs (:func:`~offline_adp.evaluation.fqe_interval.read_where_fitted`)."""
        learner = self._check_conditional().learner
        learner.ensemble, learner._forest, learner._cache = None, None, {}
        if learner.leaf_values is not None and learner.leaf_values.base is not learner._values:
            learner._values = None  # the buffer settle() replaced (learner.predict rebuilds it when asked)
        self.q_function_ = None  # type: ignore[assignment]
        release_freed()  # the trees' pages back to the system, not left in the heap for smaller arrays only

    def _forget_replicate_values(self) -> None:
        """The replicates' start values at the query entries (:meth:`_row_space`) are read
        again: the leaf values moved in place (:meth:`settle`)."""
        cached = self.__dict__.get("_row_space_cache")
        if cached is not None:
            self.__dict__["_row_space_cache"] = (*cached[:2], None, None)

    def drop_replicate_cache(self) -> None:
        """Free the replicates' shared structure (:meth:`_row_space`), rebuilt when next asked."""
        self.__dict__.pop("_row_space_cache", None)
        release_freed()

    def _row_space(self) -> tuple[Any, np.ndarray | None]:
        """The replicates' shared structure (:func:`~offline_adp.algorithms.fqe_replicates.row_space`,
        None where it would be dense), built once per fit, and the fitted leaf values at its
        query entries."""
        from offline_adp.algorithms.fqe_replicates import row_space, row_space_sparse

        fit = self.fit_state_
        cached = self.__dict__.get("_row_space_cache")
        if cached is None or cached[0] is not fit.learner:
            pi = np.asarray(fit.backup.probabilities("next", 0), dtype=np.float64)
            ops = self.__dict__.get("_ops_cache")
            held = ops is not None and ops[0] is fit.learner and "next" in ops[1]
            # the next-state operator only while the row space is built (not held through the replicates),
            # and not at all where the row space would be dense
            rs = None if not row_space_sparse(fit.learner, pi) else row_space(
                fit.learner, ops[1]["next"] if held else query_operators(fit.learner, ("next",))["next"], pi)
            cached = (fit.learner, rs, None, None)
            release_freed()
        # at the query entries (settle moves them)
        if cached[1] is not None and cached[2] is not fit.learner.leaf_values:
            values = fit.learner.leaf_values
            cached = (*cached[:2], values, np.asarray(values, dtype=np.float64)[cached[1].q_leaf])
        self.__dict__["_row_space_cache"] = cached
        return cached[1], cached[3]

    def support_bounds(self, lower: float, upper: float, min_tree_share: float = 1e-9,
                       radius: float | None = None) -> dict[str, float]:
        """Start values of the fitted structure's *per-action read* with every pair the logs
        cannot read valued ``lower`` and then ``upper``
        (:func:`~offline_adp.algorithms.fqe_bootstrap.support_operators`; ``mode="frozen"``,
        discounted only): ``{"lower", "upper", "unsupported_next", "unsupported_start"}``, the
        last two the policy's mean probability mass on unsupported pairs at the next and the
        start states. With ``lower`` and ``upper`` bounds on any Q value (e.g. from the
        cost's range), the two values bracket what the same leaves say about the policy once
        other actions' rows no longer stand in for its own."""
        fit = self._check_conditional()
        d = fit.data
        if d.encoder.continuous:
            raise InvalidArgumentError("support_bounds reads the fitted structure per action-table entry; over "
                                       "continuous commands there is no such entry (evaluation/continuous.py measures "
                                       "command support instead)")
        # each action's query rows made when read, not the whole next-state operator (held: ~0.5 GiB at 1M rows)
        P, u, P0, u0 = support_operators(d, fit.backup, fit.learner, None, min_tree_share, radius)
        return {"lower": bounded_value(d, P, u, P0, u0, float(lower)),
                "upper": bounded_value(d, P, u, P0, u0, float(upper)),
                "unsupported_next": float(u.mean()) if len(u) else 0.0,
                "unsupported_start": float(u0.mean()) if len(u0) else 0.0}

    def _query_operators(self, names: tuple[str, ...] = ("next", "start")) -> dict[str, Any]:
        """The fitted structure's query operators ``names`` (next-state, start-state), each built
        once per fit when first asked for (every replicate reweights the same ones)."""
        learner = self.fit_state_.learner
        cached = self.__dict__.get("_ops_cache")
        if cached is None or cached[0] is not learner:
            cached = (learner, {})
        missing = tuple(k for k in names if k not in cached[1])
        if missing:
            cached = (learner, {**cached[1], **query_operators(learner, missing)})
        self.__dict__["_ops_cache"] = cached
        return cached[1]

    def _check_conditional(self) -> FitState:
        """The fit's :class:`~offline_adp.algorithms.fqi_loop.FitState`, if it is one the
        structure-conditional methods apply to."""
        fit = getattr(self, "fit_state_", None)
        if fit is None:
            raise NotFittedError("this FittedQEvaluation is not fitted in this process (fit it first)")
        if (not isinstance(fit.learner, FrozenTreesLearner) or self.horizon_ is not None or fit.data.valid is not None
                or fit.data.gamma >= 1.0):
            raise InvalidArgumentError("needs a discounted (gamma < 1) FQE fitted with mode='frozen' and no "
                                       "validation split")
        return fit

    def _result_policy(self, q: QFunction) -> Any:
        return self.policy


def on_policy_weights(state_index: np.ndarray, occupancy: np.ndarray) -> np.ndarray:
    """Per-sample weights ``w_i = occupancy[s_i]``: the expected (discounted) time the
    evaluated policy spends in each sample's state, e.g. ``(1 - gamma)^-1`` times
    :func:`offline_adp.dp.discounted_occupancy` for tabular problems."""
    return np.asarray(occupancy, dtype=np.float64)[np.asarray(state_index, dtype=np.int64).reshape(-1)]
