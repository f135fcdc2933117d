"""How :class:`~offline_adp.algorithms.fqi.FittedQIteration` chooses and configures LEARN.

A mixin holding the choices around the loop, not the loop: the mode a fit runs
(``"auto"`` resolved), the iteration plan (``n_iterations="auto"``), the frozen mode's
schedule of structure builds (when a build happens, on how many rows, the tree screen and
the early builds) and the settling of its final structure (:mod:`offline_adp.learn.settle`),
the learner built from them (:mod:`offline_adp.learn`), and the parameter combinations
``_parameter_constraints`` cannot express. FittedQEvaluation inherits the same choices.

The schedule of ``n_iterations="auto"`` (issue #44). Rebuilding a structure pays when the
targets have moved enough to need other splits: fast at first (the ``k``-step values of
small ``k`` change shape with every step), hardly at all once ``gamma^k`` is small. Builds
at 1 and at ``L, L/4, L/16, ...`` (``L`` the largest power of two up to ``K_b / 4``, where
``gamma^L`` is 0.47-0.69) follow that; the builds before the last grow a
fifth of the forest (``early_build_trees="auto"``), since only the last structure is kept,
and its fixed point is then solved for (settled) instead of iterated towards in hundreds
of plain backups. With a fixed count of iterations the schedule is as before: one build
per 12.5 iterations, whole forests, plain backups. Measured: docs/fqi-modes.md.
"""

from __future__ import annotations

import functools
import warnings
from typing import Any

import numpy as np

from offline_adp.algorithms.fqi_data import GreedyBackup, Prepared
from offline_adp.algorithms.fqi_monitor import auto_iterations
from offline_adp.algorithms.params import check_learner, invalid_parameter
from offline_adp.learn import (
    EarlyBuilds,
    FrozenSchedule,
    FrozenTreesLearner,
    Learner,
    LearnSpec,
    LightGBMWarmStartLearner,
    RefitLearner,
    Settle,
    TreeScreen,
    check_structure_fractions,
)
from offline_adp.learn.settle import backups
from offline_adp.regressors import make_regressor, predict_n_jobs

#: default frozen schedule: structures per iteration (8 over 100 iterations; docs/fqi-modes.md)
STRUCTURES_PER_ITERATION = 0.08
#: ``structure_max_samples="auto"``: a frozen structure is grown on at most this many rows (bootstrap)
STRUCTURE_ROWS = 131_072
MODES = ("auto", "refit", "frozen", "warm_start")
#: ``n_iterations="auto"``'s default schedule (:func:`geometric_builds`): the last build at the
#: largest power of two up to this fraction of K_b, the ones before it this factor apart
GEOMETRIC_LAST, GEOMETRIC_RATIO = 0.25, 4
#: ... and the builds before the last grow this fraction of the forest (``early_build_trees="auto"``)
INTERMEDIATE_TREES = 0.2


def _next_backup(backup: Any, q_next: Any) -> Any:
    """The loop's backup of next-state Q-values (what a frozen learner settles with): a
    module-level function, so that a fitted estimator pickles (a Dask task's result)."""
    return backup(q_next, "next", None)


def geometric_builds(k_b: int, last: float = GEOMETRIC_LAST, ratio: int = GEOMETRIC_RATIO) -> tuple[int, ...]:
    """Iteration 1 and ``L, L / ratio, L / ratio^2, ...`` (whole numbers), ``L`` the largest
    power of two at most ``max(1, last * k_b)``: at gamma 0.99 (K_b 299) 1, 4, 16, 64; at
    0.95 (K_b 59) 1, 2, 8."""
    top = 1 << max(0, int(np.floor(np.log2(max(1.0, last * k_b)))))
    out, x = {1}, top
    while x >= 1:
        out.add(x)
        if x % ratio:
            break
        x //= ratio
    return tuple(sorted(out))


class LearnModes:
    """The mode, iteration plan and frozen schedule of a fitted-Q estimator (module
    docstring); mixed into :class:`~offline_adp.algorithms.fqi.FittedQIteration`, whose
    hyper-parameters it reads."""

    @staticmethod
    def mode_caveat(mode: str | None) -> str | None:
        """What a user should know before trusting ``mode`` (None: nothing): the fast paths
        did not hold the refit score on every problem we measured (docs/fqi-modes.md)."""
        if mode == "warm_start":
            return (f"mode = {mode!r} did not hold the refit score on any problem we measured (docs/fqi-modes.md); "
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

    def iteration_plan(self) -> tuple[int, int]:
        """``(K_b, K_max)`` of a fit: the iterations the frozen builds are spread over, and
        the most it runs (``n_iterations`` for both when it is a number; for ``"auto"``
        :func:`~offline_adp.algorithms.fqi_monitor.auto_iterations` of the fit's gamma and
        mode). Needs the fit's ``gamma_`` (set at the start of ``fit``)."""
        if self.n_iterations != "auto":
            return int(self.n_iterations), int(self.n_iterations)
        settles = getattr(self, "mode_", None) == "frozen" and not self.target_noise  # a fixed point to reach
        return auto_iterations(self.gamma_, settles)

    def _schedule(self) -> tuple[int, ...]:
        """Iterations at which ``mode="frozen"`` builds a structure: ``n_structures`` evenly
        spaced over the K iterations (K_b for ``"auto"``: :meth:`iteration_plan`; T for a
        finite horizon); by default :func:`geometric_builds` of K_b where the fit settles
        (:meth:`_settles`), else one per 12.5 (``round(0.08 K)``, at least 2)."""
        T = getattr(self, "horizon_", self.horizon)
        K = T if T is not None else self.iteration_plan()[0]
        if self._settles() and self.n_structures is None:
            return geometric_builds(K)
        S = max(2, round(STRUCTURES_PER_ITERATION * K)) if self.n_structures is None else int(self.n_structures)
        S = max(1, min(S, K))
        return tuple(sorted({1 + (j * K) // S for j in range(S)}))

    def _settles(self) -> bool:
        """Whether a frozen fit solves its final structure's fixed point
        (:mod:`offline_adp.learn.settle`): ``n_iterations="auto"``, discounted, no target noise."""
        return (self.n_iterations == "auto" and getattr(self, "horizon_", self.horizon) is None
                and not self.target_noise and getattr(self, "gamma_", 0.0) < 1.0)

    def _converged(self, rows: list[dict[str, Any]]) -> bool:
        """Never on an iteration that ran the settling solver (its Q is not one backup of
        the one before: :mod:`offline_adp.learn.settle`)."""
        if rows and backups(rows[-1]):
            return False
        return super()._converged(rows)  # type: ignore[misc]

    def run_fitted_q(self, dataset: Any, sample_weight: Any, resume: Any, make_backup: Any, prepare: Any = None,
                     make_learner: Any = None, *, deferred: bool = False) -> Any:
        """The loop (:meth:`~offline_adp.algorithms.fqi_loop.FittedQEstimator.run_fitted_q`),
        with a frozen learner told the loop's targets (``bind_targets``: what the final
        structure's settling backs up)."""
        made: dict[str, Any] = {}

        def learner_of(data: Prepared) -> Learner:
            made["learner"] = (make_learner or self._learner)(data)
            return made["learner"]

        def backup_of(data: Prepared) -> Any:
            backup = make_backup(data)
            bind = getattr(made.get("learner"), "bind_targets", None)
            if bind is not None:
                bind(data.targets, functools.partial(_next_backup, backup), isinstance(backup, GreedyBackup))
            return backup

        return super().run_fitted_q(dataset, sample_weight, resume, backup_of, prepare,  # type: ignore[misc]
                                    learner_of, deferred=deferred)

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
        queries: dict[str, tuple[np.ndarray, np.ndarray | None]] = {"next": (data.train.phi_next, None),
                                                                    "start": (data.start_phi, None)}
        if data.valid is not None:
            queries["valid"] = (data.valid.phi, data.valid.actions)
            queries["valid_next"] = (data.valid.phi_next, None)
        spec = LearnSpec(regressor=reg, encoder=data.encoder, phi=data.train.phi, actions=data.train.actions,
                         queries=queries, weights=data.weights, seed=self.random_state)
        if self.mode_ == "frozen":
            return FrozenTreesLearner(spec, self._frozen_schedule(data, reg))
        if self.mode_ == "warm_start":
            if not type(reg).__name__.startswith("LGBM"):
                warnings.warn(f"mode='warm_start' boosts LightGBM trees; the regressor {type(reg).__name__} "
                              "is not used (LightGBM with 63 leaves, learning rate 0.3)", UserWarning, stacklevel=4)
            return LightGBMWarmStartLearner(spec, trees_per_iteration=self.trees_per_iteration)
        return RefitLearner(spec, predict_jobs=predict_n_jobs(self.regressor, self.regressor_params))

    def _frozen_schedule(self, data: Prepared, reg: Any) -> FrozenSchedule:
        """The builds of ``mode="frozen"`` on ``data`` (also the Dask engine's)."""
        screen = None if self.screen_trees is None else TreeScreen(int(self.screen_trees), float(self.screen_tol),
                                                                   data.gamma, ~data.train.no_boot)
        # a finite horizon's every iterate is the policy at one step: no build's error is damped
        finite = getattr(self, "horizon_", self.horizon) is not None
        settling = self._settles() and self.n_structures is None and data.gamma < 1
        trees = self.early_build_trees
        if isinstance(trees, str):  # "auto": a fifth of the forest before the settled structure, else all
            full = int(reg.get_params().get("n_estimators") or 0) if hasattr(reg, "get_params") else 0
            trees = max(1, round(INTERMEDIATE_TREES * full)) if settling and full else None
        early = (None if trees is None or finite
                 else EarlyBuilds(int(trees), data.gamma, self.iteration_plan()[0], before_last=settling))
        builds = self._schedule()
        settle = (Settle(data.gamma, max(builds), self.tol, float(self.rtol), budget=self.iteration_plan()[1])
                  if self._settles() and data.gamma < 1 else None)
        return FrozenSchedule(restructure_at=builds, screen=screen, early=early, settle=settle,
                              max_samples=self._structure_fraction(data.n, reg), builder=self.tree_builder,
                              target_unit=data.cost_unit)
