"""Scale-out on Dask (``pip install offline-adp[dask]``): distributed ingestion, FQI and
FQE with LightGBM trained by ``lightgbm.dask``, and task maps for evaluation.
Single-process stays the default.

:class:`DistributedFQI` is not a second fitted-Q loop: it runs the package's loop
(:func:`~offline_adp.algorithms.fqi_loop.run_fitted_q`) with the data prepared here (the
dataset's rows as blocks on the workers, the per-transition vectors on the client) and a
learner whose fit and predictions run on the cluster (:class:`DaskLearner`). What scales:
the regression (data-parallel LightGBM) and the predictions over every block; the
targets are O(n) vector arithmetic on the client. Extra-trees (scikit-learn) stay
single-node (the local engine).

Pitfall (dask 2026.8): persisting the direct output of ``read_parquet(columns=...)``
breaks later computes; :func:`read_dataset_dask` inserts a ``map_partitions`` first.
"""

from __future__ import annotations

import contextlib
import operator
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from offline_adp.errors import ClusterWarning, OfflineADPError
from offline_adp.learn import Learner, LearnSpec, LightGBMWarmStartLearner
from offline_adp.qfunctions import BoostedSumQ, QFunction, RegressorQ, predict_model


def _one_line(exc: BaseException, limit: int = 400) -> str:
    """An exception's text on one line (Dask's span lines and list every future), shortened."""
    text = " ".join(str(exc).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _require_dask() -> None:
    try:
        import dask  # noqa: F401
        import distributed  # noqa: F401
    except ImportError:
        raise OfflineADPError("the Dask engine needs the dask extra: pip install 'offline-adp[dask]'") from None


LOST_WORKER_TIMEOUT_S = 120
"""Seconds a local cluster waits for a restarted worker process to register (Dask's default: 15)."""


@dataclass(frozen=True)
class EngineConfig:
    """``[engine]`` settings: ``kind = "local" | "dask"``; for Dask either ``address`` of an
    existing scheduler or a LocalCluster on loopback with ``n_workers`` x ``threads_per_worker``."""

    kind: str = "local"
    address: str | None = None
    n_workers: int = 2
    threads_per_worker: int = 1
    memory_limit: str = "4GiB"
    dashboard: bool = False


@contextlib.contextmanager
def dask_client(cfg: EngineConfig) -> Iterator[Any]:
    """A ``distributed.Client`` for the config (a LocalCluster on 127.0.0.1 unless ``address``)."""
    _require_dask()
    import dask
    from distributed import Client, LocalCluster

    if cfg.address:
        try:
            client = Client(cfg.address, timeout="10s")
        except OSError as exc:
            raise OfflineADPError(f"cannot reach the Dask scheduler at {cfg.address}: {exc}") from None
        try:
            yield client
        finally:
            client.close()
        return
    # A worker process that dies is restarted by its nanny; the cluster gives the new process
    # ``lost-worker-timeout`` to register before it closes the nanny for good. Dask's 15 s is
    # less than a restart (spawn, imports) takes on a busy 2-core machine, and a cluster that
    # dropped a worker trains on fewer machines (another Q), so a local cluster waits longer.
    from dask.utils import parse_timedelta

    lost = max(LOST_WORKER_TIMEOUT_S, parse_timedelta(dask.config.get("distributed.deploy.lost-worker-timeout")) or 0)
    with (dask.config.set({"distributed.deploy.lost-worker-timeout": f"{lost}s"}),
          LocalCluster(n_workers=cfg.n_workers, threads_per_worker=cfg.threads_per_worker, processes=True,
                       host="127.0.0.1", dashboard_address=":0" if cfg.dashboard else None,
                       memory_limit=cfg.memory_limit) as cluster, Client(cluster) as client):
        yield client


def read_dataset_dask(path: str | PathLike[str], columns: list[str] | None = None) -> Any:
    """The dataset's Parquet parts as a Dask DataFrame, one partition per part (part order kept)."""
    _require_dask()
    import dask.dataframe as dd

    from offline_adp.data.io import part_files

    parts = [str(p) for p in part_files(Path(path))]
    if not parts:
        raise OfflineADPError(f"{path}: no data parts")
    ddf = dd.read_parquet(parts, columns=columns, split_row_groups=False)
    # dask 2026.8: persisting read_parquet(columns=...) directly breaks later computes
    return ddf.map_partitions(lambda df: df.copy(), meta=ddf._meta)


def flat_columns(info: Any) -> dict[str, list[str]]:
    """Column names of observations and next observations in a dataset's Parquet parts."""
    from offline_adp.data import schema as S

    names = info.feature_names
    return {"obs": [f"{S.OBS_PREFIX}{n}" for n in names], "next_obs": [f"{S.NEXT_OBS_PREFIX}{n}" for n in names]}


# ----------------------------------------------------------------------------- FQI on the cluster
class DistributedFQI:
    """Fitted Q-iteration (Algorithm 11, or 10 for a dataset whose hints make it finite
    horizon; with ``policy``, fitted Q evaluation, Algorithms 13/12) with LEARN on a Dask
    cluster: LightGBM trained data-parallel by ``lightgbm.dask``.

    It is the package's one fitted-Q loop
    (:func:`~offline_adp.algorithms.fqi_loop.run_fitted_q` and
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
                 warm_start: bool = False, trees_per_iteration: int = 10, worker_wait_s: float = 60.0) -> None:
        self.gamma, self.n_iterations, self.lgbm_params = gamma, n_iterations, lgbm_params
        self.time_out, self.retries, self.random_state, self.policy = time_out, retries, random_state, policy
        self.worker_wait_s = worker_wait_s
        self.warm_start, self.trees_per_iteration = warm_start, trees_per_iteration

    def estimator(self) -> Any:
        """The in-process estimator with these parameters (the loop this engine runs)."""
        from offline_adp.algorithms.fqe import FittedQEvaluation
        from offline_adp.algorithms.fqi import FittedQIteration

        common = {"gamma": self.gamma, "regressor": "lightgbm", "regressor_params": self.lgbm_params,
                  "n_iterations": self.n_iterations, "mode": "warm_start" if self.warm_start else "refit",
                  "trees_per_iteration": self.trees_per_iteration, "random_state": self.random_state}
        return FittedQEvaluation(policy=self.policy, **common) if self.policy is not None else FittedQIteration(**common)

    def fit(self, client: Any, dataset_dir: str | PathLike[str], on_iteration: Any = None,
            checkpoint_dir: str | PathLike[str] | None = None) -> DistributedFQI:
        """Fit on a dataset directory; ``on_iteration(k)`` is called after iteration k.

        Tasks lost with a worker are recomputed by Dask; a LightGBM training that fails
        because a worker vanished mid-way is retried (``retries`` times) from the same Q,
        with the rows back in their places. With ``checkpoint_dir`` the Q and history of
        every completed iteration are written there (atomically) and a later ``fit``
        continues from them, e.g. after the scheduler was lost, to the Q of an
        uninterrupted fit.
        """
        w = self.worker_wait_s
        if isinstance(w, bool) or not isinstance(w, int | float) or not 0 <= w < float("inf"):
            raise ValueError(f"worker_wait_s must be a number of seconds >= 0, got {w!r}")
        try:
            with client.as_current():  # every compute goes to this client, even when others exist
                return self._fit(client, dataset_dir, on_iteration, checkpoint_dir)
        except Exception as exc:  # CommClosedError is an OSError; a lost scheduler cancels the futures too
            if not isinstance(exc, OSError | TimeoutError) and client.status == "running":
                raise
            where = f"; re-run to continue from the checkpoint in {checkpoint_dir}" if checkpoint_dir else ""
            raise OfflineADPError(f"lost the Dask cluster during fitted Q-iteration ({type(exc).__name__}: "
                                 f"{_one_line(exc)}){where}") from exc

    def _fit(self, client: Any, dataset_dir: str | PathLike[str], on_iteration: Any,
             checkpoint_dir: str | PathLike[str] | None) -> DistributedFQI:
        from offline_adp.algorithms.fqi_data import GreedyBackup
        from offline_adp.algorithms.fqi_loop import run_fitted_q

        est = self.estimator()
        engine = _DaskEngine(client, est, self)
        ck = Path(checkpoint_dir) if checkpoint_dir is not None else None
        resume = _read_checkpoint(ck) if ck is not None else None
        rows: list[dict[str, Any]] = list(resume["history"]) if resume else []
        backup = est._backup if self.policy is not None else (lambda data: GreedyBackup())
        try:
            for row in run_fitted_q(est, dataset_dir, None, resume, backup, prepare=engine.prepare,
                                    make_learner=engine.learner):
                rows.append(row)
                if ck is not None:
                    _write_checkpoint(ck, est, rows)
                if on_iteration is not None:
                    on_iteration(row["iteration"])
        finally:
            engine.release()
        est.__dict__.pop("fit_state_", None)  # holds the cluster-side learner
        self.estimator_ = est
        self.gamma_, self.q_function_, self.history_ = est.gamma_, est.q_function_, est.history_
        self.verdict_, self.verdict_message_ = est.verdict_, est.verdict_message_
        self.diverged_, self.divergence_message_ = est.diverged_, est.divergence_message_
        self.retried_ = engine.retried
        self.unplaced_iterations_ = engine.unplaced
        if self.unplaced_iterations_:
            warnings.warn(f"iterations {self.unplaced_iterations_} trained with rows away from their workers (a worker "
                          f"lost and not back within worker_wait_s = {self.worker_wait_s} s, or the last retry): the Q "
                          "may differ from an undisturbed fit's", ClusterWarning, stacklevel=2)
        if self.policy is not None and self.q_function_ is not None:
            x0 = engine.data.start_obs
            self.value_ = float((self.policy.probabilities(x0, 0) * self.q_function_.values(x0, 0)).sum(axis=1).mean())
        return self


def _write_checkpoint(ck: Path, est: Any, rows: list[dict[str, Any]]) -> None:
    from offline_adp.artifacts import save_q
    from offline_adp.data.io import atomic_directory
    from offline_adp.qfunctions import TimeIndexedQ

    q: Any = est.q_function_ if est.horizon_ is None else TimeIndexedQ(list(reversed(est.q_functions_)))
    with atomic_directory(ck, overwrite=True) as tmp:
        save_q(q, tmp, extra={"iteration": len(rows)})
        pd.DataFrame(rows).to_csv(tmp / "history.csv", index=False)


def _read_checkpoint(ck: Path) -> dict[str, Any] | None:
    """``{"q", "history"}`` for :func:`~offline_adp.algorithms.fqi_loop.run_fitted_q`'s resume, or None."""
    from offline_adp.artifacts import load_q
    from offline_adp.qfunctions import TimeIndexedQ

    if not (ck / "q.json").exists():
        return None
    hist = pd.read_csv(ck / "history.csv")
    if "sup_dq" not in hist.columns:
        raise OfflineADPError(f"{ck}: a checkpoint of an older version of the Dask FQI (no diagnostics); "
                              "remove it to start the fit again")
    q, _ = load_q(ck)
    rows = [{k: (None if pd.isna(v) else v) for k, v in r.items()} for r in hist.to_dict("records")]
    return {"q": list(q.qs) if isinstance(q, TimeIndexedQ) else q, "history": rows}


class _DaskEngine:
    """The two parts :func:`~offline_adp.algorithms.fqi_loop.run_fitted_q` takes from the Dask
    engine: the prepared data (vectors on the client, inputs on the workers) and the learner."""

    def __init__(self, client: Any, est: Any, cfg: DistributedFQI) -> None:
        self.client, self.est, self.cfg = client, est, cfg
        self.blocks: _Blocks | None = None
        self.learner_: DaskLearner | None = None

    @property
    def retried(self) -> int:
        return 0 if self.learner_ is None else self.learner_.retried

    @property
    def unplaced(self) -> list[int]:
        return [] if self.learner_ is None else list(self.learner_.unplaced)

    def prepare(self, dataset_dir: str | PathLike[str], sample_weight: Any = None) -> Any:
        from offline_adp.algorithms.fqi_data import Prepared, Samples, value_bound
        from offline_adp.data.discount import resolve_discount
        from offline_adp.data.info import DatasetInfo
        from offline_adp.data.io import part_files, read_info
        from offline_adp.qfunctions import QEncoder

        path = Path(dataset_dir)
        info = DatasetInfo.from_dict(read_info(path), where=str(path / "meta" / "info.json"))
        parts = [str(p) for p in part_files(path)]
        if not parts:
            raise OfflineADPError(f"{path}: no data parts")
        af = np.asarray(info.action_table.values, dtype=np.float64)
        cols = flat_columns(info)
        n_workers = len(self.client.scheduler_info()["workers"])
        plan = _chunk_plan(parts, n_workers)
        if not plan:
            raise ValueError("the dataset is empty")
        self.blocks = _Blocks(self.client, plan, cols["obs"], cols["next_obs"], af, n_workers,
                              wait_s=self.cfg.worker_wait_s)
        v = self.blocks.gather(("cost", "terminated", "action", "step"))
        cost, term, step = v["cost"], v["terminated"], v["step"]
        est = self.est
        disc = resolve_discount(info, est.gamma, est.horizon, terminates=bool(term.any()))
        est.gamma_, est.horizon_ = disc.gamma, disc.horizon
        if disc.horizon is None and not disc.gamma < 1.0 and not term.any():
            raise ValueError(f"the infinite-horizon algorithm needs gamma < 1 (got {disc.gamma}) unless episodes "
                             "terminate (a shortest-path problem); give a horizon instead")
        bound, text = value_bound(float(np.abs(cost).max()), disc.gamma, disc.horizon)
        start = step == 0
        start_obs = self.blocks.gather(("start",))["start"] if start.any() else self.blocks.gather(("first",))["first"][:1]
        next_obs = self.blocks.gather(("next",))["next"] if self.cfg.policy is not None else None  # FQE's backup
        est._encoder = enc = QEncoder(len(af), af)
        actions = v["action"].astype(np.int64)
        # phi, next inputs and observations stay on the workers (self.blocks): None here
        train = Samples(phi=None, actions=actions, cost=cost, no_boot=term, phi_next=None, next_obs=next_obs)  # type: ignore[arg-type]
        self.data = Prepared(train=train, valid=None, weights=None, gamma=disc.gamma, n_actions=len(af), encoder=enc,
                             obs=None, obs_std=None, start_phi=None, start_obs=start_obs,  # type: ignore[arg-type]
                             start_rows=np.flatnonzero(start) if start.any() else np.zeros(1, np.int64),
                             bound=bound, bound_text=text)
        return self.data

    def learner(self, data: Any) -> DaskLearner:
        from offline_adp.regressors import make_regressor

        est, cfg = self.est, self.cfg
        if est.mode == "frozen":
            raise ValueError("the Dask engine runs mode 'refit' or 'warm_start'; mode = 'frozen' runs in process")
        est.mode_ = "warm_start" if est.mode == "warm_start" else "refit"  # 'auto': refit on the workers
        reg = make_regressor(est.regressor, **(est.regressor_params or {}))
        assert self.blocks is not None
        self.learner_ = DaskLearner(self.client, self.blocks, reg, data.encoder, data.train.actions, est.random_state,
                                    warm_start=est.mode == "warm_start", trees_per_iteration=est.trees_per_iteration,
                                    time_out=cfg.time_out, retries=cfg.retries, start_obs=data.start_obs)
        return self.learner_

    def release(self) -> None:
        if self.blocks is not None:
            self.blocks.release()


def _chunk_plan(parts: list[str], n_workers: int) -> list[tuple[str, int, int]]:
    """Row ranges ``(part, lo, hi)`` in dataset order: one per Parquet part, the largest
    halved until there is one per worker (a function of the data and ``n_workers`` only)."""
    import pyarrow.parquet as pq

    plan = [(p, 0, pq.ParquetFile(p).metadata.num_rows) for p in parts]
    plan = [c for c in plan if c[2] > c[1]]
    while plan and len(plan) < n_workers:
        j = max(range(len(plan)), key=lambda i: plan[i][2] - plan[i][1])
        p, lo, hi = plan[j]
        if hi - lo < 2:
            break
        plan[j:j + 1] = [(p, lo, (lo + hi) // 2), (p, (lo + hi) // 2, hi)]
    return plan


def _load_block(path: str, lo: int, hi: int, obs_cols: list[str], next_cols: list[str],
                action_features: np.ndarray) -> dict[str, np.ndarray]:
    """Rows ``lo:hi`` of one Parquet part as the arrays a worker keeps (joint training
    inputs ``[x, f(a)]``, next states, start states) and the client's vectors."""
    import pyarrow.parquet as pq

    from offline_adp.data import schema as S

    t = pq.read_table(path, columns=[*obs_cols, *next_cols, S.ACTION, S.COST, S.TERMINATED, S.STEP]).slice(lo, hi - lo)

    def matrix(names: list[str]) -> np.ndarray:
        return np.column_stack([t.column(c).to_numpy().astype(np.float64, copy=False) for c in names])

    obs, a, step = matrix(obs_cols), t.column(S.ACTION).to_numpy().astype(np.int64), t.column(S.STEP).to_numpy()
    nxt = matrix(next_cols)
    follows = np.zeros(len(obs), bool)  # x_i == x'_{i-1}: a logged episode continues
    follows[1:] = (obs[1:] == nxt[:-1]).all(axis=1)
    return {"X": np.hstack([obs, action_features[a]]), "next": nxt, "start": obs[step == 0],
            "start_pos": np.flatnonzero(step == 0), "follows": follows,
            "first": obs[:1], "action": a, "cost": t.column(S.COST).to_numpy().astype(np.float64, copy=False),
            "terminated": t.column(S.TERMINATED).to_numpy(), "step": step}


def _pick(block: dict[str, np.ndarray], keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    return {k: block[k] for k in keys}


class _Blocks:
    """The dataset's rows as blocks on the workers, block ``i`` on the ``i``-th worker."""

    def __init__(self, client: Any, plan: list[tuple[str, int, int]], obs_cols: list[str], next_cols: list[str],
                 action_features: np.ndarray, n_workers: int, wait_s: float = 60.0) -> None:
        self.client, self.plan, self.n_workers, self.wait_s = client, plan, n_workers, wait_s
        self.args = (obs_cols, next_cols, action_features)
        self.futures: list[Any] = []
        self.where: list[str] = []
        self.short = False  # the last placement had fewer workers than at the start
        self._gave_up_at = -1  # the worker count at which a wait last timed out
        self.lengths = [hi - lo for _, lo, hi in plan]
        self.place()

    def place(self) -> None:
        """Block ``i`` on the ``i``-th worker (sorted addresses, mod n). When a block is
        elsewhere (a worker was lost), wait for the workers to be back (up to ``wait_s``)
        and load every block again; check the placement after loading (a worker may come
        or go meanwhile)."""
        from distributed import wait

        client = self.client
        deadline = time.monotonic() + self.wait_s  # one wait per placement, however many tries
        for _ in range(5):
            workers = self._workers(deadline)[: self.n_workers]  # as many ranks as at the start, never more
            ranks = min(len(self.plan), self.n_workers)
            self.short = min(len(self.plan), len(workers)) < ranks  # fewer LightGBM ranks than at the start
            want = [workers[i % len(workers)] for i in range(len(self.plan))]
            if self.futures and want == self.where and self._placed():
                return
            old = self.futures
            self.futures = [client.submit(_load_block, *c, *self.args, workers=[w], allow_other_workers=True, pure=False)
                            for c, w in zip(self.plan, want, strict=True)]
            self.where, self._x = want, None
            wait(self.futures)
            for f in old:
                with contextlib.suppress(Exception):
                    f.release()
            if self._placed():
                return
            time.sleep(1.0)  # a worker came or went while loading

    def _workers(self, deadline: float) -> list[str]:
        """The scheduler's running workers (sorted), once there are ``n_workers`` of them or
        at ``deadline``; after one wait timed out, not again while their number stays the
        same (a worker lost for good costs one wait, not one per iteration). Polled from the
        scheduler: ``Client.wait_for_workers`` goes through a local cluster's own worker
        bookkeeping, and in a stress run here it returned while the restarted worker was
        still missing."""
        while True:
            if self.client.status != "running":
                raise OSError(f"the Dask client is {self.client.status}: no scheduler to place the blocks on")
            info = self.client.scheduler_info()["workers"]
            workers = sorted(w for w, d in info.items() if d.get("status", "running") == "running")
            if len(workers) >= self.n_workers or len(workers) == self._gave_up_at:
                return workers
            if time.monotonic() >= deadline:
                if not workers:
                    raise OfflineADPError(f"no running Dask worker after waiting {self.wait_s:g} s (worker_wait_s)")
                self._gave_up_at = len(workers)
                return workers
            time.sleep(0.25)

    def _placed(self) -> bool:
        has = self.client.who_has(self.futures)
        return all(w in has.get(f.key, ()) for f, w in zip(self.futures, self.where, strict=True))

    def map(self, fn: Any, *args: Any) -> list[Any]:
        """``fn(block, *args)`` for every block, on the block's worker."""
        return [self.client.submit(fn, f, *args, workers=[w], allow_other_workers=True, pure=False)
                for f, w in zip(self.futures, self.where, strict=True)]

    def gather(self, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
        """The blocks' arrays ``keys``, concatenated in row order, on the client."""
        got = self.client.gather(self.map(_pick, keys))
        return {k: np.concatenate([g[k] for g in got]) for k in keys}

    def forget_inputs(self) -> None:
        self._x = None

    def training_inputs(self) -> Any:
        """The joint inputs ``[x_i, f(a_i)]`` as a Dask array, chunk ``i`` on block ``i``'s worker."""
        import dask.array as da

        if self._x is None:
            width = len(self.args[0]) + self.args[2].shape[1]
            parts = self.map(operator.getitem, "X")
            self._x = da.concatenate([da.from_delayed(f, shape=(m, width), dtype=np.float64)
                                      for f, m in zip(parts, self.lengths, strict=True)])
        return self._x

    def labels(self, y: np.ndarray) -> Any:
        """``y`` as a Dask array chunked (and placed) like :meth:`training_inputs`."""
        import dask.array as da

        edges = np.r_[0, np.cumsum(self.lengths)]
        futs = [self.client.scatter(y[lo:hi], workers=[w], hash=False)
                for lo, hi, w in zip(edges[:-1], edges[1:], self.where, strict=True)]
        return da.concatenate([da.from_delayed(f, shape=(m,), dtype=np.float64)
                               for f, m in zip(futs, self.lengths, strict=True)])

    def release(self) -> None:
        for f in self.futures:
            with contextlib.suppress(Exception):  # the cluster may be gone already
                f.release()
        self.futures, self._x = [], None


def _predict_block(block: dict[str, np.ndarray], model: Any, encoder: Any, booster: bool) -> dict[str, np.ndarray]:
    """One model's predictions on a block, one thread (the worker's own): ``next`` and
    ``start`` ``(m, n_actions)`` for every action, ``train`` ``(m,)`` at the logged
    actions. A training input equal to one already predicted (the previous row's next
    state, or a start state) is read from there: the same input gives the same value."""
    def pred(X: np.ndarray) -> np.ndarray:
        if not len(X):
            return np.zeros(0)
        return np.asarray(model.predict(X, raw_score=True, num_threads=1), dtype=np.float64) if booster else predict_model(model, X)

    def all_actions(x: np.ndarray) -> np.ndarray:
        return pred(encoder.all_pairs(x)).reshape(encoder.n_actions, len(x)).T

    out = {"next": all_actions(block["next"]), "start": all_actions(block["start"])}
    a, follows, start = block["action"], block["follows"], block["start_pos"]
    train = np.empty(len(a))
    rest = ~follows
    rest[start] = False
    train[follows] = out["next"][np.flatnonzero(follows) - 1, a[follows]]
    train[start] = out["start"][np.arange(len(start)), a[start]]
    train[rest] = pred(block["X"][rest])
    out["train"] = train
    return out


class DaskLearner(Learner):
    """LEARN on the cluster over the dataset's blocks (:class:`DistributedFQI`): LightGBM
    trained data-parallel by ``lightgbm.dask`` on the joint inputs ``[x, f(a)]``;
    predictions of the training, next and start sets computed block by block on the
    workers and gathered. ``warm_start``: each iteration boosts ``trees_per_iteration``
    trees on the residual from the previous Q, with the sums cached on the client (as
    :class:`~offline_adp.learn.warm_start.LightGBMWarmStartLearner`, with its parameters).
    Iteration ``k``'s trees are seeded with ``seed + k``.
    """

    QUERIES = ("train", "next", "start")

    def __init__(self, client: Any, blocks: _Blocks, regressor: Any, encoder: Any, actions: np.ndarray, seed: int, *,
                 warm_start: bool = False, trees_per_iteration: int = 10, time_out: int = 2, retries: int = 2,
                 start_obs: np.ndarray | None = None) -> None:
        super().__init__(LearnSpec(regressor, encoder, None, actions, {}, None, seed))  # type: ignore[arg-type]
        self.client, self.blocks, self.warm_start, self.trees_per_iteration = client, blocks, warm_start, trees_per_iteration
        self.time_out, self.retries, self.retried = time_out, retries, 0
        self.unplaced: list[int] = []  # iterations trained with a block away from its worker
        self.start_obs = start_obs  # start states when no block has one (the first row)
        self.n_start = int(sum(blocks.client.gather(blocks.map(_count_starts))))
        self.boosters: list[Any] = []
        self._cache: dict[str, np.ndarray] = {}
        if warm_start:
            self._cache = self._sum_predictions([])

    def _params(self, k: int) -> dict[str, Any]:
        if self.warm_start:  # the in-process warm start's parameters, in the scikit-learn interface's names
            p = LightGBMWarmStartLearner.booster_params(self.regressor, self.seed + k)
            renamed = {"min_data_in_leaf": "min_child_samples", "seed": "random_state"}
            params = {renamed.get(key, key): v for key, v in p.items() if key != "num_threads"}
            return {**params, "n_estimators": self.trees_per_iteration}
        params = {key: v for key, v in self.regressor.get_params().items() if key != "n_jobs"}  # workers decide threads
        return {**params, "random_state": self.seed + k}

    def fit(self, y: np.ndarray, k: int) -> None:
        from lightgbm.dask import DaskLGBMRegressor

        label = y - self._cache["train"] if self.warm_start else y  # warm start: the residual, boosted from its mean
        for attempt in range(self.retries + 1):
            try:
                self.blocks.place()  # the rows each worker trains on decide LightGBM's result
                ordered = _OrderedClient(self.client, self.blocks.where, strict=attempt < self.retries)  # last: wherever
                model = DaskLGBMRegressor(client=ordered, time_out=self.time_out, **self._params(k))
                with warnings.catch_warnings():  # said on every fit: the workers' threads are their own
                    warnings.filterwarnings("ignore", message="Parameter n_jobs will be ignored")
                    model.fit(self.blocks.training_inputs(), self.blocks.labels(label))
                if ordered.misplaced or self.blocks.short:
                    self.unplaced.append(k)
                break
            except Exception as exc:  # a worker lost during LightGBM's collective training
                self.blocks.forget_inputs()  # the next try builds the training inputs afresh
                if self.client.status != "running":  # the scheduler itself is gone: nothing to retry on
                    raise OSError(f"no connection to the scheduler: {_one_line(exc)}") from exc
                if attempt == self.retries:
                    raise OfflineADPError(f"iteration {k} failed {attempt + 1} times on the Dask cluster: "
                                         f"{_one_line(exc)}") from exc
                self.retried += 1
                time.sleep(1.0)  # let the scheduler see a worker that went
        if self.warm_start:
            self.boosters.append(model.booster_)
            new = self._sum_predictions([model.booster_])
            self._cache = {name: self._cache[name] + new[name] for name in self.QUERIES}
        else:
            local = model.to_local()
            local.set_params(n_jobs=1)
            self.q = RegressorQ([local], self.encoder)
            self._cache = {}

    def _predict(self, model: Any, booster: bool) -> dict[str, np.ndarray]:
        """``model`` on every query set, one task per block on its worker."""
        m = self.client.scatter(model, broadcast=True, hash=False)
        got = self.client.gather(self.blocks.map(_predict_block, m, self.encoder, booster))
        out = {name: np.concatenate([g[name] for g in got]) for name in self.QUERIES}
        if self.n_start == 0:  # no start state in the data: the first row (as in-process)
            out["start"] = _predict_block(_query_block(self.start_obs), model, self.encoder, booster)["start"]
        return out

    def _sum_predictions(self, boosters: list[Any]) -> dict[str, np.ndarray]:
        """``sum_b b(X)`` over ``boosters`` for every query set, added in order (as cached in-process)."""
        A, n = self.encoder.n_actions, len(self.actions)
        total = {"train": np.zeros(n), "next": np.zeros((n, A)),
                 "start": np.zeros((self.n_start if self.n_start else len(self.start_obs), A))}
        for b in boosters:
            new = self._predict(b, booster=True)
            total = {name: total[name] + new[name] for name in self.QUERIES}
        return total

    def predict(self, name: str) -> np.ndarray:
        if not self._cache:  # refit: Q_k on every query set at once (the loop and its diagnostics read all)
            self._cache = self._predict(self.q.models[0], booster=False)
        return self._cache[name]

    def snapshot(self) -> QFunction:
        return BoostedSumQ(list(self.boosters), self.encoder) if self.warm_start else self.q

    def restore(self, q: QFunction, iteration: int, rows: list[dict[str, Any]] | None = None) -> None:
        if self.warm_start:
            self.boosters = [getattr(b, "booster", b) for b in q.boosters]  # type: ignore[attr-defined]
            self._cache = self._sum_predictions(self.boosters)
        else:
            self.q, self._cache = q, {}  # type: ignore[assignment]


class _OrderedClient:
    """A client for ``lightgbm.dask`` whose ``who_has`` lists the futures in the order
    given, part r held by ``where[r]`` alone. ``lightgbm.dask`` numbers its machines
    (ranks) in that order and trains part r on the first worker listed for it, and
    ``distributed.Client.who_has`` returns sets (whose order changes from run to run, and
    a part copied to a second worker has two holders), and with them which rows each rank
    holds and the trees. With this client, rank r is the worker of block r. A part not on
    its block's worker (a worker came or went) raises :class:`_Misplaced` before any
    training, and is retried; with ``strict=False`` (the last try) it trains where it is
    and ``misplaced`` says so."""

    def __init__(self, client: Any, where: list[str], strict: bool = True) -> None:
        self._client, self._where, self._strict = client, where, strict
        self.misplaced = False

    def __getattr__(self, name: str) -> Any:
        return getattr(self._client, name)

    def who_has(self, futures: Any = None, **kwargs: Any) -> dict[Any, Any]:
        got = self._client.who_has(futures, **kwargs)
        if futures is None:
            return got
        keys = list(dict.fromkeys(f.key for f in self._client.futures_of(futures)))
        placed = len(keys) == len(self._where) and all(w in got.get(k, ()) for k, w in zip(keys, self._where, strict=True))
        if placed:
            return {k: (w,) for k, w in zip(keys, self._where, strict=True)}
        if any(not got.get(k) for k in keys):
            raise _Misplaced(f"LightGBM parts held by no worker: {[k for k in keys if not got.get(k)]}")
        if self._strict:
            raise _Misplaced(f"LightGBM's parts are not on their blocks' workers: {[got.get(k) for k in keys]}")
        self.misplaced = True
        return {k: tuple(sorted(got[k])) for k in keys if k in got}


class _Misplaced(RuntimeError):
    """A LightGBM part on another worker than its block (retried after placing the blocks)."""


def _count_starts(block: dict[str, np.ndarray]) -> int:
    return len(block["start"])


def _query_block(x: np.ndarray) -> dict[str, np.ndarray]:
    """States ``x`` as a block whose ``start`` set they are (client-side predictions)."""
    return {"next": x[:0], "start": x, "start_pos": np.zeros(0, np.int64), "follows": np.zeros(0, bool),
            "action": np.zeros(0, np.int64), "X": np.zeros((0, x.shape[1]))}


def _ingest_file(path: str | list[str], spec: Any, fmt: str, on_error: str | None) -> tuple[Any, Any, Any]:
    """One file (MCAP: one recording, i.e. a file or the parts of a split recording) ->
    (dataset, doctor findings, quarantined rows or None) on a worker; nothing is written there."""
    if fmt == "parquet":
        from offline_adp.ingest.parquet import ingest_tables

        res = ingest_tables([path], spec, on_error=on_error)
        return res.dataset, res.report.findings.assign(file=str(path)), res.quarantine
    from offline_adp.ingest.mcap.build import ingest_mcap_tables

    parts = path if isinstance(path, list) else [path]
    ds, quarantine, summary = ingest_mcap_tables(parts, spec, on_error=on_error)
    return (ds, pd.DataFrame([{**{k: v for k, v in summary.items() if np.isscalar(v)}, "file": ", ".join(parts)}]),
            quarantine)


def ingest_distributed(client: Any, files: list[str | PathLike[str]], spec: Any, out: str | PathLike[str], *,
                       fmt: str = "parquet", on_error: str | None = None, overwrite: bool = False) -> tuple[Any, pd.DataFrame]:
    """Ingest many files in parallel on the workers (one task per file, the doctor run per
    file), then concatenate in the given file order and write one dataset (atomically).

    Returns the dataset and the merged per-file reports. ``spec`` is a parsed spec
    (:class:`~offline_adp.ingest.spec.ParquetSpec` or ``McapSpec``) or a spec file path.
    """
    from offline_adp.data.dataset import TransitionDataset
    from offline_adp.data.io import write_dataset

    if isinstance(spec, str | Path):
        if fmt == "parquet":
            from offline_adp.ingest.spec import load_parquet_spec

            spec = load_parquet_spec(spec)
        else:
            from offline_adp.ingest.mcap import load_mcap_spec

            spec = load_mcap_spec(spec)
    paths: list[Any] = [str(Path(f).resolve()) for f in files]
    if fmt == "mcap":  # the parts of a split recording stay together
        from offline_adp.ingest.mcap import resolve_sources

        paths = [[str(p) for p in rec] for rec in resolve_sources(paths, spec)]
    futures = client.map(_ingest_file, paths, spec=spec, fmt=fmt, on_error=on_error, pure=False)
    results = client.gather(futures)  # in file order: deterministic part order
    ds = TransitionDataset.concat([r[0] for r in results])
    quarantined = [r[2] for r in results if r[2] is not None and r[2].num_rows]
    import pyarrow as pa

    write_dataset(ds, out, overwrite=overwrite,
                  quarantine=pa.concat_tables(quarantined, promote_options="default") if quarantined else None)
    return ds, pd.concat([r[1] for r in results], ignore_index=True)


class DaskTaskMap:
    """A task map (:mod:`offline_adp.parallel`) on a Dask cluster: ``shared`` objects are
    broadcast to every worker once, each item is one task, results come back in item
    order (so the outcome does not depend on which worker ran what)."""

    def __init__(self, client: Any) -> None:
        self.client = client

    def __call__(self, fn: Any, items: Any, shared: dict[str, Any] | None = None, on_done: Any = None) -> list[Any]:
        from distributed import as_completed

        items = list(items)
        if not items:
            return []
        futures_shared = {k: self.client.scatter(v, broadcast=True, hash=False) for k, v in (shared or {}).items()}
        futures = self.client.map(fn, items, pure=False, **futures_shared)
        for k, _f in enumerate(as_completed(futures)):
            if on_done is not None:
                on_done(k)
        return self.client.gather(futures)
