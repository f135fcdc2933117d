"""Fitted Q-iteration and evaluation on the cluster.

:class:`DistributedFQI` is not a second fitted-Q loop: it runs the package's loop
(:meth:`~offline_adp.algorithms.fqi_loop.FittedQEstimator.run_fitted_q`) with the data prepared here (the
dataset's rows as blocks on the workers, the per-transition vectors on the client) and a
learner whose fit and predictions run on the cluster
(:class:`~offline_adp.engines.dask.learner.DaskLearner`). :class:`DaskFit` is the same
engine for the run writer (:func:`offline_adp.runs.fit_run` with ``engine=``), so a Dask
fit's run directory is written, checkpointed and resumed by the same code as a local one's.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.engines.dask.blocks import _Blocks, _chunk_plan, scheduler_workers
from offline_adp.engines.dask.cluster import _one_line, flat_columns
from offline_adp.engines.dask.frozen import DaskFrozenLearner
from offline_adp.engines.dask.learner import DaskLearner
from offline_adp.errors import (
    ClusterError,
    ClusterWarning,
    DatasetNotFoundError,
    IngestError,
    InvalidArgumentError,
    OfflineADPError,
)


class DistributedFQI:
    """Fitted Q-iteration (Algorithm 11, or 10 for a dataset whose hints make it finite
    horizon; with ``policy``, fitted Q evaluation, Algorithms 13/12) with LEARN on a Dask
    cluster: LightGBM trained data-parallel by ``lightgbm.dask``.

    It is the package's one fitted-Q loop
    (:meth:`~offline_adp.algorithms.fqi_loop.FittedQEstimator.run_fitted_q` and
    :func:`~offline_adp.algorithms.fqi_loop.fitted_q_loop`) run for :meth:`estimator`, the
    in-process estimator with the same parameters, with two parts supplied from here: the
    prepared data and the learner (:class:`DaskLearner`). Per iteration::

        y_i = c_i + gamma (1 - term_i) min_a' Q_{k-1}(x'_i, a')    (client: numpy, O(n))
        Q_k = LEARN({((x_i, a_i), y_i)})                            (workers: lightgbm.dask)
        Q_k(x'_i, a'), Q_k(x_i, a_i), Q_k(x_0, a)                  (workers, per block)

    The regression inputs stay on the workers, block ``i`` of the dataset's rows on the
    ``i``-th worker (sorted addresses, modulo their number): LightGBM's data-parallel
    result depends on which rows each worker holds, so this placement is restored before
    every training (after a worker was lost and restarted, the fit continues to the same
    Q). The client holds the per-transition vectors the loop reads (cost, flags, actions,
    ``Q(x', .)``: ``8 (n_actions + 3)`` bytes per transition; next states too for FQE).
    With one worker the result equals :meth:`estimator`'s in-process fit (LightGBM with
    one thread); with several, LightGBM's data-parallel training gives a close, not an
    equal, Q (its histogram bins come from each worker's rows).

    ``regressor="extra_trees"`` (with ``regressor_params``) runs the in-process default
    mode instead, frozen extra-trees structures
    (:class:`~offline_adp.engines.dask.frozen.DaskFrozenLearner`: trees grown on the
    workers, leaf values re-averaged from per-block leaf sums; ``n_iterations="auto"``
    and the in-process build schedule). On one worker its Q equals the in-process
    ``FittedQIteration()`` fit's bit for bit, on one worker or several (the leaf sums are
    taken in row order, segment after segment).

    ``warm_start=True`` is the in-process ``mode="warm_start"``: each iteration adds
    ``trees_per_iteration`` trees fitted to the residual ``y_k - Q_{k-1}(x_i, a_i)``;
    the cached predictions live on the client, only the new trees are evaluated on the
    workers. History, divergence monitor and verdict are the in-process ones.

    Parameters
    ----------
    gamma : float, optional
        Default: the dataset's hint, else 0.95 (:func:`offline_adp.data.discount.resolve_discount`).
    n_iterations : int
    lgbm_params : dict
        LightGBM parameters (on top of the ``lightgbm`` registry entry's); ``n_jobs`` is
        ignored on the cluster (a worker uses its own threads).
    regressor : {"lightgbm", "extra_trees"}
        LightGBM (refit or warm start) or the default frozen extra-trees mode.
    regressor_params : dict, optional
        The extra-trees parameters (``regressor="extra_trees"``).
    time_out : int
        Minutes LightGBM's Dask network setup may wait (so nothing hangs for hours).
    retries : int
        Times an iteration whose LightGBM training lost a worker (or found its rows on
        other workers than their blocks') is retried; the last try trains wherever the
        rows are (the Q may then differ from an undisturbed fit's).
    worker_wait_s : float
        Seconds to wait for a lost worker to be back before an iteration trains on the
        workers there are (that iteration is then listed in ``unplaced_iterations_``).
        After one such wait the fit does not wait again until the number of workers
        changes. Workers that join never add LightGBM ranks: the blocks stay on as many
        workers as the fit started with.
    random_state : int
        Iteration k's trees are seeded with ``random_state + k``.
    policy : Policy, optional
        Evaluate this policy (FQE backup) instead of the greedy one.
    warm_start : bool
        Boost each Q from the previous one (see above).
    trees_per_iteration : int
        New trees per iteration with ``warm_start``.

    Attributes
    ----------
    q_function_, history_, verdict_, verdict_message_, diverged_, divergence_message_, gamma_
        As :class:`~offline_adp.algorithms.fqi.FittedQIteration`'s.
    value_ : float
        With ``policy``: the estimated expected cost from the data's start states.
    estimator_ : FittedQIteration
        The in-process estimator the loop ran for (holds the same attributes).
    retried_ : int
        Trainings retried (a lost worker, rows not in their places).
    unplaced_iterations_ : list of int
        Iterations trained with some block away from its worker (fewer workers than at
        the start after ``worker_wait_s``, or the last retry): their Q may differ from an
        undisturbed fit's. A :class:`~offline_adp.errors.ClusterWarning` names them.
    """

    def __init__(self, gamma: float | None = None, n_iterations: int = 10, lgbm_params: dict | None = None,
                 time_out: int = 2, retries: int = 2, random_state: int = 0, policy: Any = None,
                 warm_start: bool = False, trees_per_iteration: int = 10, worker_wait_s: float = 60.0,
                 regressor: str = "lightgbm", regressor_params: dict | None = None) -> None:
        self.gamma, self.n_iterations, self.lgbm_params = gamma, n_iterations, lgbm_params
        self.regressor, self.regressor_params = regressor, regressor_params
        self.time_out, self.retries, self.random_state, self.policy = time_out, retries, random_state, policy
        self.worker_wait_s = worker_wait_s
        self.warm_start, self.trees_per_iteration = warm_start, trees_per_iteration

    def estimator(self) -> Any:
        """The in-process estimator with these parameters (the loop this engine runs)."""
        from offline_adp.algorithms.fqe import FittedQEvaluation
        from offline_adp.algorithms.fqi import FittedQIteration

        lgbm = self.regressor == "lightgbm"
        common = {"gamma": self.gamma, "regressor": self.regressor,
                  "regressor_params": self.lgbm_params if lgbm else self.regressor_params,
                  "n_iterations": self.n_iterations,
                  "mode": "warm_start" if self.warm_start else "refit" if lgbm else "auto",
                  "trees_per_iteration": self.trees_per_iteration, "random_state": self.random_state}
        return FittedQEvaluation(policy=self.policy,
                                 **common) if self.policy is not None else FittedQIteration(**common)

    def fit(self, client: Any, dataset_dir: str | PathLike[str], on_iteration: Any = None,
            checkpoint_dir: str | PathLike[str] | None = None) -> DistributedFQI:
        """Fit on a dataset directory; ``on_iteration(k)`` is called after iteration k.

        Tasks lost with a worker are recomputed by Dask; a LightGBM training that fails
        because a worker vanished mid-way is retried (``retries`` times) from the same Q,
        with the rows back in their places. With ``checkpoint_dir`` the Q and history of
        every completed iteration are written there (atomically, by the run writer's codec
        :mod:`offline_adp.algorithms.checkpoint`) and a later ``fit`` continues from them,
        e.g. after the scheduler was lost, to the Q of an uninterrupted fit.

        Raises
        ------
        ClusterError
            The cluster was lost (or had no worker) during the fit; the message names the
            checkpoint to continue from.
        ArtifactError
            ``checkpoint_dir`` holds a damaged checkpoint (the message names the file).
        """
        from offline_adp.algorithms.checkpoint import read_checkpoint, write_checkpoint

        engine = DaskFit(client, time_out=self.time_out, retries=self.retries, worker_wait_s=self.worker_wait_s)
        est = self.estimator()
        ck = Path(checkpoint_dir) if checkpoint_dir is not None else None
        resume = read_checkpoint(ck) if ck is not None else None
        rows: list[dict[str, Any]] = list(resume["history"]) if resume else []
        for row in engine.fit_iter(est, dataset_dir, resume, checkpoint_dir=ck):
            rows.append(row)
            if ck is not None:
                write_checkpoint(ck, est, rows)
            if on_iteration is not None:
                on_iteration(row["iteration"])
        self.estimator_ = est
        self.gamma_, self.q_function_, self.history_ = est.gamma_, est.q_function_, est.history_
        self.verdict_, self.verdict_message_ = est.verdict_, est.verdict_message_
        self.diverged_, self.divergence_message_ = est.diverged_, est.divergence_message_
        self.retried_ = engine.retried_
        self.unplaced_iterations_ = engine.unplaced_iterations_
        if self.policy is not None and self.q_function_ is not None:
            self.value_ = est.value_
        return self


#: Estimator parameters the Dask engine honours; any other must keep its default value
HONOURED = frozenset({"regressor", "regressor_params", "gamma", "horizon", "n_iterations", "random_state", "mode",
                      "trees_per_iteration", "tol", "rtol", "infeasible_cost", "target_noise", "on_divergence",
                      "patience", "divergence_slack", "policy"})
#: ... and in the frozen extra-trees mode, its build schedule
HONOURED_FROZEN = frozenset({"n_structures", "structure_max_samples", "tree_builder", "early_build_trees"})


def unsupported(est: Any, dataset_dir: str | PathLike[str] | None = None) -> str | None:
    """Why the Dask engine cannot fit ``est`` (a ``FittedQIteration`` or
    ``FittedQEvaluation``) on ``dataset_dir`` as the local fit would, or None when it can:
    LightGBM in ``refit``/``warm_start`` (``auto``: refit), or extra-trees / random
    forests in the frozen mode (``frozen``, or ``auto`` where it resolves to frozen for this
    dataset's discount: a finite horizon resolves to ``refit``), with every parameter the
    engine does not read at its default."""
    import inspect

    from offline_adp.data.discount import resolve_discount
    from offline_adp.data.info import DatasetInfo
    from offline_adp.data.io import read_info
    from offline_adp.regressors import make_regressor

    defaults = {k: p.default for k, p in inspect.signature(type(est).__init__).parameters.items()
                if p.default is not inspect.Parameter.empty}
    reg = make_regressor(est.regressor, **(est.regressor_params or {}))
    lightgbm = type(reg).__name__.startswith("LGBM")
    honoured = HONOURED if lightgbm else HONOURED | HONOURED_FROZEN
    changed = sorted(k for k, v in est.get_params(deep=False).items()
                     if k not in honoured and k in defaults and not _same(v, defaults[k]))
    if changed:
        return f"parameters {changed} are not read by the Dask engine"
    if lightgbm:
        return None if est.mode in ("auto", "refit", "warm_start") else f"mode {est.mode!r} with LightGBM"
    if est.mode == "warm_start":
        return f"warm start with {type(reg).__name__}"
    horizon = est.horizon
    if horizon is None and dataset_dir is not None:  # the dataset's hints may make the fit finite-horizon
        with contextlib.suppress(OfflineADPError, OSError, ValueError):  # a bad info.json: the fit's own error
            info = DatasetInfo.from_dict(read_info(Path(dataset_dir)))
            horizon = resolve_discount(info, est.gamma, None).horizon
    mode = est.mode
    if mode == "auto":  # as resolved_mode, with the dataset's horizon: finite means refit
        mode = "refit" if horizon is not None else est.resolved_mode(reg)
    if mode != "frozen":
        return f"{type(reg).__name__} in mode {mode!r} (the engine fits trees in the frozen mode only)"
    from sklearn.ensemble import ExtraTreesRegressor, RandomForestRegressor

    if not isinstance(reg, ExtraTreesRegressor | RandomForestRegressor):
        return f"the frozen mode with {type(reg).__name__} (it needs extra-trees or a random forest)"
    return None


def _warn_logs(info: Any, cost: np.ndarray, term: np.ndarray, step: np.ndarray, obs_min: np.ndarray,
               obs_max: np.ndarray, who: str, costs_in_unit: bool) -> None:
    """The in-process fit's warnings on the logs (costs or features too small for the
    tree builders, a time limit flagged as terminal), from the blocks' vectors and each
    block's feature range: episodes are contiguous in a dataset, their steps consecutive."""
    from offline_adp.algorithms.fqi_data import _warn_scale, _warn_time_limit

    span = np.vstack([obs_min.min(axis=0), obs_max.max(axis=0)]) if len(obs_min) else np.zeros((0, 0))
    _warn_scale(cost, span, list(info.feature_names), who, costs_in_unit)
    new = np.ones(len(step), bool)
    new[1:] = (step[1:] == 0) | (step[1:] != step[:-1] + 1)
    _warn_time_limit(np.cumsum(new) - 1, term, who)


def _same(a: Any, b: Any) -> bool:
    try:
        return bool(a == b) or (a is None and b == {}) or (a == {} and b is None)
    except Exception:  # arrays and the like: only identity counts as unchanged
        return a is b


class DaskFit:
    """The Dask engine of the run writer (:func:`offline_adp.runs.fit_run`'s ``engine``):
    runs a fitted-Q estimator's iterations (FQI or FQE) on the cluster: the loop of its
    ``fit_iter``. LightGBM (``mode`` ``"refit"``, ``"auto"`` (refit) or ``"warm_start"``),
    or frozen extra-trees (``mode="frozen"``, or ``"auto"`` where it resolves to frozen:
    the default ``FittedQIteration()``; :class:`DaskFrozenLearner`, the local fit's Q bit
    for bit). Other regressors, modes and parameters are refused before anything runs
    (:func:`unsupported`; InvalidArgumentError).

    Parameters
    ----------
    client : distributed.Client
        The cluster's client.
    time_out, retries, worker_wait_s
        As :class:`DistributedFQI`'s.

    Attributes
    ----------
    retried_ : int
        Trainings retried in the last fit.
    unplaced_iterations_ : list of int
        Iterations of the last fit trained with rows away from their workers.
    """

    name = "dask"

    def __init__(self, client: Any, *, time_out: int = 2, retries: int = 2, worker_wait_s: float = 60.0) -> None:
        w = worker_wait_s
        if isinstance(w, bool) or not isinstance(w, int | float) or not 0 <= w < float("inf"):
            raise InvalidArgumentError(f"worker_wait_s must be a number of seconds >= 0, got {w!r}")
        self.client, self.time_out, self.retries, self.worker_wait_s = client, time_out, retries, worker_wait_s
        self.retried_, self.unplaced_iterations_ = 0, []

    def fit_iter(self, est: Any, dataset_dir: str | PathLike[str], resume: dict[str, Any] | None = None, *,
                 checkpoint_dir: str | PathLike[str] | None = None) -> Iterator[dict[str, Any]]:
        """Fit ``est`` (a ``FittedQIteration`` or ``FittedQEvaluation``) on the dataset
        directory on the cluster, yielding each iteration's history row as ``est.fit_iter``
        does; ``resume`` is a checkpoint
        (:func:`~offline_adp.algorithms.checkpoint.read_checkpoint`). ``checkpoint_dir`` is
        only named in the error of a lost cluster. ``est`` ends fitted (FQE: with ``value_``)."""
        from offline_adp.algorithms.fqe import FittedQEvaluation
        from offline_adp.algorithms.fqi_data import GreedyBackup

        why = unsupported(est, dataset_dir)
        if why is not None:
            raise InvalidArgumentError(f"the Dask engine cannot run this fit ({why}); use the local engine")
        fqe = isinstance(est, FittedQEvaluation)
        engine = _DaskEngine(self.client, est, self, fqe=fqe)
        backup = est._backup if fqe else (lambda data: GreedyBackup())
        try:
            with self.client.as_current():  # every compute goes to this client, even when others exist
                yield from est.run_fitted_q(dataset_dir, None, resume, backup, prepare=engine.prepare,
                                            make_learner=engine.learner)
        except Exception as exc:  # CommClosedError is an OSError; a lost scheduler cancels the futures too
            from distributed.client import FutureCancelledError

            where = f"; re-run to continue from the checkpoint in {checkpoint_dir}" if checkpoint_dir else ""
            if isinstance(engine.learner_, DaskFrozenLearner) and self.client.status == "running" \
                    and isinstance(exc, KeyError | FutureCancelledError | ClusterError):
                # the frozen mode's leaf positions live on their workers: a worker gone takes them
                raise ClusterError(f"a worker holding rows of the frozen-structure fit was lost "
                                   f"({type(exc).__name__}: {_one_line(exc)}){where}") from exc
            if not isinstance(exc, OSError | TimeoutError) and self.client.status == "running":
                raise
            raise ClusterError(f"lost the Dask cluster during fitted Q-iteration ({type(exc).__name__}: "
                               f"{_one_line(exc)}){where}") from exc
        finally:
            engine.release()
            est.discard_fit_state()  # fit_state_ holds the cluster-side learner
            self.retried_, self.unplaced_iterations_ = engine.retried, engine.unplaced
        if self.unplaced_iterations_:
            warnings.warn(f"iterations {self.unplaced_iterations_} trained with rows away from their workers (a worker "
                          f"lost and not back within worker_wait_s = {self.worker_wait_s} s, or the last retry): the Q "
                          "may differ from an undisturbed fit's", ClusterWarning, stacklevel=2)
        if fqe and est.q_function_ is not None:
            x0 = engine.data.start_obs
            est.value_ = float((est.policy.probabilities(x0, 0) * est.q_function_.values(x0, 0)).sum(axis=1).mean())

    @staticmethod
    def unsupported(est: Any, dataset_dir: str | PathLike[str] | None = None) -> str | None:
        """Why this engine cannot run ``est`` on ``dataset_dir`` (:func:`unsupported`), or None."""
        return unsupported(est, dataset_dir)

    def summary(self) -> dict[str, Any]:
        """What the run writer adds to ``run.json`` for a fit on this engine."""
        return {"engine": self.name, "retried": self.retried_, "unplaced_iterations": list(self.unplaced_iterations_)}


class _DaskEngine:
    """The two parts :meth:`~offline_adp.algorithms.fqi_loop.FittedQEstimator.run_fitted_q` takes from the Dask
    engine: the prepared data (vectors on the client, inputs on the workers) and the learner."""

    def __init__(self, client: Any, est: Any, cfg: DaskFit, fqe: bool = False) -> None:
        self.client, self.est, self.cfg, self.fqe = client, est, cfg, fqe
        self.blocks: _Blocks | None = None
        self.learner_: DaskLearner | DaskFrozenLearner | None = None

    @property
    def retried(self) -> int:
        return getattr(self.learner_, "retried", 0)

    @property
    def unplaced(self) -> list[int]:
        return list(getattr(self.learner_, "unplaced", []))

    def prepare(self, dataset_dir: str | PathLike[str], sample_weight: Any = None) -> Any:
        from offline_adp.algorithms.fqi_data import Prepared, Samples, value_bound
        from offline_adp.data.discount import resolve_discount
        from offline_adp.data.info import DatasetInfo
        from offline_adp.data.io import part_files, read_info
        from offline_adp.qfunctions import QEncoder
        from offline_adp.regressors import make_regressor

        path = Path(dataset_dir)
        info = DatasetInfo.from_dict(read_info(path), where=str(path / "meta" / "info.json"))
        parts = [str(p) for p in part_files(path)]
        if not parts:
            raise DatasetNotFoundError(f"{path}: no data parts (part-*.parquet); is it a dataset directory?")
        if info.action_table.continuous and getattr(self.estimator(), "commands", "auto") != "binned":
            from offline_adp.errors import IncompatibleError

            raise IncompatibleError(f"{path}: the Dask engine learns over the action table's entries; this dataset's "
                                    "commands are continuous: fit it in process, or with commands = 'binned' to learn "
                                    "over its bins")
        af = np.asarray(info.action_table.values, dtype=np.float64)
        cols = flat_columns(info)
        n_workers = len(scheduler_workers(self.client))
        plan = _chunk_plan(parts, n_workers)
        if not plan:
            raise IngestError(f"{path}: the dataset is empty (no rows in its parts)")
        self.blocks = _Blocks(self.client, plan, cols["obs"], cols["next_obs"], af, n_workers,
                              wait_s=self.cfg.worker_wait_s)
        v = self.blocks.gather(("cost", "terminated", "action", "step", "obs_min", "obs_max"))
        cost, term, step = v["cost"], v["terminated"], v["step"]
        est = self.est
        _warn_logs(info, cost, term, step, v["obs_min"], v["obs_max"], type(est).__name__,
                   costs_in_unit=est.resolved_mode(make_regressor(est.regressor, **(est.regressor_params or {})))
                   == "frozen")
        disc = resolve_discount(info, est.gamma, est.horizon, terminates=bool(term.any()))
        est.gamma_, est.horizon_ = disc.gamma, disc.horizon
        if disc.horizon is None and not disc.gamma < 1.0 and not term.any():
            raise InvalidArgumentError(f"the infinite-horizon algorithm needs gamma < 1 (got {disc.gamma}) "
                                       "unless episodes terminate (a shortest-path problem); give a horizon instead")
        # the chapter's c^-: no bootstrap from a row that reached it, targets clamped
        c_inf = getattr(est, "infeasible_cost", None)
        no_boot = term if c_inf is None else term | (cost >= c_inf)
        bound, text = value_bound(float(np.abs(cost).max()), disc.gamma, disc.horizon, c_inf,
                                  getattr(est, "target_noise", 0.0), cmin=float(cost.min()))
        start = step == 0
        start_obs = self.blocks.gather(("start",
                                        ))["start"] if start.any() else self.blocks.gather(("first",))["first"][:1]
        next_obs = self.blocks.gather(("next",))["next"] if self.fqe else None  # FQE's backup
        est._encoder = enc = QEncoder(len(af), af)
        actions = v["action"].astype(np.int64)
        # phi, next inputs and observations stay on the workers (self.blocks): None here
        train = Samples(phi=None, actions=actions, cost=cost, no_boot=no_boot, phi_next=None, next_obs=next_obs)  # type: ignore[arg-type]
        self.data = Prepared(train=train, valid=None, weights=None, gamma=disc.gamma, n_actions=len(af), encoder=enc,
                             obs=None, obs_std=None, start_phi=None, start_obs=start_obs,  # type: ignore[arg-type]
                             start_rows=np.flatnonzero(start) if start.any() else np.zeros(1, np.int64),
                             bound=bound, bound_text=text, infeasible_cost=c_inf)
        return self.data

    def learner(self, data: Any) -> DaskLearner | DaskFrozenLearner:
        from offline_adp.regressors import make_regressor

        est, cfg = self.est, self.cfg
        reg = make_regressor(est.regressor, **(est.regressor_params or {}))
        assert self.blocks is not None
        if est.mode != "warm_start" and est.resolved_mode(reg) == "frozen":  # the default: frozen extra-trees
            est.mode_ = "frozen"
            self.learner_ = DaskFrozenLearner(self.client, self.blocks, reg, data.encoder, data.train.actions,
                                              est.random_state, est._frozen_schedule(data, reg),
                                              start_obs=data.start_obs)
            return self.learner_
        if not type(reg).__name__.startswith("LGBM") and est.mode != "warm_start":
            raise InvalidArgumentError(f"the Dask engine fits {type(reg).__name__} in mode 'frozen' (or "
                                       f"'auto' resolving to it) only, not {est.mode!r}; use the local engine")
        est.mode_ = "warm_start" if est.mode == "warm_start" else "refit"  # LightGBM 'auto': refit on the workers
        self.learner_ = DaskLearner(self.client, self.blocks, reg, data.encoder, data.train.actions, est.random_state,
                                    warm_start=est.mode == "warm_start", trees_per_iteration=est.trees_per_iteration,
                                    time_out=cfg.time_out, retries=cfg.retries, start_obs=data.start_obs)
        return self.learner_

    def release(self) -> None:
        if isinstance(self.learner_, DaskFrozenLearner):
            self.learner_.release()
        if self.blocks is not None:
            self.blocks.release()

