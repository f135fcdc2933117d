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

Continuous commands (``commands="continuous"``; the default on a dataset whose action
table is ``continuous``): ``Q(x, u)`` takes the exact logged command ``u`` as input, and the
minimum over ``a'`` runs over the candidate set ``C(x')`` of the next state: the commands
logged at the ``n_candidates`` logged states nearest to ``x'``
(:class:`~offline_adp.qfunctions.NeighbourCommands`; batch-constrained, as in Fujimoto et
al. 2019), followed by ``R``, up to ``n_representatives`` representative commands of the
whole log (:func:`~offline_adp.algorithms.fqi_data.command_representatives`: the logged
command nearest the mean of each occupied cell of a grid of quantile bins, ``floor(n^(1/m))``
per varying component)::

    C(x) = {u_j : j among the n_candidates logged states nearest to x}  U  R
    y_i = c_i + gamma * (1 - terminated_i) * min_{u' in C(x'_i)} Q_{k-1}(x'_i, u')
    Q_k = LEARN({((x_i, u_i), y_i)})

and the greedy policy is ``argmin_{u in C(x)} Q(x, u)`` (ties to the nearest neighbour's
command). What it guarantees: neither the backup nor the policy ever uses a command that was
not logged at one of the ``n_candidates`` logged states nearest to the state in question or
is not one of ``R`` (each a command logged somewhere in the data, dense
where the logged commands are dense: a binned fit of the same logs minimises over such
representatives everywhere), so the minimum cannot run to an arbitrary command between or
beyond the logged ones (the chapter's warning about the min over actions). ``R`` is there
because the neighbours alone were measured to lose to bins on path_tracking (a neighbourhood
of demonstrations offers only the demonstrator's commands; docs/continuous-commands.md);
``n_representatives=0`` keeps the stricter, neighbourhood-only set. "Nearest" has no distance cap (at the data's edge
the nearest logged states can be far). With a fixed ``C(x')`` per next state (no ``next_state_noise``) the backup is
still a gamma-contraction for a fixed tree structure (an averager; the frozen mode's convergence statement holds
unchanged).

Fitted Q *evaluation* (Algorithms 12/13, :mod:`offline_adp.algorithms.fqe`) is the same
loop, :func:`~offline_adp.algorithms.fqi_loop.fitted_q_loop`, with another backup (the policy's expectation instead of
the minimum, :mod:`offline_adp.algorithms.fqi_data`). ``terminated`` transitions (goal or failure) are nailed to their
cost; ``truncated`` ones bootstrap from ``next_obs``. With ``infeasible_cost = c^-`` every target is clamped to at most
``c^-`` and transitions costing ``>= c^-`` do not bootstrap. See :mod:`offline_adp.learn` for the three ways of doing
LEARN (``mode``). Around the loop, not in it: the divergence monitor and verdict
(:mod:`~offline_adp.algorithms.fqi_monitor`), the history, resume, and save/load.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from numbers import Integral, Real
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from sklearn.utils._param_validation import HasMethods, Interval, StrOptions

from offline_adp.algorithms.fqi_data import GreedyBackup, Prepared, prepare, resolve_commands
from offline_adp.algorithms.fqi_loop import FittedQEstimator
from offline_adp.algorithms.fqi_modes import (
    MODES,
    LearnModes,
)
from offline_adp.algorithms.fqi_modes import (
    STRUCTURE_ROWS as STRUCTURE_ROWS,  # re-exported: the old import path
)
from offline_adp.algorithms.fqi_modes import STRUCTURES_PER_ITERATION as STRUCTURES_PER_ITERATION
from offline_adp.algorithms.fqi_monitor import structure_builds as structure_builds
from offline_adp.algorithms.params import (
    GAMMA,
    NON_NEGATIVE,
    POSITIVE_INT,
    SEED,
)
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.discount import resolve_discount
from offline_adp.errors import NotFittedError
from offline_adp.policies import attach_signature, greedy_policy
from offline_adp.qfunctions import QFunction, TimeIndexedQ
from offline_adp.regressors import REGRESSORS


# ----------------------------------------------------------------------------- the estimator
class FittedQIteration(LearnModes, FittedQEstimator):
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
        (Ernst et al.'s and mushroom-rl's design); how they compare: docs/fqi-modes.md.
        ``mode="frozen"`` grows ``per_action`` as trees that split on the action first
        (a joint Q); ``auto`` runs it as ``refit``; warm-start needs ``joint``.
    action_input : {"value", "onehot"}
        What a joint model sees of the action: its value vector from the action table
        (Ernst et al.'s choice) or a one-hot code.
    feature_map : transformer, optional
        ``phi``, fitted on the dataset's observations before LEARN.
    n_iterations : int or "auto"
        K for the infinite horizon (ignored for finite horizons); every mode runs K
        iterations at most. ``"auto"`` (default): chosen by the discount
        (:func:`~offline_adp.algorithms.fqi_monitor.auto_iterations`, ``K_b = ceil(log 0.05 /
        log gamma)``: 59 at gamma 0.95, 299 at 0.99). A frozen fit builds its structures at
        geometrically spaced iterations up to ``K_b / 4`` (``n_structures``), then solves its
        final structure's fixed point (accelerated backups, :mod:`offline_adp.learn.settle`)
        and stops on the first plain iteration that has converged (below), at ``4 K_b``
        iterations at most; the other modes run ``K_b``.
    tol, rtol : float or None, float
        When a fit has converged, and stops early (never before the last scheduled
        build, nor on an iteration that rebuilt a structure or ran the settling solver). In the frozen mode: when
        ``gamma / (1 - gamma) * sup|Q_k - Q_{k-1}|`` over the data's pairs (how far the
        values can still be from the final structure's fixed point, at any input; see
        :mod:`~offline_adp.algorithms.fqi_monitor`) is at most ``tol`` if given, else
        ``rtol * max|Q_k|`` (default 0.01: 1% of the values' scale). In the refit and warm-start modes no such bound
        holds: the fit stops when
        ``sup|Q_k - Q_{k-1}| < tol`` and otherwise runs all K (``rtol`` is not used).
    mode : {"auto", "refit", "frozen", "warm_start"}
        ``auto`` (default): ``frozen`` where it applies (a discounted fit, a bagged
        scikit-learn tree ensemble such as the default extra-trees, the joint action
        encoding, no next-state noise), else ``refit``; the mode that ran is ``mode_``.
        ``refit``: the plain loop, any regressor, re-fitted every iteration.
        ``frozen``: a scikit-learn tree ensemble's structure is built on a schedule
        (``n_structures``; again after any build on constant targets), and the iterations
        in between only re-average leaf values (Ernst et al. 2005, section 4.3). Between
        builds it converges towards the fixed point of the averager its structure defines,
        which is only as good as the structure, so the schedule matters (its score and CPU
        against refit and against fixed counts: docs/fqi-modes.md).
        ``warm_start``: LightGBM, ``trees_per_iteration`` new trees per iteration boosted
        from the previous Q (joint encoding; with a non-LightGBM regressor it uses LightGBM
        with 63 leaves and learning rate 0.3, and says so in a warning). Boosting a few
        trees per iteration is a partial LEARN; it did not hold the refit score on any
        problem we measured (docs/fqi-modes.md), and the CLI warns.
    trees_per_iteration : int
        For ``warm_start``.
    n_structures : int or None
        For ``frozen``: that many builds evenly spaced over the K iterations (``K_b`` for
        ``"auto"``). None (default): with ``n_iterations="auto"`` builds at 1 and at
        ``L, L/4, L/16, ...``, ``L`` the largest power of two up to ``K_b / 4`` (1, 4, 16, 64
        at gamma 0.99; :func:`~offline_adp.algorithms.fqi_modes.geometric_builds`); with a
        number K one per 12.5 iterations (``round(0.08 K)``, at least 2). Each build costs
        about one refit iteration; an averaging iteration costs a few percent of one.
    structure_max_samples : "auto", float, list of (float or None), or None
        For ``frozen``: each tree's structure is grown on a bootstrap sample of this
        fraction of the rows (``bootstrap=True, max_samples=...``); its leaves are then
        averaged over *all* training rows falling in them. Builds are cheaper and the
        forest smaller (about ``2 * fraction * n`` nodes a fully grown tree, instead of
        ``2n``), but each leaf averages ~``1 / fraction`` rows: coarser (docs/fqi-modes.md).
        A list gives
        one fraction per scheduled build (``1.0``: all rows). ``"auto"`` (default): all
        rows up to 131,072, a bootstrap of 131,072 rows beyond (so 1M transitions fit in
        memory and time); ``None``: the regressor's own.
    screen_trees : int or None
        For ``frozen``, opt-in (None, the default: every build grows the whole forest).
        Each build first grows this many trees, and grows the regressor's full count (its
        ``n_estimators``, scikit-learn's warm start: the same trees a one-shot fit grows)
        only when the smaller forest would bias the greedy targets: the expected shortfall
        of ``min_a' Q(x', a')`` below the full forest's from Monte Carlo noise between the
        best action and the others (:func:`~offline_adp.learn.schedule.greedy_min_bias`, summed
        over the other actions), averaged over the next states, carried through the
        horizon ``1 / (1 - gamma)``, above ``screen_tol * std(y)``. No screen with
        ``screen_tol = 0``, ``gamma >= 1``, one action, or ``n_estimators <= screen_trees``.
        **Not the default because it did not hold everywhere** (docs/fqi-modes.md):
        compare with an unscreened fit before relying on it.
    screen_tol : float
        The screen's threshold, a fraction of the targets' standard deviation (>= 0; 0
        grows the whole forest at every build).
    early_build_trees : int, "auto" or None
        For ``frozen``. ``"auto"`` (default): with the schedule of ``n_iterations="auto"``
        (``n_structures=None``) the builds before the last grow a fifth of the forest (the
        last structure is solved to its own fixed point; measured: docs/fqi-modes.md),
        otherwise as None. None: every build grows the whole forest. A number, opt-in: with
        that schedule the builds before the last grow that many trees; otherwise a
        build whose error reaches the final Q with less than half the weight of the last
        build's grows only this many trees (the first trees of the forest it would grow).
        Fitted Q-iteration's last iterate carries the error of iteration ``j``'s LEARN
        step by ``gamma^(K - j)`` (the chapter's bound on approximate value iteration), so
        a structure serving iterations ``s .. e`` weighs ``sum_{j=s..e} gamma^(K - j)``
        (:func:`~offline_adp.learn.schedule.build_weight`). The last build always grows the
        whole forest (unless the screen keeps fewer), and ``tol`` never stops a fit before
        it; the weights assume all K iterations run, so a fit that ``tol`` stops early has
        damped its early builds' error less. No effect with a finite horizon, where every
        iterate is the policy at one step.
        **The weight rule is opt-in because it did not hold everywhere** (docs/fqi-modes.md):
        the bound damps an early structure's error in the values, not in the later
        structures grown on the targets it produced.
    tree_builder : {"auto", "sklearn"}
        Who grows the frozen mode's structures. ``"auto"`` (default): the compiled
        extra-trees builder (:mod:`offline_adp.trees.builder`, numba) wherever the regressor
        is a scikit-learn ``ExtraTreesRegressor`` with settings it implements (the default
        regressor's are); scikit-learn otherwise. It is the same algorithm (Geurts et al.
        2006) with the same settings, not the same random draws, so a fit differs from the
        ``"sklearn"`` one as two seeds do, with one exception: on targets tied up to the
        learner's tie-breaking jitter scikit-learn stops splitting at random points (a
        rounding effect) where this builder splits on (see :mod:`offline_adp.trees.builder`).
        It grows structures in less CPU than scikit-learn and returns each training
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
    commands : {"auto", "continuous", "binned"}
        What an action is. ``"continuous"``: the exact command vector of each row (the
        dataset's ``action_value.<dim>`` columns), minimised over each state's candidate
        commands (module docstring); ``"binned"``: the action table's entries (bins of a
        continuous command, or a discrete table); ``"auto"`` (default): continuous where
        the dataset's action table is ``continuous``, else the table.
    n_candidates : int
        Continuous commands: the candidate set of a state is the commands logged at its
        ``n_candidates`` nearest logged states (default 8).
    n_representatives : int
        Continuous commands: the candidate set of every state also holds up to this many
        representative commands of the whole log (default 16; 0: the neighbours' alone;
        module docstring).

    Attributes
    ----------
    q_function_ : QFunction
        ``Q`` (infinite horizon) or a :class:`TimeIndexedQ` over ``Q_0..Q_{T-1}``.
    policy_ : GreedyPolicy or GreedyCommandPolicy
        The latter for continuous commands: ``act`` returns command vectors.
    commands_ : str
        ``"continuous"`` or ``"binned"``: what the fit's actions were.
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
        "n_iterations": [POSITIVE_INT, StrOptions({"auto"})],
        "tol": [NON_NEGATIVE, None],
        "rtol": [NON_NEGATIVE],
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
        "early_build_trees": [POSITIVE_INT, StrOptions({"auto"}), None],
        "tree_builder": [StrOptions({"auto", "sklearn"})],
        "commands": [StrOptions({"auto", "continuous", "binned"})],
        "n_candidates": [Interval(Integral, 1, 4096, closed="both")],
        "n_representatives": [Interval(Integral, 0, 4096, closed="both")],
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
        n_iterations: int | str = "auto",
        tol: float | None = None,
        rtol: float = 0.01,
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
        early_build_trees: int | str | None = "auto",
        tree_builder: str = "auto",
        commands: str = "auto",
        n_candidates: int = 8,
        n_representatives: int = 16,
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
        self.rtol = rtol
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
        self.commands = commands
        self.n_candidates = n_candidates
        self.n_representatives = n_representatives

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
        return self.run_fitted_q(dataset, sample_weight, resume, lambda data: GreedyBackup(), deferred=deferred)

    def predict(self, obs: np.ndarray, t: int | np.ndarray = 0) -> np.ndarray:
        """Q-values of all actions, shape (n, n_actions)."""
        self._check_fitted()
        return self.q_function_.values(np.asarray(obs, dtype=np.float64), t)

    # ------------------------------------------------------------------ pieces
    def _prepare(self, ds: TransitionDataset, sample_weight: np.ndarray | None) -> Prepared:
        q0 = 0.0
        if self.initial_q is not None:
            a = ds.arrays()
            q0 = float(np.abs(self.initial_q.values(a.obs, 0)).max())
        disc = resolve_discount(ds.info, self.gamma, self.horizon,  # the package's one rule
                                terminates=bool(len(ds)) and bool(ds.arrays().terminated.any()))
        self.gamma_, self.horizon_ = disc.gamma, disc.horizon
        self.commands_ = resolve_commands(self, ds)
        data = prepare(ds, gamma=self.gamma_, horizon=self.horizon_, sample_weight=sample_weight,
                       validation_fraction=self.validation_fraction, random_state=self.random_state,
                       feature_map=self.feature_map, action_input=self.action_input,
                       action_encoding=self.action_encoding, infeasible_cost=self.infeasible_cost,
                       target_noise=self.target_noise, initial_q_abs=q0, who=type(self).__name__,
                       n_candidates=self.n_candidates if self.commands_ == "continuous" else None,
                       policy_commands=self._policy_commands(), n_representatives=self.n_representatives,
                       costs_in_unit=self.resolved_mode() == "frozen")
        self._encoder = data.encoder
        return data

    def _policy_commands(self) -> Any:
        """The candidate set of an evaluation over continuous commands (FQE: the policy's
        command); None: the commands logged at the nearest logged states."""
        return None

    def _result_policy(self, q: QFunction) -> Any:
        return greedy_policy(q)

    def _check_fitted(self) -> None:
        if getattr(self, "q_function_", None) is None:
            raise NotFittedError(f"this {type(self).__name__} is not fitted yet; call fit(dataset) first")


# ----------------------------------------------------------------------------- save / load
def save_fqi(est: FittedQIteration, directory: Any, dataset_fingerprint: str | None = None) -> None:
    """Write a fitted FQI's Q-functions, greedy policy definition, params, history and verdict.

    Layout: ``q.json`` + ``q.npz`` (see :mod:`offline_adp.artifacts`; ``q.json`` also holds
    the verdict), ``params.json`` (``get_params()``, estimators by name or repr),
    ``history.csv``.
    """
    from offline_adp.artifacts import save_q

    est._check_fitted()
    d = Path(directory)
    plain = str | int | float | bool | type(None) | dict | list
    params = {k: (v if isinstance(v, plain) else repr(v)) for k, v in est.get_params().items()}
    meta = {"algorithm": "fqi", "dataset_fingerprint": dataset_fingerprint, "policy": "greedy (argmin_a Q)",
            "verdict": getattr(est, "verdict_", None), "verdict_message": getattr(est, "verdict_message_", None),
            "gamma": getattr(est, "gamma_", est.gamma), "horizon": getattr(est, "horizon_", est.horizon)}
    save_q(est.q_function_, d, extra=meta)
    (d / "params.json").write_text(json.dumps(params, indent=1))
    est.history_.to_csv(d / "history.csv", index=False)


def load_fqi(directory: Any) -> FittedQIteration:
    """Read what :func:`save_fqi` wrote; the result predicts and acts like the saved one."""
    from offline_adp.artifacts import load_q
    from offline_adp.data.files import read_json_file, read_table_file

    d = Path(directory)
    q, meta = load_q(d)
    raw = read_json_file(d / "params.json")  # missing, corrupt or not an object: ArtifactError naming it
    known = FittedQIteration().get_params()
    est = FittedQIteration(**{k: v for k, v in raw.items() if k in known
                              and not (isinstance(v, str) and v.startswith(("<", "Pipeline(", "OneHot")))})
    est.q_function_ = q
    est.q_functions_ = list(q.qs) if isinstance(q, TimeIndexedQ) else None
    est.horizon_ = len(q.qs) if isinstance(q, TimeIndexedQ) else None
    est.gamma_ = meta.get("gamma", est.gamma)
    est.policy_ = est._result_policy(q)
    est.history_ = read_table_file(d / "history.csv")
    est.verdict_, est.verdict_message_ = meta.get("verdict"), meta.get("verdict_message")
    est.diverged_ = est.verdict_ == "diverging"
    est.divergence_message_ = est.verdict_message_ if est.diverged_ else None
    est.dataset_fingerprint_ = meta.get("dataset_fingerprint")
    return est
