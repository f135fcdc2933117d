"""The builds of the frozen-structure LEARN step: when a structure is (re)built and what each
build grows (:class:`FrozenBuilds`: jitter where targets tie, row fraction, early and screened
builds, the compiled or scikit-learn builder, the bookkeeping a resumed fit restores) and
the plan of one build (:class:`BuildPlan`). Shared by
:class:`~offline_adp.learn.frozen.FrozenTreesLearner` and the Dask engine's learner
(:mod:`offline_adp.engines.dask.frozen`), which differ only in where the rows are.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from sklearn.base import clone

from offline_adp.errors import InvalidArgumentError
from offline_adp.learn.base import seeded
from offline_adp.learn.schedule import FrozenSchedule, build_weight
from offline_adp.learn.settle import backups, settle_solve
from offline_adp.qfunctions import QFunction, TreeQ
from offline_adp.trees import builder as compiled
from offline_adp.trees.ensemble import TreeEnsemble, constant_ensemble
from offline_adp.trees.sklearn import sklearn_trees_known


@dataclass
class BuildPlan:
    """What a (non-constant) build grows, decided from its targets and the schedule
    (:meth:`FrozenBuilds._plan`): the same for the in-process and the Dask learner."""

    grow: np.ndarray  #: the targets the trees are grown on (``y``, jittered where tied)
    model: Any  #: the seeded regressor (``n_estimators``: the trees of this build; fewer for an early build)
    full: int  #: the regressor's tree count
    screen: bool  #: grow ``screen.trees`` trees first and the rest only when the screen says so
    native: compiled.TreeParams | None  #: the compiled builder's settings (None: scikit-learn's builder)


class FrozenBuilds:
    """When a frozen-structure LEARN step builds and what each build grows (jitter, row
    fraction, early and screened builds, the builder), and the per-iteration facts it
    records: shared by :class:`FrozenTreesLearner` and the Dask engine's learner
    (:mod:`offline_adp.engines.dask.frozen`), which differ in where the rows are."""

    regressor: Any
    seed: int
    encoder: Any

    def _init_builds(self, schedule: FrozenSchedule | None) -> None:
        self.schedule = schedule = FrozenSchedule() if schedule is None else schedule
        self.builder = schedule.builder
        self.grown_by: str | None = None  # who grew the last build: "compiled", "scikit-learn" (None: constant)
        self.restructure_at = schedule.builds
        self.max_samples = schedule.max_samples
        self.screen = schedule.screen
        self.early = schedule.early
        self.screen_value: float | None = None  # the last build's screen (None: not screened)
        self._pending = True  # no structure yet
        self.structures = 0
        self.built_on_constant = False
        self._m = 0
        self.settle = schedule.settle
        self._targets: Any = None  # (targets, value, greedy): the loop's backup (bind_targets), for the settling
        self._settle_spent = 0  # the solver's backups in this structure
        self.inner_backups = 0  # this iteration's

    def _builds_at(self, k: int) -> bool:
        """Whether iteration ``k`` builds (scheduled, or no structure from real targets yet)."""
        return self._pending or k in self.restructure_at

    def _built(self) -> None:
        self._pending = self.built_on_constant  # constant targets say nothing about where to split

    def bind_targets(self, targets: Any, value: Any, greedy: bool) -> None:
        """The loop's backup, for the final structure's settling (:mod:`offline_adp.learn.settle`):
        ``targets(v_next) -> y`` and ``value(Q(x'_i, .)) -> v_next``, the minimum over the
        columns when ``greedy``."""
        self._targets = (targets, value, bool(greedy))

    def _settle(self, y: np.ndarray, v: np.ndarray, v_prev: np.ndarray | None, k: int, built: bool) -> np.ndarray:
        """Iteration ``k``'s leaf values from its targets ``y`` and their leaf means ``v`` (the
        plain step): in the final structure, when the plain step does not put the values
        within the tolerance of the fixed point (``v_prev``: ``Q_{k-1}``'s leaf values),
        one plain backup of :func:`~offline_adp.learn.settle.anderson_solve`'s fixed point;
        elsewhere ``v``."""
        self.inner_backups = 0
        if built:
            self._settle_spent = 0
        s = self.settle
        if (s is None or self._targets is None or built or v_prev is None or k <= s.after or self.built_on_constant
                or len(v_prev) != len(v)):
            return v
        if s.certifies(float(np.abs(v - v_prev).max(initial=0.0)), y):
            return v  # a plain step within the tolerance: the fit can stop on it
        budget = s.budget - self._settle_spent
        if budget < 2:
            return v
        targets, value, greedy = self._targets
        g, n = settle_solve(np.asarray(y, dtype=np.float64), self._evaluate,
                            lambda v: np.asarray(targets(v), dtype=np.float64), value, s, budget, greedy)
        self._settle_spent += n
        self.inner_backups = n
        return self._leaf_means(g)

    def _evaluate(self, y: np.ndarray) -> np.ndarray:
        """``Q(x'_i, .)`` in this structure with the leaf means of ``y``."""
        return self._next_q(self._leaf_means(y))

    def _leaf_means(self, y: np.ndarray) -> np.ndarray:
        """The (weighted) mean of ``y`` in each leaf (compact index)."""
        raise NotImplementedError

    def _next_q(self, values: np.ndarray) -> np.ndarray:
        """``Q(x'_i, .)`` (as ``predict("next")``) with leaf values ``values``."""
        raise NotImplementedError

    def _start_build(self, y: np.ndarray) -> bool:
        """Count a build; True when its targets are constant (then one-leaf trees)."""
        self.structures += 1
        self.built_on_constant = bool(np.ptp(y) == 0.0)
        self.screen_value = None
        if self.built_on_constant:
            self.grown_by = None
        return self.built_on_constant

    def _constant_structure(self, y: np.ndarray, n_features: int) -> TreeEnsemble:
        """LEARN on constant targets: as many one-leaf trees as the regressor has trees."""
        ens = constant_ensemble(float(y[0]), int(self.regressor.get_params().get("n_estimators", 1)))
        ens.n_features_in_ = int(n_features)  # type: ignore[attr-defined]
        return ens

    def _structure_model(self, k: int) -> Any:
        model = seeded(clone(self.regressor), self.seed + k)
        f = self.schedule.fraction(k)
        if f is not None and f < 1.0:
            if "max_samples" not in model.get_params():
                raise InvalidArgumentError("structure max_samples needs a bagging tree ensemble (extra_trees, "
                                           f"random_forest), not {type(model).__name__}")
            model.set_params(bootstrap=True, max_samples=float(f))
        return model

    def _plan(self, y: np.ndarray, k: int, n_rows: int, n_features: int) -> BuildPlan:
        """The build of iteration ``k`` on targets ``y`` (not constant) over ``n_rows`` joint
        inputs of ``n_features``: jitter where ties would stop splits, the seeded model, an
        early build's tree count, whether to screen, and the builder (sets ``grown_by``)."""
        u, grow = self.schedule.target_unit, y
        if len(np.unique(y)) < len(y):  # ties would stop a node from splitting: break them
            grow = y + np.random.default_rng([self.seed, k, 7]).normal(0.0, 1e-6 * (u + float(np.std(y))), len(y))
        if u != 1.0:  # the builders' absolute constants (a node whose variance is <= eps is pure) read y / u;
            grow = grow / u  # the grown values are multiplied back at the export (_exported)
        model = self._structure_model(k)
        params = model.get_params()
        full = int(params.get("n_estimators") or 0)
        e = self.early
        early = (e is not None and e.gamma < 1.0 and 0 < e.trees < full
                 and (k < max(self.restructure_at) if e.before_last
                      else build_weight(k, tuple(self.restructure_at), e.gamma, e.n_iterations) < e.ratio))
        if early:  # its error is damped before the end: the forest's first trees only, unscreened
            model.set_params(n_estimators=e.trees)
        s = self.screen
        screen = (not early and s is not None and s.tol > 0 and s.gamma < 1.0 and self.encoder.n_actions > 1
                  and "warm_start" in params and full > s.trees)
        native = (compiled.native_params(model, n_rows, n_features)
                  if self.builder == "auto" and compiled.available() and sklearn_trees_known() else None)
        self.grown_by = "compiled" if native is not None else "scikit-learn"
        return BuildPlan(grow, model, full, screen, native)

    def state(self) -> dict[str, Any]:
        return {"structure": self.structures, "structure_on_constant": self.built_on_constant,
                "structure_trees": int(self._m), "structure_screen": self.screen_value,
                "structure_builder": self.grown_by, "inner_backups": self.inner_backups}

    def snapshot(self) -> QFunction:
        """The current Q: the structure (``_exported()``) with the leaf values of this iteration
        (a leaf without training rows keeps the value it was grown with)."""
        ens = self._exported()  # type: ignore[attr-defined]
        value = ens.value.copy()
        value[self.leaf_ids] = self.leaf_values  # type: ignore[attr-defined]
        return TreeQ([ens.with_values(value)], self.encoder)

    def _restore_builds(self, rows: list[dict[str, Any]] | None) -> None:
        """The build bookkeeping of a resumed fit, from its history rows."""
        last = (rows or [{}])[-1]
        self.structures = int(last.get("structure") or 1)
        self.built_on_constant = bool(last.get("structure_on_constant") or False)
        screened = last.get("structure_screen")
        self.screen_value = None if screened is None or screened != screened else float(screened)  # NaN: none
        by = last.get("structure_builder")
        self.grown_by = by if isinstance(by, str) else None
        self._pending = self.built_on_constant
        # the solver's backups so far in this structure, as the rows recorded them
        self._settle_spent = sum(backups(r) for r in rows or [] if r.get("structure") == last.get("structure"))
        self.inner_backups = backups(last)
