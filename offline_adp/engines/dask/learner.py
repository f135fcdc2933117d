"""LEARN on the cluster: LightGBM trained data-parallel by ``lightgbm.dask`` over the
blocks, predictions per block on their workers (:class:`DaskLearner`)."""

from __future__ import annotations

import time
import warnings
from typing import Any

import numpy as np

from offline_adp.engines.dask.blocks import _Blocks, _count_starts, _predict_block, _query_block
from offline_adp.engines.dask.cluster import _one_line
from offline_adp.errors import ClusterError
from offline_adp.learn import Learner, LearnSpec, LightGBMWarmStartLearner
from offline_adp.qfunctions import BoostedSumQ, QFunction, RegressorQ


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
        self.client, self.blocks, self.warm_start, self.trees_per_iteration = (
            client,
            blocks,
            warm_start,
            trees_per_iteration,
        )
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
                # last: wherever
                ordered = _OrderedClient(self.client, self.blocks.where, strict=attempt < self.retries)
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
                    raise ClusterError(f"iteration {k} failed {attempt + 1} times on the Dask cluster: "
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
        placed = len(keys) == len(self._where) and all(w in got.get(k,
                                                                    ()) for k, w in zip(keys, self._where, strict=True))
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

