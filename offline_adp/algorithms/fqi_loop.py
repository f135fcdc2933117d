"""The fitted-Q loop (:func:`fitted_q_loop`) and the bookkeeping around it
(:func:`run_fitted_q`: prepare, restore, history, monitor, verdict, fitted attributes),
shared by :class:`~offline_adp.algorithms.fqi.FittedQIteration` and
:class:`~offline_adp.algorithms.fqe.FittedQEvaluation` (and the Dask engine).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from offline_adp.algorithms.fqi_data import Backup, Prepared
from offline_adp.algorithms.fqi_monitor import DivergenceMonitor, distance_bound, verdict
from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import DivergenceWarning
from offline_adp.learn import Learner
from offline_adp.qfunctions import QFunction, TimeIndexedQ

if TYPE_CHECKING:
    from offline_adp.algorithms.fqi import FittedQIteration


# ----------------------------------------------------------------------------- the loop
@dataclass(frozen=True)
class Noise:
    """Optional smoothing; iteration k's draws depend on ``(random_state, k)`` only."""

    random_state: int = 0
    target: float = 0.0  #: std of Gaussian noise added to the targets
    next_state: float = 0.0  #: std (in feature std units) of noise added to x'

    def targets(self, k: int, n: int) -> np.ndarray | float:
        return np.random.default_rng([self.random_state, k, 17]).normal(0.0, self.target, n) if self.target else 0.0

    def next_obs(self, k: int, data: Prepared) -> np.ndarray:
        x = data.train.next_obs
        return x + np.random.default_rng([self.random_state, k, 23]).normal(0.0, self.next_state, x.shape) * data.obs_std


@dataclass(frozen=True, eq=False)
class FitState:
    """What a fit ran on, kept in this process (``fit_state_``; never saved): the prepared
    data, the learner holding the last Q (its structure, for a frozen fit) and the backup."""

    data: Prepared
    learner: Learner
    backup: Backup


@dataclass(frozen=True)
class Iterate:
    """What one pass of the loop produced (the learner holds Q_k itself)."""

    k: int  #: iteration, 1-based
    t: int | None  #: the step fitted (finite horizon), else None
    q_next_old: np.ndarray  #: Q_{k-1}(x'_i, .)
    q_next: np.ndarray  #: Q_k(x'_i, .)


def fitted_q_loop(data: Prepared, learner: Learner, backup: Backup, iterations: Iterable[tuple[int, int | None]],
                  q_next: np.ndarray, noise: Noise = Noise()) -> Iterator[Iterate]:
    """Algorithms 10-13: Bellman targets from the previous Q, then LEARN. One iteration per
    ``(k, t)`` of ``iterations`` (``t = T - k`` for a finite horizon, else ``None``);
    ``q_next`` is ``Q_{k-1}(x'_i, a')`` for every next state and action."""
    for k, t in iterations:
        if noise.next_state and k > 1:  # Q_{k-1} at perturbed next states (smoothing)
            q_next = learner.snapshot().values(noise.next_obs(k, data))
        y = data.targets(backup(q_next, "next", t))  # y_i = c_i + gamma (1 - term_i) V_{k-1}(x'_i)
        y = y + noise.targets(k, len(y))
        learner.fit(y, k)  # Q_k = LEARN({((x_i, a_i), y_i)})
        q_new = learner.predict("next")  # Q_k(x'_i, a') for all a': one batched call
        yield Iterate(k, t, q_next, q_new)
        q_next = q_new


# ----------------------------------------------------------------------------- bookkeeping around the loop
def run_fitted_q(est: FittedQIteration, dataset: TransitionDataset, sample_weight: np.ndarray | None,
                 resume: dict[str, Any] | None, make_backup: Any, prepare: Any = None,
                 make_learner: Any = None, *, deferred: bool = False) -> Iterator[dict[str, Any]]:
    """Prepare, restore, run :func:`fitted_q_loop`, and keep history, monitor, verdict and
    the fitted attributes of ``est`` up to date (FQI and FQE alike). ``prepare(dataset,
    sample_weight) -> Prepared`` (setting ``est.gamma_``, ``est.horizon_``) and
    ``make_learner(data) -> Learner`` replace ``est``'s own (the Dask engine's data and LEARN).
    ``deferred``: an infinite-horizon ``Q_k`` becomes ``est.q_function_`` at the end only."""
    est._validate_params()  # scikit-learn's, on _parameter_constraints
    est._check_param_combinations()
    data = (prepare or est._prepare)(dataset, sample_weight)
    learner = (make_learner or est._learner)(data)
    backup = make_backup(data)
    finite = est.horizon_ is not None
    total = est.horizon_ if finite else est.iteration_plan()[1]
    monitor = DivergenceMonitor(data.bound, data.bound_text, q0_abs=data.q0_abs, margin=est.divergence_slack,
                                window=est.patience, finite=finite)
    est.fit_state_ = FitState(data, learner, backup)  # for structure-conditional re-weighting (not saved)
    rows: list[dict[str, Any]] = []
    est.__dict__["_history_rows"], est.__dict__["_history_frame"] = rows, None
    est.diverged_, est.divergence_message_ = False, None
    est.q_function_ = None
    qs: list[QFunction] = []
    n = data.n
    if est.initial_q is not None:  # Q_0 (or the terminal Q_T)
        q_next = est.initial_q.values(data.train.next_obs, est.horizon_ or 0)
        q_train = est.initial_q.values(data.obs, 0)[np.arange(n), data.train.actions]
    else:
        q_next, q_train = np.zeros((n, data.n_actions)), np.zeros(n)
    if resume is not None and resume["history"]:
        rows.extend(dict(r) for r in resume["history"])
        qs = list(resume["q"]) if finite else []
        learner.restore(resume["q"][-1] if finite else resume["q"], len(rows), rows)
        q_next, q_train = learner.predict("next"), learner.predict("train")
        for j in range(1, len(rows) + 1):  # replay the monitor silently
            msg = None if (est.on_divergence == "ignore" or est.diverged_) else monitor.check(rows[:j])
            if msg:
                est.diverged_, est.divergence_message_ = True, msg
        _set_result(est, learner, qs)
    done = len(rows)
    if not _finished(est, rows, total):
        iterations = ((k, (est.horizon_ - k) if finite else None) for k in range(done + 1, total + 1))
        t0, c0 = time.perf_counter(), time.process_time()  # an iteration's clocks run from here to its row
        for it in fitted_q_loop(data, learner, backup, iterations, q_next, Noise(est.random_state, est.target_noise, est.next_state_noise)):
            q_train_new = learner.predict("train")
            rows.append(_diagnostics(data, learner, backup, it, q_train, q_train_new, t0, c0))
            est.__dict__["_history_dirty"] = True
            q_train = q_train_new
            if finite:
                qs.append(learner.snapshot())
            if finite or not deferred:
                _set_result(est, learner, qs)
            if not (est.on_divergence == "ignore" or est.diverged_):
                msg = monitor.check(rows)
                if msg:
                    est.diverged_, est.divergence_message_ = True, msg
                    action = "stopping (on_divergence='stop')" if est.on_divergence == "stop" else "continuing (on_divergence='warn')"
                    warnings.warn(f"{type(est).__name__} is diverging: {msg}; {action}", DivergenceWarning, stacklevel=3)
            yield rows[-1]
            if _finished(est, rows, total):
                break
            t0, c0 = time.perf_counter(), time.process_time()
    if rows and deferred:
        _set_result(est, learner, qs)
    conv = _converged(est, rows)
    frozen = _bounded(est)
    est.verdict_, est.verdict_message_ = verdict(
        rows, finite=finite, divergence=est.divergence_message_, converged=conv, gamma=data.gamma,
        tolerance=_tolerance(est, rows[-1]) if rows else None, frozen=frozen, window=est.patience,
        capped=est.n_iterations == "auto" and len(rows) >= total and not conv)
    est.converged_ = conv
    if rows:
        rows[-1]["verdict"] = est.verdict_
        est.__dict__["_history_dirty"] = True


def _bounded(est: FittedQIteration) -> bool:
    """Whether the contraction bound decides convergence: a frozen structure, gamma < 1 and
    no target noise (fresh noise every iteration: no fixed point to be near)."""
    return getattr(est, "mode_", est.mode) == "frozen" and est.gamma_ < 1 and not est.target_noise


def _tolerance(est: FittedQIteration, last: dict[str, Any]) -> float | None:
    """What the convergence test compares with (:mod:`~offline_adp.algorithms.fqi_monitor`):
    frozen with gamma < 1: ``tol`` if given, else ``rtol max|Q_k|``, for the distance bound;
    else ``tol``."""
    if not _bounded(est) or est.tol is not None:
        return est.tol
    return float(est.rtol) * float(last["max_abs_q"])


def _converged(est: FittedQIteration, rows: list[dict[str, Any]]) -> bool:
    """Converged at the last row (:mod:`~offline_adp.algorithms.fqi_monitor`): frozen, the
    distance bound ``gamma/(1-gamma) sup|dQ|`` within :func:`_tolerance`, after the last
    scheduled build, on an iteration that did not rebuild (or rebuilt one-leaf trees on
    constant targets, as the one before did: they stay constant); other modes ``sup|dQ| < tol``.
    A pure function of the history, so a resumed fit decides the same."""
    if est.horizon_ is not None or len(rows) < 2:
        return False
    last, prev = rows[-1], rows[-2]
    # targets constant at two iterations in a row (every row's cost alike, no terminal): they stay
    # constant, one-leaf trees are exact, and rebuilding them each iteration changes nothing
    constant = bool(last.get("structure_on_constant")) and bool(prev.get("structure_on_constant"))
    if last.get("structure") != prev.get("structure") and not constant:
        return False
    if getattr(est, "mode_", est.mode) == "frozen" and (last["iteration"] < max(est._schedule())
                                                        or (last.get("structure_on_constant") and not constant)):
        return False
    if not _bounded(est):
        return est.tol is not None and last["sup_dq"] < est.tol
    return distance_bound(last["sup_dq"], est.gamma_) <= _tolerance(est, last)


def _finished(est: FittedQIteration, rows: list[dict[str, Any]], total: int) -> bool:
    if not rows:
        return False
    return (len(rows) >= total or _converged(est, rows)
            or (est.diverged_ and est.on_divergence == "stop"))


def _diagnostics(data: Prepared, learner: Learner, backup: Backup, it: Iterate, q_prev_train: np.ndarray,
                 q_train: np.ndarray, t0: float, c0: float) -> dict[str, Any]:
    dq = np.abs(q_train - q_prev_train)
    boot = ~data.train.no_boot
    # sup|dQ| over the data's pairs: the training pairs and every next-state pair the targets
    # read (the contraction's sup norm; fqi_monitor)
    d_next = np.abs(it.q_next - it.q_next_old).max(axis=1, initial=0.0)[boot]  # per row, over actions
    sup_dq = max(float(dq.max()) if len(dq) else 0.0, float(d_next.max()) if len(d_next) else 0.0)
    changed = (it.q_next.argmin(axis=1) != it.q_next_old.argmin(axis=1))[boot]
    if data.valid is not None:
        v = data.valid
        target = v.cost + data.gamma * np.where(v.no_boot, 0.0, backup(learner.predict("valid_next"), "valid_next", it.t))
        resid = float(np.sqrt(np.mean((learner.predict("valid") - target) ** 2)))
    else:  # on the training data, against Q_k's own targets
        resid = float(np.sqrt(np.mean((q_train - data.targets(backup(it.q_next, "next", it.t))) ** 2)))
    return {
        "iteration": it.k,
        "step": it.t,
        "sup_dq": sup_dq,
        "mean_dq": float(dq.mean()),
        "max_abs_q": float(np.abs(q_train).max()),
        "bellman_residual": resid,
        "greedy_changed": float(changed.mean()) if len(changed) else 0.0,
        "start_value": float(backup(learner.predict("start"), "start", -1 if it.t is None else it.t - 1).mean()),
        "wall_time": time.perf_counter() - t0,
        "cpu_time": time.process_time() - c0,
        "structure": None,
        **learner.state(),
    }


def _set_result(est: FittedQIteration, learner: Learner, qs: list[QFunction]) -> None:
    if est.horizon_ is not None:
        if not qs:
            return
        est.q_functions_ = list(reversed(qs))  # index t = 0..T-1
        est.q_function_ = TimeIndexedQ(est.q_functions_) if len(est.q_functions_) == est.horizon_ else None
    else:
        est.q_function_ = learner.snapshot()
    if est.q_function_ is not None:
        est.policy_ = est._result_policy(est.q_function_)
