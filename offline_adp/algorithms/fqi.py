"""Fitted Q-iteration (the chapter's Algorithms 10 and 11; Ernst, Geurts & Wehenkel 2005).

Access model: trace data only (a :class:`~offline_adp.data.dataset.TransitionDataset`).
Costs are minimised.

Infinite horizon, discounted (Algorithm 11)::

    Q_0 = 0
    for k = 1, 2, ..., K:
        y_i = c_i + gamma * (1 - terminated_i) * min_a' Q_{k-1}(x'_i, a')
        Q_k = LEARN({((x_i, a_i), y_i)})

Finite horizon T (Algorithm 10; one Q per step, all samples at every step because the
dynamics are stationary)::

    Q_T = 0
    for t = T-1, ..., 0:
        y_i = c_i + gamma * (1 - terminated_i) * min_a' Q_{t+1}(x'_i, a')
        Q_t = LEARN({((x_i, a_i), y_i)})

``terminated`` transitions (goal or failure) are nailed to their cost; ``truncated``
ones bootstrap from ``next_obs``. With ``infeasible_cost = c^-`` every target is clamped
to at most ``c^-`` and transitions costing ``>= c^-`` do not bootstrap, so values of
failure states cannot blow up. ``min_a' Q(x'_i, a')`` is one batched prediction over all
(x'_i, a') pairs. See :mod:`offline_adp.learners` for the three ways of doing LEARN
(``mode``): the naive refit loop, the frozen tree structure, and LightGBM warm start.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np
import pandas as pd
from sklearn.base import BaseEstimator

from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import DivergenceWarning, NotFittedError
from offline_adp.learners import FrozenTreesLearner, Learner, LightGBMWarmStartLearner, RefitLearner
from offline_adp.policies import GreedyPolicy, attach_signature
from offline_adp.qfunctions import QEncoder, QFunction, TimeIndexedQ
from offline_adp.regressors import make_regressor

MODES = ("refit", "frozen", "warm_start")


class FittedQIteration(BaseEstimator):
    """Fitted Q-iteration with a pluggable regressor (LEARN).

    Parameters
    ----------
    horizon : int or None
        ``T`` for the finite-horizon Algorithm 10 (one Q per step), ``None`` for the
        discounted Algorithm 11.
    gamma : float or None
        Discount factor; default: the dataset's hint, else 1.0 (finite) / 0.95.
    regressor : str or estimator
        A registry name (:mod:`offline_adp.regressors`) or any scikit-learn regressor,
        cloned for every fit.
    regressor_params : dict, optional
        Parameters for a registry name.
    action_encoding : {"joint", "per_action"}
        One model on ``[phi(x), action]`` or one model per action on ``phi(x)``.
    action_input : {"value", "onehot"}
        What a joint model sees of the action: its value vector from the action table
        (Ernst et al.'s choice) or a one-hot code.
    feature_map : transformer, optional
        ``phi``, fitted on the dataset's observations before LEARN (the chapter: run the
        algorithm on features of the state).
    n_iterations : int
        K for the infinite horizon (ignored for finite horizons).
    tol : float or None
        Stop early when ``sup_i |Q_k - Q_{k-1}|`` on the data falls below ``tol``.
    mode : {"refit", "frozen", "warm_start"}
        ``frozen``: tree structure fitted on the first targets, ``n_iterations`` leaf
        re-averaging iterations, one restructuring on the converged targets, then
        ``n_iterations`` more. ``warm_start``: LightGBM, ``trees_per_iteration`` new trees
        per iteration.
    trees_per_iteration : int
        For ``warm_start``.
    infeasible_cost : float or None
        The chapter's ``c^-``.
    target_noise, next_state_noise : float
        Standard deviations of Gaussian smoothing of the targets and of the next states
        (in units of each feature's standard deviation); off by default. Next-state
        noise needs ``mode="refit"``.
    validation_fraction : float
        Fraction of episodes held out for the Bellman residual (0: residual on the
        training data).
    on_divergence : {"stop", "warn", "ignore"}
        What to do when the monitor sees divergence (infinite horizon): values beyond
        ``max|c| / (1 - gamma)``, a change ``sup|Q_k - Q_{k-1}|`` beyond
        ``(1 + divergence_slack)`` times the first iteration's, or a change growing for
        ``patience`` iterations in a row (by half or more).
    patience : int
    divergence_slack : float
    initial_q : QFunction, optional
        ``Q_0`` (infinite horizon) or the terminal ``Q_T`` (finite horizon); zero by
        default. The value bound of the monitor grows by ``max |Q_0|``.
    random_state : int
        Seeds the split and, as ``random_state + k``, the regressor at iteration k.

    Attributes
    ----------
    q_function_ : QFunction
        ``Q`` (infinite horizon) or a :class:`TimeIndexedQ` over ``Q_0..Q_{T-1}``.
    policy_ : GreedyPolicy
    history_ : pandas.DataFrame
        One row per iteration: ``iteration, step, sup_dq, mean_dq, max_abs_q,
        bellman_residual, greedy_changed, start_value, wall_time, structure``.
    diverged_ : bool
    divergence_message_ : str
        What the monitor saw, when ``diverged_``.
    """

    def __init__(
        self,
        horizon: int | None = None,
        gamma: float | None = None,
        regressor: Any = "extra_trees",
        regressor_params: dict | None = None,
        action_encoding: str = "joint",
        action_input: str = "value",
        feature_map: Any = None,
        n_iterations: int = 50,
        tol: float | None = None,
        mode: str = "refit",
        trees_per_iteration: int = 10,
        infeasible_cost: float | None = None,
        target_noise: float = 0.0,
        next_state_noise: float = 0.0,
        validation_fraction: float = 0.0,
        on_divergence: str = "stop",
        patience: int = 5,
        divergence_slack: float = 1.0,
        initial_q: QFunction | None = None,
        random_state: int = 0,
    ) -> None:
        self.horizon = horizon
        self.gamma = gamma
        self.regressor = regressor
        self.regressor_params = regressor_params
        self.action_encoding = action_encoding
        self.action_input = action_input
        self.feature_map = feature_map
        self.n_iterations = n_iterations
        self.tol = tol
        self.mode = mode
        self.trees_per_iteration = trees_per_iteration
        self.infeasible_cost = infeasible_cost
        self.target_noise = target_noise
        self.next_state_noise = next_state_noise
        self.validation_fraction = validation_fraction
        self.on_divergence = on_divergence
        self.patience = patience
        self.divergence_slack = divergence_slack
        self.initial_q = initial_q
        self.random_state = random_state

    # ------------------------------------------------------------------ public API
    def fit(self, dataset: TransitionDataset, sample_weight: np.ndarray | None = None, *, verbose: bool = False,
            show_progress: bool = False) -> FittedQIteration:
        """Run the iteration to the end (see :meth:`fit_iter`); returns self.

        ``show_progress`` draws a progress bar on stderr, ``verbose`` logs each
        iteration's diagnostics (INFO, logger ``offline_adp.algorithms.fqi``). The policy
        gets the dataset's :class:`~offline_adp.policies.PolicySignature`.
        """
        from offline_adp.progress import fit_progress

        with fit_progress(self, verbose, show_progress) as bar:
            for row in self.fit_iter(dataset, sample_weight):
                bar.update(row)
        attach_signature(getattr(self, "policy_", None), dataset)
        return self

    def fit_iter(
        self,
        dataset: TransitionDataset,
        sample_weight: np.ndarray | None = None,
        resume: dict[str, Any] | None = None,
    ) -> Iterator[dict[str, Any]]:
        """Fit, yielding each iteration's diagnostics (a dict, one ``history_`` row).

        ``resume`` continues an interrupted fit from a checkpoint: ``{"q": Q_k (or the
        list Q_{T-1}, ..., Q_{T-k} for a finite horizon), "history": rows 1..k}``. With
        the same data and parameters the result equals an uninterrupted fit (iteration
        k's randomness depends on ``random_state + k`` only). Not for ``mode="frozen"``.
        """
        self._validate_params()
        d = self._prepare(dataset, sample_weight)
        learner = self._learner(d)
        self._fit_state = (d, learner)  # kept for structure-conditional re-weighting (not saved)
        self.history_ = pd.DataFrame()
        self.diverged_ = False
        rows: list[dict[str, Any]] = []
        n, A = len(d["cost"]), d["n_actions"]
        q_next = np.zeros((n, A))  # Q_0(x'_i, .) = 0  (or Q_T = 0)
        q_prev_train = np.zeros(n)
        if self.initial_q is not None:  # start from a given Q_0 (or terminal Q_T)
            q_next = self.initial_q.values(d["next_obs"], self.horizon or 0)
            q_prev_train = self.initial_q.values(d["obs"], 0)[np.arange(n), d["actions"]]
            d["bound"] = 2 * d["bound"] + float(np.abs(q_prev_train).max())
            d["bound_text"] = "2 max|c| / (1 - gamma) + max|Q_0|"
        qs: list[QFunction] = []
        finite = self.horizon is not None
        done = 0
        if resume is not None:
            if self.mode == "frozen":
                raise ValueError("resuming is not supported for mode='frozen' (its iterations are cheap: refit instead)")
            rows = [dict(r) for r in resume["history"]]
            done = len(rows)
            last = resume["q"][-1] if finite else resume["q"]
            qs = list(resume["q"]) if finite else []
            learner.restore(last, done)
            q_next, q_prev_train = learner.predict("next"), learner.predict("train")
        # frozen structure: one phase on the first structure, one after restructuring
        phases = 2 if (self.mode == "frozen" and not finite) else 1
        per_phase = self.horizon if finite else self.n_iterations
        k = 0
        for phase in range(phases):
            if phase:
                learner.restructure()  # one restructuring pass on the converged targets
            first = k + 1  # a rebuilt structure interpolates its targets: its first change says nothing
            for _ in range(per_phase):
                k += 1
                if k <= done:
                    continue
                t = self.horizon - k if finite else None  # Algorithm 10 runs t = T-1, ..., 0
                t0 = time.perf_counter()
                if self.next_state_noise and k > 1:
                    q_next = self._noisy_next_values(learner, d)
                y = self._targets(d, q_next, t)  # y_i = c_i + gamma (1 - term_i) min_a' Q(x'_i, a')
                learner.fit(y)  # Q_k = LEARN({(x_i, a_i), y_i})
                q_train = learner.predict("train")
                q_next_new = learner.predict("next")  # all (x'_i, a') in one batched call
                row = self._diagnostics(d, learner, k, t, q_train, q_prev_train, q_next, q_next_new, t0)
                q_next, q_prev_train = q_next_new, q_train
                if finite:
                    qs.append(learner.snapshot())
                rows.append(row)
                self.history_ = pd.DataFrame(rows)
                self._set_result(learner, qs)
                yield row
                if not finite and self._check_divergence(rows, d):
                    return
                if not finite and self.tol is not None and k > first and row["sup_dq"] < self.tol:
                    break  # converged (in this phase)

    def predict(self, obs: np.ndarray, t: int | np.ndarray = 0) -> np.ndarray:
        """Q-values of all actions, shape (n, n_actions)."""
        self._check_fitted()
        return self.q_function_.values(np.asarray(obs, dtype=np.float64), t)

    # ------------------------------------------------------------------ steps
    def _validate_params(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.action_encoding not in ("joint", "per_action"):
            raise ValueError(f"action_encoding must be 'joint' or 'per_action', got {self.action_encoding!r}")
        if self.action_input not in ("value", "onehot"):
            raise ValueError(f"action_input must be 'value' or 'onehot', got {self.action_input!r}")
        if self.horizon is not None and (not isinstance(self.horizon, int | np.integer) or self.horizon <= 0):
            raise ValueError(f"horizon must be a positive integer or None, got {self.horizon!r}")
        if self.on_divergence not in ("stop", "warn", "ignore"):
            raise ValueError(f"on_divergence must be 'stop', 'warn' or 'ignore', got {self.on_divergence!r}")
        if self.next_state_noise and self.mode != "refit":
            raise ValueError("next_state_noise needs mode='refit' (the other modes precompute next-state inputs)")

    def _prepare(self, ds: TransitionDataset, sample_weight: np.ndarray | None) -> dict[str, Any]:
        if not isinstance(ds, TransitionDataset):
            raise TypeError(f"FittedQIteration.fit needs a TransitionDataset (trace data), got {type(ds).__name__}")
        if len(ds) == 0:
            raise ValueError("the dataset is empty")
        gamma = self.gamma if self.gamma is not None else (ds.info.gamma if ds.info.gamma is not None else (1.0 if self.horizon else 0.95))
        if self.horizon is None and not gamma < 1.0 and not ds.arrays().terminated.any():
            raise ValueError(
                f"the infinite-horizon algorithm needs gamma < 1 (got {gamma}) unless episodes terminate "
                "(a shortest-path problem); give a horizon instead"
            )
        w_all = None if sample_weight is None else np.asarray(sample_weight, dtype=np.float64)
        if w_all is not None and w_all.shape != (len(ds),):
            raise ValueError(f"sample_weight has shape {w_all.shape}, expected ({len(ds)},)")
        train_rows = np.ones(len(ds), bool)
        if self.validation_fraction:
            rng = np.random.default_rng(self.random_state)
            n_ep = ds.n_episodes
            n_val = max(1, int(round(self.validation_fraction * n_ep)))
            val_eps = np.zeros(n_ep, bool)
            val_eps[rng.permutation(n_ep)[:n_val]] = True
            train_rows = ~val_eps[ds.episode_index]
        a = ds.arrays()
        fmap = None
        if self.feature_map is not None:
            from sklearn.base import clone

            fmap = clone(self.feature_map).fit(a.obs[train_rows])
        at = ds.info.action_table
        af = at.values if self.action_input == "value" else np.eye(len(at))
        enc = QEncoder(len(at), af, per_action=self.action_encoding == "per_action", feature_map=fmap)
        cost = a.cost
        no_boot = a.terminated.copy()
        if self.infeasible_cost is not None:
            no_boot |= cost >= self.infeasible_cost
        tr = train_rows
        phi_obs, phi_next = enc.phi(a.obs), enc.phi(a.next_obs)
        start = a.step == 0
        d = {
            "gamma": float(gamma),
            "n_actions": len(at),
            "encoder": enc,
            "cost": cost[tr],
            "no_boot": no_boot[tr],
            "weights": None if w_all is None else w_all[tr],
            "phi": phi_obs[tr],
            "actions": a.action[tr],
            "phi_next": phi_next[tr],
            "next_obs": a.next_obs[tr],
            "obs": a.obs[tr],
            "obs_std": a.obs.std(axis=0) + 1e-12,
            "start_phi": phi_obs[start & tr] if (start & tr).any() else phi_obs[tr][:1],
            "start_obs": a.obs[start & tr] if (start & tr).any() else a.obs[tr][:1],
            "start_rows": np.flatnonzero((start & tr)[tr]) if (start & tr).any() else np.zeros(1, np.int64),
            "valid": None,
            "bound": (np.abs(cost).max() / (1.0 - gamma)) if gamma < 1 else np.inf,
        }
        if self.infeasible_cost is not None:
            d["bound"] = max(min(d["bound"], abs(self.infeasible_cost)), np.abs(cost).max())
        if self.target_noise and gamma < 1:  # noisy targets may overshoot by a few noise std
            d["bound"] += 4 * self.target_noise / (1.0 - gamma)
        if (~tr).any():
            v = ~tr
            d["valid"] = {"phi": phi_obs[v], "actions": a.action[v], "phi_next": phi_next[v], "cost": cost[v],
                          "no_boot": no_boot[v], "next_obs": a.next_obs[v]}
        self._encoder = enc
        return d

    def _learner(self, d: dict[str, Any]) -> Learner:
        reg = make_regressor(self.regressor, **(self.regressor_params or {}))
        queries: dict[str, tuple[np.ndarray, np.ndarray | None]] = {"next": (d["phi_next"], None), "start": (d["start_phi"], None)}
        if d["valid"] is not None:
            queries["valid"] = (d["valid"]["phi"], d["valid"]["actions"])
            queries["valid_next"] = (d["valid"]["phi_next"], None)
        args = (reg, d["encoder"], d["phi"], d["actions"], queries, d["weights"], self.random_state)
        if self.mode == "frozen":
            return FrozenTreesLearner(*args)
        if self.mode == "warm_start":
            return LightGBMWarmStartLearner(*args, trees_per_iteration=self.trees_per_iteration)
        return RefitLearner(*args)

    def _next_value(self, q_next: np.ndarray, which: str, t: int | None) -> np.ndarray:
        """The backed-up value of the next states: ``min_a' Q(x', a')`` (FQI)."""
        return q_next.min(axis=1)

    def _targets(self, d: dict[str, Any], q_next: np.ndarray, t: int | None = None) -> np.ndarray:
        """y_i = c_i + gamma * (1 - terminated_i) * V(x'_i), clamped at c^-."""
        y = d["cost"] + d["gamma"] * np.where(d["no_boot"], 0.0, self._next_value(q_next, "next", t))
        if self.infeasible_cost is not None:
            y = np.minimum(y, self.infeasible_cost)
        if self.target_noise:
            rng = np.random.default_rng([self.random_state, len(self.history_) + 1, 17])
            y = y + rng.normal(0.0, self.target_noise, len(y))
        return y

    def _noisy_next_values(self, learner: Learner, d: dict[str, Any]) -> np.ndarray:
        rng = np.random.default_rng([self.random_state, len(self.history_) + 1, 23])
        x = d["next_obs"] + rng.normal(0.0, self.next_state_noise, d["next_obs"].shape) * d["obs_std"]
        return learner.snapshot().values(x)

    def _diagnostics(self, d, learner, k, t, q_train, q_prev_train, q_next_old, q_next_new, t0) -> dict[str, Any]:
        dq = np.abs(q_train - q_prev_train)
        boot = ~d["no_boot"]
        changed = (q_next_new.argmin(axis=1) != q_next_old.argmin(axis=1))[boot]
        if d["valid"] is not None:
            v = d["valid"]
            target = v["cost"] + d["gamma"] * np.where(v["no_boot"], 0.0, self._next_value(learner.predict("valid_next"), "valid_next", t))
            resid = float(np.sqrt(np.mean((learner.predict("valid") - target) ** 2)))
        else:  # on the training data, against Q_k's own targets
            target = d["cost"] + d["gamma"] * np.where(d["no_boot"], 0.0, self._next_value(q_next_new, "next", t))
            resid = float(np.sqrt(np.mean((q_train - target) ** 2)))
        return {
            "iteration": k,
            "step": t,
            "sup_dq": float(dq.max()),
            "mean_dq": float(dq.mean()),
            "max_abs_q": float(np.abs(q_train).max()),
            "bellman_residual": resid,
            "greedy_changed": float(changed.mean()) if len(changed) else 0.0,
            "start_value": float(learner.predict("start").min(axis=1).mean()),
            "wall_time": time.perf_counter() - t0,
            "structure": getattr(learner, "structures", None),
        }

    def _check_divergence(self, rows: list[dict[str, Any]], d: dict[str, Any]) -> bool:
        """Flag what an exact backup can never do.

        The exact Bellman operator is a gamma-contraction (a non-expansion for
        undiscounted shortest-path problems), so from ``Q_0 = 0``: values stay within
        ``max|c| / (1 - gamma)``, and ``sup|Q_k - Q_(k-1)|`` never exceeds its first
        value ``sup|Q_1|``. Approximate backups are allowed slack (``1 +
        divergence_slack``) before the run is flagged; a change that keeps growing for
        ``patience`` iterations (by half or more) is flagged too.
        """
        if self.on_divergence == "ignore" or self.diverged_:
            return False
        last, first = rows[-1], rows[0]
        msg = None
        if last["max_abs_q"] > d["bound"] * (1 + 1e-6) + 1e-9:
            msg = (f"iteration {last['iteration']}: max |Q| = {last['max_abs_q']:.4g} exceeds the bound "
                   f"{d.get('bound_text', 'max|c| / (1 - gamma)')} = {d['bound']:.4g}")
        elif last["sup_dq"] > (1 + self.divergence_slack) * first["sup_dq"] + 1e-12:
            msg = (f"iteration {last['iteration']}: sup |Q_k - Q_(k-1)| = {last['sup_dq']:.4g} is more than "
                   f"{1 + self.divergence_slack:g}x the first iteration's {first['sup_dq']:.4g}; an exact backup "
                   "never increases it")
        elif len(rows) > self.patience:
            recent = rows[-self.patience - 1 :]
            streak = all(b["sup_dq"] > a["sup_dq"] for a, b in zip(recent, recent[1:], strict=False))
            if streak and recent[-1]["sup_dq"] > 1.5 * recent[0]["sup_dq"]:
                msg = (f"iteration {last['iteration']}: sup |Q_k - Q_(k-1)| grew for {self.patience} iterations "
                       f"in a row, from {recent[0]['sup_dq']:.4g} to {last['sup_dq']:.4g}")
        if msg is None:
            return False
        self.diverged_ = True
        self.divergence_message_ = msg
        action = "stopping (on_divergence='stop')" if self.on_divergence == "stop" else "continuing (on_divergence='warn')"
        warnings.warn(f"{type(self).__name__} is diverging: {msg}; {action}", DivergenceWarning, stacklevel=3)
        return self.on_divergence == "stop"

    def _set_result(self, learner: Learner, qs: list[QFunction]) -> None:
        if self.horizon is not None:
            if not qs:
                return
            self.q_functions_ = list(reversed(qs))  # index t = 0..T-1
            self.q_function_ = TimeIndexedQ(self.q_functions_) if len(self.q_functions_) == self.horizon else None
        else:
            self.q_function_ = learner.snapshot()
        if self.q_function_ is not None:
            self.policy_ = self._result_policy(self.q_function_)

    def _result_policy(self, q: QFunction) -> Any:
        return GreedyPolicy(q)

    def _check_fitted(self) -> None:
        if getattr(self, "q_function_", None) is None:
            raise NotFittedError("this FittedQIteration is not fitted yet; call fit(dataset) first")


def save_fqi(est: FittedQIteration, directory: Any, dataset_fingerprint: str | None = None) -> None:
    """Write a fitted FQI's Q-functions, greedy policy definition, params and history.

    Layout: ``q.json`` + ``q.npz`` (see :mod:`offline_adp.artifacts`), ``params.json``
    (``get_params()``, estimators by name or repr), ``history.csv``.
    """
    import json
    from pathlib import Path

    from offline_adp.artifacts import save_q

    est._check_fitted()
    d = Path(directory)
    params = {k: (v if isinstance(v, str | int | float | bool | type(None) | dict | list) else repr(v)) for k, v in est.get_params().items()}
    save_q(est.q_function_, d, extra={"algorithm": "fqi", "dataset_fingerprint": dataset_fingerprint, "policy": "greedy (argmin_a Q)"})
    (d / "params.json").write_text(json.dumps(params, indent=1))
    est.history_.to_csv(d / "history.csv", index=False)


def load_fqi(directory: Any) -> FittedQIteration:
    """Read what :func:`save_fqi` wrote; the result predicts and acts like the saved one."""
    import json
    from pathlib import Path

    from offline_adp.artifacts import load_q

    d = Path(directory)
    q, meta = load_q(d)
    raw = json.loads((d / "params.json").read_text())
    known = FittedQIteration().get_params()
    est = FittedQIteration(**{k: v for k, v in raw.items() if k in known and not (isinstance(v, str) and v.startswith(("<", "Pipeline(", "OneHot")))})
    est.q_function_ = q
    est.q_functions_ = list(q.qs) if isinstance(q, TimeIndexedQ) else None
    est.policy_ = GreedyPolicy(q)
    est.history_ = pd.read_csv(d / "history.csv")
    est.diverged_ = False
    est.dataset_fingerprint_ = meta.get("dataset_fingerprint")
    return est
