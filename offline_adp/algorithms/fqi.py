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

Fitted Q *evaluation* (Algorithms 12/13, :mod:`offline_adp.algorithms.fqe`) is the same
loop, :func:`fitted_q_loop`, with another backup (the policy's expectation instead of the
minimum, :mod:`offline_adp.algorithms.fqi_data`). ``terminated`` transitions (goal or
failure) are nailed to their cost; ``truncated`` ones bootstrap from ``next_obs``. With
``infeasible_cost = c^-`` every target is clamped to at most ``c^-`` and transitions
costing ``>= c^-`` do not bootstrap. See :mod:`offline_adp.learners` for the three ways
of doing LEARN (``mode``). Around the loop, not in it: the divergence monitor and verdict
(:mod:`~offline_adp.algorithms.fqi_monitor`), the history, resume, and save/load.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any, ClassVar

import numpy as np
import pandas as pd
from sklearn.utils._param_validation import HasMethods, Interval, StrOptions

from offline_adp.algorithms.fqi_data import Backup, GreedyBackup, Prepared, prepare
from offline_adp.algorithms.fqi_monitor import DivergenceMonitor, verdict
from offline_adp.algorithms.params import (
    GAMMA,
    NON_NEGATIVE,
    POSITIVE_INT,
    SEED,
    CheckedEstimator,
    check_learner,
    invalid_parameter,
)
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.discount import resolve_discount
from offline_adp.errors import DivergenceWarning, NotFittedError
from offline_adp.learners import (
    EarlyBuilds,
    FrozenTreesLearner,
    Learner,
    LightGBMWarmStartLearner,
    RefitLearner,
    TreeScreen,
    check_structure_fractions,
)
from offline_adp.policies import GreedyPolicy, attach_signature
from offline_adp.qfunctions import QFunction, TimeIndexedQ
from offline_adp.regressors import REGRESSORS, make_regressor

#: default frozen schedule: structures per iteration (8 over 100 iterations), measured in benchmarks/fqi_suite.py
STRUCTURES_PER_ITERATION = 0.08
#: ``structure_max_samples="auto"``: a frozen structure is grown on at most this many rows (bootstrap)
STRUCTURE_ROWS = 131_072
MODES = ("auto", "refit", "frozen", "warm_start")


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


# ----------------------------------------------------------------------------- the estimator
class FittedQIteration(CheckedEstimator):
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
        One model on ``[phi(x), action]`` or one model per action on ``phi(x)``
        (Ernst et al.'s and mushroom-rl's design). Measured with refit extra-trees
        (``benchmarks/fqi_suite.py --quick``, paired over unselected data seeds):
        ``joint`` scored far better on CartPole-v1 (331 vs 151, all 5 seeds), the same on
        Acrobot-v1, and slightly worse on car-on-the-hill (0.193 vs 0.220, 7 of 9 seeds);
        ``per_action`` fits ~20% less CPU. The frozen and warm-start modes need ``joint``.
    action_input : {"value", "onehot"}
        What a joint model sees of the action: its value vector from the action table
        (Ernst et al.'s choice) or a one-hot code.
    feature_map : transformer, optional
        ``phi``, fitted on the dataset's observations before LEARN.
    n_iterations : int
        K for the infinite horizon (ignored for finite horizons); every mode runs K
        iterations at most.
    tol : float or None
        Stop early when ``sup_i |Q_k - Q_{k-1}|`` on the data falls below ``tol`` (not on
        an iteration that rebuilt a tree structure, nor before the last scheduled one).
    mode : {"auto", "refit", "frozen", "warm_start"}
        ``auto`` (default): ``frozen`` where it applies (a discounted fit, a bagged
        scikit-learn tree ensemble such as the default extra-trees, the joint action
        encoding, no next-state noise), else ``refit``; the mode that ran is ``mode_``.
        ``refit``: the plain loop, any regressor, re-fitted every iteration.
        ``frozen``: a scikit-learn tree ensemble's structure is built at ``n_structures``
        evenly spaced iterations (and again after any build on constant targets), and the
        iterations in between only re-average leaf values (Ernst et al. 2005, section 4.3).
        Between builds it converges towards the fixed point of the averager its structure
        defines, which is only as good as the structure, so the number of builds matters:
        with 4 builds over 100 iterations CartPole-v1 scored 452 +- 57 against refit's
        496 +- 7, with 8 (the default, one per 12.5 iterations) 498 +- 3 at 0.10 of
        refit's CPU (``benchmarks/fqi_suite.py``, 50k transitions, 50 trees, 3 learner
        seeds). On the whole suite it scored as well as refit or better on every problem
        at 0.07-0.11 of its CPU (docs/fqi-modes.md).
        ``warm_start``: LightGBM, ``trees_per_iteration`` new trees per iteration boosted
        from the previous Q (joint encoding; with a non-LightGBM regressor it uses LightGBM
        with 63 leaves and learning rate 0.3, and says so in a warning). Boosting a few
        trees per iteration is a partial LEARN; it did not hold the refit score on any
        problem of the suite (e.g. car-on-the-hill 0.10 vs 0.20, CartPole 141 vs 441 in
        the quick suite), and the CLI warns.
    trees_per_iteration : int
        For ``warm_start``.
    n_structures : int or None
        For ``frozen``: scheduled structure builds over the K iterations; None: one per
        12.5 iterations (``round(0.08 K)``, at least 2). Each build costs about one refit
        iteration; an averaging iteration costs a few percent of one.
    structure_max_samples : "auto", float, list of (float or None), or None
        For ``frozen``: each tree's structure is grown on a bootstrap sample of this
        fraction of the rows (``bootstrap=True, max_samples=...``); its leaves are then
        averaged over *all* training rows falling in them. Builds are cheaper and the
        forest smaller (about ``2 * fraction * n`` nodes a fully grown tree, instead of
        ``2n``), but each leaf averages ~``1 / fraction`` rows: coarser (1/8 of the rows
        for every build lost Acrobot and path tracking at 10k transitions). A list gives
        one fraction per scheduled build (``1.0``: all rows). ``"auto"`` (default): all
        rows up to 131,072, a bootstrap of 131,072 rows beyond (so 1M transitions fit in
        memory and time); ``None``: the regressor's own.
    screen_trees : int or None
        For ``frozen``, opt-in (None, the default: every build grows the whole forest).
        Each build first grows this many trees, and grows the regressor's full count (its
        ``n_estimators``, scikit-learn's warm start: the same trees a one-shot fit grows)
        only when the smaller forest would bias the greedy targets: the expected shortfall
        of ``min_a' Q(x', a')`` below the full forest's from Monte Carlo noise between the
        best action and the others (:func:`~offline_adp.learners.greedy_min_bias`, summed
        over the other actions), averaged over the next states, carried through the
        horizon ``1 / (1 - gamma)``, above ``screen_tol * std(y)``. No screen with
        ``screen_tol = 0``, ``gamma >= 1``, one action, or ``n_estimators <= screen_trees``.
        **Not the default because it did not hold everywhere** (docs/fqi-modes.md):
        with ``screen_trees=10`` car-on-the-hill (gamma 0.95) kept 10 trees in 34 of 36
        builds over 9 data seeds and scored as refit (+0.004 +- 0.013 paired) at 0.027 of
        its CPU, but CartPole-v1 at gamma 0.95 kept 10 trees in its last three builds at
        screen values like car-on-the-hill's (0.002-0.003) and scored 136 / 318 / 346
        against 296 / 366 / 431 unscreened (learner seeds 0-2). Compare with an
        unscreened fit before relying on it.
    screen_tol : float
        The screen's threshold, a fraction of the targets' standard deviation (>= 0; 0
        grows the whole forest at every build).
    early_build_trees : int or None
        For ``frozen``, opt-in (None, the default: every build grows the whole forest). A
        build whose error reaches the final Q with less than half the weight of the last
        build's grows only this many trees (the first trees of the forest it would grow).
        Fitted Q-iteration's last iterate carries the error of iteration ``j``'s LEARN
        step by ``gamma^(K - j)`` (the chapter's bound on approximate value iteration), so
        a structure serving iterations ``s .. e`` weighs ``sum_{j=s..e} gamma^(K - j)``
        (:func:`~offline_adp.learners.build_weight`). The last build always grows the
        whole forest (unless the screen keeps fewer), and ``tol`` never stops a fit before
        it; the weights assume all K iterations run, so a fit that ``tol`` stops early has
        damped its early builds' error less. No effect with a finite horizon, where every
        iterate is the policy at one step.
        **Not the default because it did not hold everywhere** (docs/fqi-modes.md): with
        ``early_build_trees=10`` CartPole-v1, Acrobot-v1 and MountainCar-v0 at gamma 0.99
        (100-200 iterations) scored as with whole builds at 0.46-0.76 of the CPU, but
        CartPole-v1 at gamma 0.95 and 50 iterations lost on two of three data seeds
        (e.g. 275 / 465 / 228 against 347 / 464 / 349). The bound damps an early
        structure's error in the values, not in the later structures grown on the targets
        it produced.
    tree_builder : {"auto", "sklearn"}
        Who grows the frozen mode's structures. ``"auto"`` (default): the compiled
        extra-trees builder (:mod:`offline_adp.extra_trees`, numba) wherever the regressor
        is a scikit-learn ``ExtraTreesRegressor`` with settings it implements (the default
        regressor's are); scikit-learn otherwise. It is the same algorithm (Geurts et al.
        2006) with the same settings, not the same random draws, so a fit differs from the
        ``"sklearn"`` one as two seeds do, with one exception: on targets tied up to the
        learner's tie-breaking jitter scikit-learn stops splitting at random points (a
        rounding effect) where this builder splits on (see :mod:`offline_adp.extra_trees`).
        It grows a car-on-the-hill structure (56k rows, 50 trees) at 0.41-0.48 of
        scikit-learn's CPU (``benchmarks/tree_builder.py``) and returns each training
        row's leaf, so those rows, and the next-state queries that repeat them, are not
        looked up again (docs/fqi-modes.md). Its trees are bit-for-bit reproducible on
        one machine (resume is exact). ``refit`` always uses the regressor as given.
    infeasible_cost : float or None
        The chapter's ``c^-``.
    target_noise, next_state_noise : float
        Standard deviations of Gaussian smoothing of the targets and of the next states
        (in units of each feature's standard deviation); off by default. Next-state
        noise needs ``mode="refit"``.
    validation_fraction : float
        Fraction of episodes held out for the Bellman residual (0: residual on the
        training data).
    on_divergence : {"warn", "stop", "ignore"}
        What to do when the monitor sees unambiguous divergence
        (:mod:`~offline_adp.algorithms.fqi_monitor`: values beyond the bound by more than
        ``divergence_slack``, or sustained accelerating growth of max|Q| over
        ``patience``-iteration windows).
    patience : int
        The monitor's window (iterations).
    divergence_slack : float
        Margin over the value bound, as a fraction of the bound.
    initial_q : QFunction, optional
        ``Q_0`` (infinite horizon) or the terminal ``Q_T`` (finite horizon); zero by
        default. The value bound grows by ``max |Q_0|``.
    random_state : int
        Seeds the split and, as ``random_state + k``, the regressor at iteration k.

    Attributes
    ----------
    q_function_ : QFunction
        ``Q`` (infinite horizon) or a :class:`TimeIndexedQ` over ``Q_0..Q_{T-1}``.
    policy_ : GreedyPolicy
    mode_ : str
        The mode that ran (``mode`` with ``"auto"`` resolved).
    history_ : pandas.DataFrame
        One row per iteration: ``iteration, step, sup_dq, mean_dq, max_abs_q,
        bellman_residual, greedy_changed, start_value, target_std, wall_time, cpu_time``,
        for a frozen fit ``structure`` (builds so far), ``structure_trees`` (trees in the
        current structure), ``structure_screen`` (its build's screen value, see
        ``screen_trees``) and ``structure_builder`` (who grew it, see ``tree_builder``),
        and ``verdict`` on the last row.
    verdict_ : str
        ``"converged"``, ``"still changing"``, ``"diverging"`` or ``"completed"`` (finite).
    verdict_message_ : str
    diverged_ : bool
    divergence_message_ : str
        What the monitor saw, when ``diverged_``.
    """

    #: scikit-learn's declaration of the values above, checked by ``_validate_params()`` at
    #: the start of every fit and by the configuration layer before a run
    _parameter_constraints: ClassVar[dict[str, list[Any]]] = {
        "horizon": [POSITIVE_INT, None],
        "gamma": [GAMMA, None],
        "regressor": [StrOptions(set(REGRESSORS)), HasMethods(["fit", "predict"])],
        "regressor_params": [dict, None],
        "action_encoding": [StrOptions({"joint", "per_action"})],
        "action_input": [StrOptions({"value", "onehot"})],
        "feature_map": [HasMethods(["fit", "transform"]), None],
        "n_iterations": [POSITIVE_INT],
        "tol": [NON_NEGATIVE, None],
        "mode": [StrOptions(set(MODES))],
        "trees_per_iteration": [POSITIVE_INT],
        "infeasible_cost": [Interval(Real, None, None, closed="neither"), None],
        "target_noise": [NON_NEGATIVE],
        "next_state_noise": [NON_NEGATIVE],
        "validation_fraction": [Interval(Real, 0, 1, closed="left")],
        "on_divergence": [StrOptions({"warn", "stop", "ignore"})],
        "patience": [Interval(Integral, 2, None, closed="left")],
        "divergence_slack": [NON_NEGATIVE],
        "initial_q": [HasMethods(["values"]), None],
        "random_state": [SEED],
        "n_structures": [POSITIVE_INT, None],
        "structure_max_samples": [StrOptions({"auto"}), Interval(Real, 0, 1, closed="right"), list, tuple, None],
        "screen_trees": [Interval(Integral, 2, None, closed="left"), None],  # a spread needs two trees
        "screen_tol": [NON_NEGATIVE],
        "early_build_trees": [POSITIVE_INT, None],
        "tree_builder": [StrOptions({"auto", "sklearn"})],
    }

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
        mode: str = "auto",
        trees_per_iteration: int = 10,
        infeasible_cost: float | None = None,
        target_noise: float = 0.0,
        next_state_noise: float = 0.0,
        validation_fraction: float = 0.0,
        on_divergence: str = "warn",
        patience: int = 10,
        divergence_slack: float = 0.1,
        initial_q: QFunction | None = None,
        random_state: int = 0,
        n_structures: int | None = None,
        structure_max_samples: float | list[float | None] | str | None = "auto",
        screen_trees: int | None = None,
        screen_tol: float = 0.005,
        early_build_trees: int | None = None,
        tree_builder: str = "auto",
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
        self.n_structures = n_structures
        self.structure_max_samples = structure_max_samples
        self.screen_trees = screen_trees
        self.screen_tol = screen_tol
        self.early_build_trees = early_build_trees
        self.tree_builder = tree_builder

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
            for row in self.fit_iter(dataset, sample_weight, deferred=True):  # nobody reads Q_k in between
                bar.update(row)
        attach_signature(getattr(self, "policy_", None), dataset)
        return self

    def fit_iter(self, dataset: TransitionDataset, sample_weight: np.ndarray | None = None,
                 resume: dict[str, Any] | None = None, *, deferred: bool = False) -> Iterator[dict[str, Any]]:
        """Fit, yielding each iteration's diagnostics (a dict, one ``history_`` row).

        ``resume`` continues an interrupted fit from a checkpoint: ``{"q": Q_k (or the
        list Q_{T-1}, ..., Q_{T-k} for a finite horizon), "history": rows 1..k}``. With
        the same data and parameters the result equals an uninterrupted fit in every mode
        (iteration k's randomness depends on ``random_state + k`` only); a checkpoint
        that already ends the fit (last iteration, converged, stopped) runs nothing.

        ``deferred=True`` sets an infinite-horizon fit's ``q_function_`` and ``policy_``
        once, when the iteration ends, instead of after every iteration (a frozen fit then
        exports its structure once); :meth:`fit` uses it. A caller that stops a deferred
        ``fit_iter`` early is left without them. A finite-horizon fit sets them after every
        step either way.
        """
        return run_fitted_q(self, dataset, sample_weight, resume, lambda data: GreedyBackup(), deferred=deferred)

    def predict(self, obs: np.ndarray, t: int | np.ndarray = 0) -> np.ndarray:
        """Q-values of all actions, shape (n, n_actions)."""
        self._check_fitted()
        return self.q_function_.values(np.asarray(obs, dtype=np.float64), t)

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
        self.__dict__["_history_rows"] = [{k: (None if _isna(v) else v) for k, v in r.items()} for r in frame.to_dict("records")]
        self.__dict__["_history_frame"] = frame

    # ------------------------------------------------------------------ pieces
    @staticmethod
    def mode_caveat(mode: str | None) -> str | None:
        """What a user should know before trusting ``mode`` (None: nothing): the fast paths
        did not hold the refit score on every problem of ``benchmarks/fqi_suite.py``."""
        if mode == "warm_start":
            return (f"mode = {mode!r} did not hold the refit score on any problem of benchmarks/fqi_suite.py; "
                    "compare with a mode = 'refit' run on your data")
        return None

    def _check_param_combinations(self) -> None:
        """What ``_parameter_constraints`` cannot say (see :mod:`~offline_adp.algorithms.params`):
        next-state noise needs the refit loop, a list of structure fractions holds fractions,
        and the regressor takes ``regressor_params``."""
        super()._check_param_combinations()
        if self.next_state_noise and self.mode not in ("refit", "auto"):
            raise invalid_parameter(self, "next_state_noise", "0 unless mode='refit' (the other modes precompute "
                                    f"next-state inputs; mode={self.mode!r})", self.next_state_noise)
        if isinstance(self.structure_max_samples, list | tuple):
            try:
                check_structure_fractions(list(self.structure_max_samples))
            except ValueError:
                raise invalid_parameter(self, "structure_max_samples", "'auto', a fraction in (0, 1], None, or a list "
                                        "of fractions in (0, 1] or None", self.structure_max_samples) from None
        check_learner(self, f"the regressor {self.regressor!r}", "regressor_params", make_regressor, self.regressor,
                      self.regressor_params)

    def _prepare(self, ds: TransitionDataset, sample_weight: np.ndarray | None) -> Prepared:
        q0 = 0.0
        if self.initial_q is not None:
            a = ds.arrays()
            q0 = float(np.abs(self.initial_q.values(a.obs, 0)).max())
        disc = resolve_discount(ds.info, self.gamma, self.horizon,  # the package's one rule
                                terminates=bool(len(ds)) and bool(ds.arrays().terminated.any()))
        self.gamma_, self.horizon_ = disc.gamma, disc.horizon
        data = prepare(ds, gamma=self.gamma_, horizon=self.horizon_, sample_weight=sample_weight,
                       validation_fraction=self.validation_fraction, random_state=self.random_state,
                       feature_map=self.feature_map, action_input=self.action_input,
                       action_encoding=self.action_encoding, infeasible_cost=self.infeasible_cost,
                       target_noise=self.target_noise, initial_q_abs=q0, who=type(self).__name__)
        self._encoder = data.encoder
        return data

    def _schedule(self) -> tuple[int, ...]:
        """Iterations at which ``mode="frozen"`` builds a structure: ``n_structures`` evenly
        spaced over the K iterations, by default one per 12.5 (``round(0.08 K)``, at least 2)."""
        T = getattr(self, "horizon_", self.horizon)
        K = T if T is not None else self.n_iterations
        S = max(2, round(STRUCTURES_PER_ITERATION * K)) if self.n_structures is None else int(self.n_structures)
        S = max(1, min(S, K))
        return tuple(sorted({1 + (j * K) // S for j in range(S)}))

    def _structure_fraction(self, n: int, regressor: Any) -> float | list[float | None] | None:
        """``structure_max_samples`` with ``"auto"`` resolved: each structure grown on at most
        ``STRUCTURE_ROWS`` rows (a bootstrap fraction) when the regressor bags, else all."""
        f = self.structure_max_samples
        if not (isinstance(f, str) and f == "auto"):
            return f
        return STRUCTURE_ROWS / n if n > STRUCTURE_ROWS and "max_samples" in regressor.get_params() else None

    def resolved_mode(self, regressor: Any = None) -> str:
        """The mode a fit runs: ``mode``, or for ``"auto"`` ``"frozen"`` where it applies (a
        discounted fit, a bagged scikit-learn tree ensemble, the joint action encoding, no
        next-state noise) and ``"refit"`` elsewhere."""
        if self.mode != "auto":
            return self.mode
        from sklearn.ensemble import ExtraTreesRegressor, RandomForestRegressor

        reg = regressor if regressor is not None else make_regressor(self.regressor, **(self.regressor_params or {}))
        finite = getattr(self, "horizon_", self.horizon) is not None
        fits = isinstance(reg, ExtraTreesRegressor | RandomForestRegressor) and self.action_encoding == "joint"
        return "frozen" if fits and not finite and not self.next_state_noise else "refit"

    def _learner(self, data: Prepared) -> Learner:
        reg = make_regressor(self.regressor, **(self.regressor_params or {}))
        self.mode_ = self.resolved_mode(reg)
        queries: dict[str, tuple[np.ndarray, np.ndarray | None]] = {"next": (data.train.phi_next, None), "start": (data.start_phi, None)}
        if data.valid is not None:
            queries["valid"] = (data.valid.phi, data.valid.actions)
            queries["valid_next"] = (data.valid.phi_next, None)
        args = (reg, data.encoder, data.train.phi, data.train.actions, queries, data.weights, self.random_state)
        if self.mode_ == "frozen":
            screen = None if self.screen_trees is None else TreeScreen(int(self.screen_trees), float(self.screen_tol),
                                                                       data.gamma, ~data.train.no_boot)
            # a finite horizon's every iterate is the policy at one step: no build's error is damped
            finite = getattr(self, "horizon_", self.horizon) is not None
            early = (None if self.early_build_trees is None or finite
                     else EarlyBuilds(int(self.early_build_trees), data.gamma, int(self.n_iterations)))
            return FrozenTreesLearner(*args, restructure_at=self._schedule(), max_samples=self._structure_fraction(data.n, reg),
                                      screen=screen, early=early, builder=self.tree_builder)
        if self.mode_ == "warm_start":
            if not type(reg).__name__.startswith("LGBM"):
                warnings.warn(f"mode='warm_start' boosts LightGBM trees; the regressor {type(reg).__name__} is not used "
                              "(LightGBM with 63 leaves, learning rate 0.3)", UserWarning, stacklevel=4)
            return LightGBMWarmStartLearner(*args, trees_per_iteration=self.trees_per_iteration)
        return RefitLearner(*args)

    def _result_policy(self, q: QFunction) -> Any:
        return GreedyPolicy(q)

    def _check_fitted(self) -> None:
        if getattr(self, "q_function_", None) is None:
            raise NotFittedError(f"this {type(self).__name__} is not fitted yet; call fit(dataset) first")


def structure_builds(history: pd.DataFrame) -> list[dict[str, Any]]:
    """The structure builds of a frozen fit's ``history_``: ``{"iteration", "trees", "screen",
    "constant", "builder"}`` per build, in order (``screen``: the build's screen value, None
    when not screened; ``constant``: a build on constant targets, one-leaf trees; ``builder``:
    ``"compiled"`` or ``"scikit-learn"``, None for a constant build; ``trees`` and ``builder``
    None in rows written before they were recorded); an empty list for the other modes."""
    if not len(history) or "structure_trees" not in history:
        return []
    built = history["structure"].diff().fillna(1).to_numpy() != 0
    cols = ["iteration", "structure_trees", "structure_screen", "structure_on_constant", "structure_builder"]
    rows = history.loc[built, [c for c in cols if c in history]].to_dict("records")
    return [{"iteration": int(r["iteration"]),
             "trees": None if _isna(r.get("structure_trees")) else int(r["structure_trees"]),  # None: a run from before
             "screen": None if _isna(r.get("structure_screen")) else float(r["structure_screen"]),
             "constant": not _isna(r.get("structure_on_constant")) and bool(r["structure_on_constant"]),
             "builder": r["structure_builder"] if isinstance(r.get("structure_builder"), str) else None} for r in rows]


def _isna(v: Any) -> bool:
    return v is None or (isinstance(v, float) and np.isnan(v))


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
    total = est.horizon_ if finite else est.n_iterations
    monitor = DivergenceMonitor(data.bound, data.bound_text, q0_abs=data.q0_abs, margin=est.divergence_slack,
                                window=est.patience, finite=finite)
    est._fit_state = (data, learner, backup)  # kept for structure-conditional re-weighting (not saved)
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
    est.verdict_, est.verdict_message_ = verdict(rows, tol=est.tol, finite=finite, divergence=est.divergence_message_,
                                                 converged=conv, window=est.patience)
    est.converged_ = conv
    if rows:
        rows[-1]["verdict"] = est.verdict_
        est.__dict__["_history_dirty"] = True


def _converged(est: FittedQIteration, rows: list[dict[str, Any]]) -> bool:
    """``sup|dQ| < tol`` on an iteration that did not rebuild a structure, after the last
    scheduled build (a pure function of the history, so a resumed fit decides the same)."""
    if est.tol is None or est.horizon_ is not None or len(rows) < 2:
        return False
    last, prev = rows[-1], rows[-2]
    if getattr(est, "mode_", est.mode) == "frozen" and (last["iteration"] < max(est._schedule()) or last.get("structure_on_constant")):
        return False
    return last["sup_dq"] < est.tol and last.get("structure") == prev.get("structure")


def _finished(est: FittedQIteration, rows: list[dict[str, Any]], total: int) -> bool:
    if not rows:
        return False
    return (len(rows) >= total or _converged(est, rows)
            or (est.diverged_ and est.on_divergence == "stop"))


def _diagnostics(data: Prepared, learner: Learner, backup: Backup, it: Iterate, q_prev_train: np.ndarray,
                 q_train: np.ndarray, t0: float, c0: float) -> dict[str, Any]:
    dq = np.abs(q_train - q_prev_train)
    boot = ~data.train.no_boot
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
        "sup_dq": float(dq.max()),
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


# ----------------------------------------------------------------------------- save / load
def save_fqi(est: FittedQIteration, directory: Any, dataset_fingerprint: str | None = None) -> None:
    """Write a fitted FQI's Q-functions, greedy policy definition, params, history and verdict.

    Layout: ``q.json`` + ``q.npz`` (see :mod:`offline_adp.artifacts`; ``q.json`` also holds
    the verdict), ``params.json`` (``get_params()``, estimators by name or repr),
    ``history.csv``.
    """
    import json
    from pathlib import Path

    from offline_adp.artifacts import save_q

    est._check_fitted()
    d = Path(directory)
    params = {k: (v if isinstance(v, str | int | float | bool | type(None) | dict | list) else repr(v)) for k, v in est.get_params().items()}
    save_q(est.q_function_, d, extra={"algorithm": "fqi", "dataset_fingerprint": dataset_fingerprint, "policy": "greedy (argmin_a Q)",
                                      "verdict": getattr(est, "verdict_", None), "verdict_message": getattr(est, "verdict_message_", None),
                                      "gamma": getattr(est, "gamma_", est.gamma), "horizon": getattr(est, "horizon_", est.horizon)})
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
    est.horizon_ = len(q.qs) if isinstance(q, TimeIndexedQ) else None
    est.gamma_ = meta.get("gamma", est.gamma)
    est.policy_ = GreedyPolicy(q)
    est.history_ = pd.read_csv(d / "history.csv")
    est.verdict_, est.verdict_message_ = meta.get("verdict"), meta.get("verdict_message")
    est.diverged_ = est.verdict_ == "diverging"
    est.divergence_message_ = est.verdict_message_ if est.diverged_ else None
    est.dataset_fingerprint_ = meta.get("dataset_fingerprint")
    return est
