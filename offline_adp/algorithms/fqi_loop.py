"""The fitted-Q loop (:func:`fitted_q_loop`) and the estimator base class around it
(:class:`FittedQEstimator`: prepare, restore, history, monitor, verdict, fitted
attributes), shared by :class:`~offline_adp.algorithms.fqi.FittedQIteration` and
:class:`~offline_adp.algorithms.fqe.FittedQEvaluation` (and the Dask engine).

:class:`FittedQEstimator` declares what the loop needs of an estimator: the hooks a
subclass implements (:meth:`~FittedQEstimator._prepare`, :meth:`~FittedQEstimator._learner`,
:meth:`~FittedQEstimator.iteration_plan`, :meth:`~FittedQEstimator._schedule`,
:meth:`~FittedQEstimator._result_policy`), the parameters it reads and the fitted
attributes it sets; this module imports no estimator.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from offline_adp.algorithms.fqi_data import Backup, GreedyBackup, Prepared
from offline_adp.algorithms.fqi_monitor import (
    DivergenceMonitor,
    below_resolution,
    bound_text,
    convergence_verdict,
    distance_bound,
    is_missing,
    rounding_allowance,
)
from offline_adp.algorithms.params import CheckedEstimator
from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import DivergenceWarning
from offline_adp.learn import Learner
from offline_adp.qfunctions import QFunction, TimeIndexedQ, q_support, restrict_to_support


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
        return x + np.random.default_rng([self.random_state, k,
                                          23]).normal(0.0, self.next_state, x.shape) * data.obs_std


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
        support: np.ndarray | None = None
        if noise.next_state and k > 1:  # Q_{k-1} at perturbed next states (smoothing)
            q, x = learner.snapshot(), noise.next_obs(k, data)
            q_next, support = q.values(x), q_support(q, x)  # a lookup table's support: at the perturbed states
        if support is not None and isinstance(backup, GreedyBackup):
            v = backup.over(q_next, support)
        else:
            v = backup(q_next, "next", t)
        y = data.targets(v)  # y_i = c_i + gamma (1 - term_i) V_{k-1}(x'_i)
        y = y + noise.targets(k, len(y))
        learner.fit(y, k)  # Q_k = LEARN({((x_i, a_i), y_i)})
        q_new = learner.predict("next")  # Q_k(x'_i, a') for all a': one batched call
        yield Iterate(k, t, q_next, q_new)
        q_next = q_new


# ----------------------------------------------------------------------------- the estimator around the loop
class FittedQEstimator(CheckedEstimator):
    """The base of the fitted-Q estimators: :meth:`run_fitted_q` runs :func:`fitted_q_loop`
    and keeps the history, the divergence monitor, the verdict and the fitted attributes
    up to date, through the hooks a subclass implements.

    A subclass's ``__init__`` sets the parameters the loop reads: ``initial_q``,
    ``on_divergence``, ``patience``, ``divergence_slack``, ``random_state``,
    ``target_noise``, ``next_state_noise``, ``n_iterations``, ``tol``, ``rtol`` and ``mode``
    (see :class:`~offline_adp.algorithms.fqi.FittedQIteration`).
    """

    # fitted attributes (set by the hooks and by run_fitted_q)
    gamma_: float  #: set by :meth:`_prepare`
    horizon_: int | None  #: set by :meth:`_prepare`
    mode_: str  #: set by :meth:`_learner`
    fit_state_: FitState
    q_function_: QFunction | None
    q_functions_: list[QFunction]
    policy_: Any
    diverged_: bool
    divergence_message_: str | None
    verdict_: str
    verdict_message_: str
    converged_: bool

    # ------------------------------------------------------------------ the hooks
    def _prepare(self, ds: TransitionDataset, sample_weight: np.ndarray | None) -> Prepared:
        """The prepared data of a fit; sets ``gamma_`` and ``horizon_``."""
        raise NotImplementedError

    def _learner(self, data: Prepared) -> Learner:
        """The LEARN step for ``data``; sets ``mode_``."""
        raise NotImplementedError

    def iteration_plan(self) -> tuple[int, int]:
        """``(K_b, K_max)``: the iterations the frozen builds are spread over, and the most
        an infinite-horizon fit runs."""
        raise NotImplementedError

    def _schedule(self) -> tuple[int, ...]:
        """The iterations at which ``mode="frozen"`` builds a structure."""
        raise NotImplementedError

    def _result_policy(self, q: QFunction) -> Any:
        """The policy of a fitted ``q`` (``policy_``)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ the history
    @property
    def history_(self) -> pd.DataFrame:
        rows = self.__dict__.get("_history_rows")
        if rows is None:
            raise AttributeError("history_")
        frame = self.__dict__.get("_history_frame")
        if frame is None or len(frame) != len(rows) or self.__dict__.get("_history_dirty", False):
            frame = pd.DataFrame(rows)
            self.__dict__["_history_frame"], self.__dict__["_history_dirty"] = frame, False
        return frame

    @history_.setter
    def history_(self, frame: pd.DataFrame) -> None:
        self.__dict__["_history_rows"] = [{k: (None if is_missing(v)
                                               else v) for k, v in r.items()} for r in frame.to_dict("records")]
        self.__dict__["_history_frame"] = frame

    def _start_history(self, rows: list[dict[str, Any]]) -> None:
        """``rows`` (appended to by the loop) becomes the history."""
        self.__dict__["_history_rows"], self.__dict__["_history_frame"] = rows, None

    def _history_changed(self) -> None:
        """A row was added or changed: ``history_`` rebuilds its frame when next read."""
        self.__dict__["_history_dirty"] = True

    def discard_fit_state(self) -> None:
        """Drop ``fit_state_`` (the prepared data and the learner; e.g. a cluster's) and what was
        cached from it (FQE's bootstrap operators over the training rows, which hold the learner)."""
        self.__dict__.pop("fit_state_", None)
        self.__dict__.pop("_row_space_cache", None)

    # ------------------------------------------------------------------ the fit
    def run_fitted_q(self, dataset: Any, sample_weight: np.ndarray | None, resume: dict[str, Any] | None,
                     make_backup: Callable[[Prepared], Backup],
                     prepare: Callable[[Any, np.ndarray | None], Prepared] | None = None,
                     make_learner: Callable[[Prepared], Learner] | None = None, *,
                     deferred: bool = False) -> Iterator[dict[str, Any]]:
        """Prepare, restore, run :func:`fitted_q_loop`, and keep history, monitor, verdict and
        the fitted attributes up to date (FQI and FQE alike), yielding each iteration's
        history row. ``prepare(dataset, sample_weight) -> Prepared`` (setting ``gamma_``,
        ``horizon_``) and ``make_learner(data) -> Learner`` replace :meth:`_prepare` and
        :meth:`_learner` (the Dask engine's data and LEARN). ``deferred``: an
        infinite-horizon ``Q_k`` becomes ``q_function_`` at the end only."""
        self.check_params()  # _parameter_constraints, then the combinations
        data = (prepare or self._prepare)(dataset, sample_weight)
        learner = (make_learner or self._learner)(data)
        backup = make_backup(data)
        bind = getattr(backup, "bind", None)
        if bind is not None:  # FQI's minimum reads the learner's support (lookup tables: the logged actions)
            bind(learner)
        finite = self.horizon_ is not None
        total = self.horizon_ if finite else self.iteration_plan()[1]
        # an averager (a frozen structure, a lookup table) cannot leave the value bound, nor grow
        # faster and faster: the growth rule would only misread a rebuild's jump there
        averager = getattr(self, "mode_", self.mode) == "frozen" or self._lookup_table()
        # what the verdict reads of the data, once (not an O(n) pass per iteration): the rows and
        # max|c| (the rounding allowance), and whether no transition bootstraps (one fit is final)
        self.__dict__["_data_facts"] = (data.n, float(np.abs(data.train.cost).max()) if data.n else 0.0,
                                        bool(np.all(data.train.no_boot)))
        monitor = DivergenceMonitor(data.bound, data.bound_text, q0_abs=data.q0_abs, margin=self.divergence_slack,
                                    window=self.patience, finite=finite, averager=averager)
        self.fit_state_ = FitState(data, learner, backup)  # for structure-conditional re-weighting (not saved)
        rows: list[dict[str, Any]] = []
        self._start_history(rows)
        self.__dict__["_waiting"] = self.__dict__["_result_iterations"] = None  # checkpoint_q: nothing yet
        self.diverged_, self.divergence_message_ = False, None
        self.q_function_ = None
        qs: list[QFunction] = []
        n = data.n
        if self.initial_q is not None:  # Q_0 (or the terminal Q_T)
            q_next = self.initial_q.values(data.train.next_obs, self.horizon_ or 0)
            q_train = self.initial_q.values(data.obs, 0)[np.arange(n), data.train.actions]
        else:
            q_next, q_train = np.zeros((n, data.n_actions)), np.zeros(n)
        if resume is not None and resume["history"]:
            rows.extend(dict(r) for r in resume["history"])
            qs = list(resume["q"]) if finite else []
            learner.restore(resume["q"][-1] if finite else resume["q"], len(rows), rows)
            q_next, q_train = learner.predict("next"), learner.predict("train")
            for j in range(1, len(rows) + 1):  # replay the monitor silently
                msg = None if (self.on_divergence == "ignore" or self.diverged_) else monitor.check(rows[:j])
                if msg:
                    self.diverged_, self.divergence_message_ = True, msg
            self._set_result(learner, qs)
            self._result_at(len(rows))
        done = len(rows)
        if not self._finished(rows, total):
            iterations = ((k, (self.horizon_ - k) if finite else None) for k in range(done + 1, total + 1))
            t0, c0 = time.perf_counter(), time.process_time()  # an iteration's clocks run from here to its row
            for it in fitted_q_loop(data, learner, backup, iterations, q_next,
                                    Noise(self.random_state, self.target_noise, self.next_state_noise)):
                q_train_new = learner.predict("train")
                rows.append(_diagnostics(data, learner, backup, it, q_train, q_train_new, t0, c0))
                self._history_changed()
                q_train = q_train_new
                if finite:
                    qs.append(learner.snapshot())
                if finite or not deferred:
                    self._set_result(learner, qs)
                    self._result_at(len(rows))
                if not (self.on_divergence == "ignore" or self.diverged_):
                    msg = monitor.check(rows)
                    if msg:
                        self.diverged_, self.divergence_message_ = True, msg
                        action = (
                            "stopping (on_divergence='stop')"
                            if self.on_divergence == "stop"
                            else "continuing (on_divergence='warn')"
                        )
                        warnings.warn(f"{type(self).__name__} is diverging: {msg}; {action}", DivergenceWarning,
                                      stacklevel=3)
                self.__dict__["_waiting"] = (len(rows), learner)  # Q_k is at hand while the caller has row k
                yield rows[-1]
                self.__dict__["_waiting"] = None
                if self._finished(rows, total):
                    break
                t0, c0 = time.perf_counter(), time.process_time()
        if rows and deferred:
            self._set_result(learner, qs)
            self._result_at(len(rows))
        conv = self._converged(rows)
        frozen = self._bounded()
        self.verdict_, self.verdict_message_ = convergence_verdict(
            rows, finite=finite, divergence=self.divergence_message_, converged=conv, gamma=data.gamma,
            tolerance=self._tolerance(rows[-1]) if rows else None, frozen=frozen, window=self.patience,
            rounding=self._rounding(rows[-1]) if rows else 0.0,
            capped=self.n_iterations == "auto" and len(rows) >= total and not conv)
        if rows and not finite and self.divergence_message_ is None and self._lookup_table():
            conv, self.verdict_, self.verdict_message_ = self._table_verdict(rows[-1])
        if rows and not finite and self.divergence_message_ is None and self._no_bootstrap():
            conv, self.verdict_ = True, "converged"
            self.verdict_message_ = (f"after {len(rows)} iteration{'s' if len(rows) > 1 else ''}: every transition is "
                                     "terminal, so the targets are the costs themselves and one fit is the answer "
                                     "(no backup to iterate)")
        self.converged_ = conv
        if rows:
            rows[-1]["verdict"] = self.verdict_
            self._history_changed()

    # ------------------------------------------------------------------ checkpoint hooks
    def _result_at(self, iterations: int) -> None:
        """``q_function_`` (``q_functions_``) is now the result of ``iterations`` iterations."""
        self.__dict__["_result_iterations"] = iterations

    def checkpoint_iterations(self) -> int:
        """How many iterations :meth:`checkpoint_q` would write (0: none), without taking the Q."""
        waiting = self.__dict__.get("_waiting")
        return waiting[0] if waiting is not None else (self.__dict__.get("_result_iterations") or 0)

    def checkpoint_q(self) -> tuple[QFunction, int] | None:
        """What a checkpoint writes: the Q of the latest iteration at hand and how many
        iterations it is the result of (None: no iteration yet). While the fit waits at an
        iteration's row (between ``fit_iter``'s yields) that is the iteration itself, a
        deferred fit's Q taken from the learner now; otherwise (a fit stopped inside an
        iteration) the last result set, which may be some iterations back. A finite
        horizon's per-step Q-functions come in the order they were fitted."""
        waiting = self.__dict__.get("_waiting")
        done = self.__dict__.get("_result_iterations")
        if waiting is not None and waiting[0] != done and self.horizon_ is None:
            return waiting[1].snapshot(), waiting[0]
        if done is None:
            return None
        if self.horizon_ is None:
            return self.q_function_, done
        return TimeIndexedQ(list(reversed(self.q_functions_))), done

    def _bounded(self) -> bool:
        """Whether the contraction bound decides convergence: a frozen structure, gamma < 1 and
        no target noise (fresh noise every iteration: no fixed point to be near)."""
        return getattr(self, "mode_", self.mode) == "frozen" and self.gamma_ < 1 and not self.target_noise

    def _lookup_table(self) -> bool:
        """A refit with the lookup table (``regressor="tabular"``), gamma < 1, no noise: each
        iteration averages the backed-up targets over a fixed set of cells, so it is a sup-norm
        gamma-contraction, as a frozen structure's is, and the distance bound holds. Its
        minimum runs over a fixed set of actions per next state (the logged ones, where any
        are: :class:`~offline_adp.algorithms.fqi_data.GreedyBackup`), which keeps it one."""
        from offline_adp.regressors import TabularRegressor, make_regressor

        if getattr(self, "mode_", self.mode) != "refit" or not self.gamma_ < 1 or self.target_noise \
                or getattr(self, "next_state_noise", 0.0):
            return False
        try:
            reg = make_regressor(self.regressor, **(self.regressor_params or {}))
        except Exception:  # noqa: BLE001 - any regressor we cannot make here is not the lookup table
            return False
        return isinstance(reg, TabularRegressor)

    def _table_verdict(self, last: dict[str, Any]) -> tuple[bool, str, str]:
        """The lookup table's verdict by the contraction bound (:meth:`_lookup_table`): "converged"
        when ``gamma/(1-gamma) sup|dQ|`` is within ``rtol max|Q|`` (or ``tol``, whichever is wider:
        ``tol`` stops the loop on ``sup|dQ|``), the bound stated either way."""
        sd, k, r = last["sup_dq"], last["iteration"], self._rounding(last)
        bound = distance_bound(sd, self.gamma_, r)
        tol = max(float(self.rtol) * float(last["max_abs_q"]), self.tol if self.tol is not None else 0.0)
        where = (f"after {k} iterations the lookup table's values are within {bound:.3g} of its fixed point "
                 f"({bound_text(sd, self.gamma_, r, bound)}: a lookup table's backup is a gamma-contraction; "
                 f"max|Q| = {last['max_abs_q']:.4g})")
        if bound <= tol:
            return True, "converged", f"{where} <= tolerance {tol:.3g}"
        note = below_resolution(tol, self.gamma_, r)
        return False, "still changing", (f"{where} > tolerance {tol:.3g}{note} "
                                         f"(more iterations {'cannot settle it' if note else 'would settle it'})")

    def _rounding(self, last: dict[str, Any]) -> float:
        """:func:`~offline_adp.algorithms.fqi_monitor.rounding_allowance` at a history row
        (0 outside a fit's loop)."""
        n, cmax, _ = self.__dict__.get("_data_facts") or (0, 0.0, False)
        return rounding_allowance(float(last["max_abs_q"]), cmax, n) if n else 0.0

    def _tolerance(self, last: dict[str, Any]) -> float | None:
        """What the convergence test compares with (:mod:`~offline_adp.algorithms.fqi_monitor`):
        frozen with gamma < 1: ``tol`` if given, else ``rtol max|Q_k|``, for the distance bound;
        else ``tol``."""
        if not self._bounded() or self.tol is not None:
            return self.tol
        return float(self.rtol) * float(last["max_abs_q"])

    def _converged(self, rows: list[dict[str, Any]]) -> bool:
        """Converged at the last row (:mod:`~offline_adp.algorithms.fqi_monitor`): frozen, the
        distance bound ``gamma/(1-gamma) sup|dQ|`` within :meth:`_tolerance`, after the last
        scheduled build, on an iteration that did not rebuild (or rebuilt one-leaf trees on
        constant targets, as the one before did: they stay constant); other modes ``sup|dQ| < tol``.
        A pure function of the history, so a resumed fit decides the same."""
        if self.horizon_ is not None or len(rows) < 2:
            return False
        last, prev = rows[-1], rows[-2]
        # targets constant at two iterations in a row (every row's cost alike, no terminal): they stay
        # constant, one-leaf trees are exact, and rebuilding them each iteration changes nothing
        constant = bool(last.get("structure_on_constant")) and bool(prev.get("structure_on_constant"))
        if last.get("structure") != prev.get("structure") and not constant:
            return False
        if getattr(self, "mode_", self.mode) == "frozen" and (last["iteration"] < max(self._schedule())
                                                              or (last.get("structure_on_constant") and not constant)):
            return False
        if not self._bounded():
            return self.tol is not None and last["sup_dq"] < self.tol
        return distance_bound(last["sup_dq"], self.gamma_, self._rounding(last)) <= self._tolerance(last)

    def _finished(self, rows: list[dict[str, Any]], total: int) -> bool:
        if not rows:
            return False
        return (len(rows) >= total or self._converged(rows) or self._stalled(rows) or self._no_bootstrap()
                or (self.diverged_ and self.on_divergence == "stop"))

    def _no_bootstrap(self) -> bool:
        """Every training transition is terminal (or reached ``c^-``): the targets never read Q,
        so the first iteration's fit is the answer of any number of them (infinite horizon)."""
        return self.horizon_ is None and (self.__dict__.get("_data_facts") or (0, 0.0, False))[2]

    def _stalled(self, rows: list[dict[str, Any]]) -> bool:
        """A frozen fit whose last backup changed nothing in float64, after its last build and
        not converged (its tolerance is below what rounding resolves): more iterations would
        repeat it, so the fit stops, saying so in the verdict."""
        if not self._bounded() or len(rows) < 2 or rows[-1]["sup_dq"] != 0:
            return False
        last, prev = rows[-1], rows[-2]
        return last.get("structure") == prev.get("structure") and last["iteration"] >= max(self._schedule())

    def _set_result(self, learner: Learner, qs: list[QFunction]) -> None:
        if self.horizon_ is not None:
            if not qs:
                return
            self.q_functions_ = list(reversed(qs))  # index t = 0..T-1
            self.q_function_ = TimeIndexedQ(self.q_functions_) if len(self.q_functions_) == self.horizon_ else None
        else:
            self.q_function_ = learner.snapshot()
        if self.q_function_ is not None:
            self.policy_ = self._result_policy(self.q_function_)


def _diagnostics(data: Prepared, learner: Learner, backup: Backup, it: Iterate, q_prev_train: np.ndarray,
                 q_train: np.ndarray, t0: float, c0: float) -> dict[str, Any]:
    dq = np.abs(q_train - q_prev_train)
    boot = ~data.train.no_boot
    # sup|dQ| over the data's pairs: the training pairs and every next-state pair the targets
    # read (the contraction's sup norm; fqi_monitor)
    d_next = np.abs(it.q_next - it.q_next_old).max(axis=1, initial=0.0)[boot]  # per row, over actions
    sup_dq = max(float(dq.max()) if len(dq) else 0.0, float(d_next.max()) if len(d_next) else 0.0)
    support = learner.support("next") if isinstance(backup, GreedyBackup) else None  # greedy over the logged actions
    changed = (restrict_to_support(it.q_next, support).argmin(axis=1)
               != restrict_to_support(it.q_next_old, support).argmin(axis=1))[boot]
    if data.valid is not None:
        v = data.valid
        target = v.cost + data.gamma * np.where(v.no_boot, 0.0, backup(learner.predict("valid_next"), "valid_next",
                                                                       it.t))
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
