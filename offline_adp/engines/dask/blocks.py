"""The dataset's rows as blocks on the workers (block ``i`` on the ``i``-th worker) and
the per-block work of :class:`~offline_adp.engines.dask.learner.DaskLearner`."""

from __future__ import annotations

import contextlib
import operator
import time
from typing import Any

import numpy as np

from offline_adp.errors import ClusterError
from offline_adp.qfunctions import predict_model


def scheduler_workers(client: Any) -> dict[str, Any]:
    """The scheduler's workers now, asked directly (``scheduler.identity``). Not
    ``Client.scheduler_info()``: it returns the client's cached identity, which the client's
    own periodic refresh may replace, between the fetch and the read, with one that carries
    cluster totals only and no workers (a fit under load reported its live workers gone)."""
    return dict(client.sync(client.scheduler.identity, n_workers=-1).get("workers") or {})


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
            "first": obs[:1], "obs_min": obs.min(axis=0, keepdims=True), "obs_max": obs.max(axis=0, keepdims=True),
            "action": a, "cost": t.column(S.COST).to_numpy().astype(np.float64, copy=False),
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
            self.futures = [client.submit(_load_block, *c, *self.args, workers=[w], allow_other_workers=True,
                                          pure=False)
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
            info = scheduler_workers(self.client)
            workers = sorted(w for w, d in info.items() if d.get("status", "running") == "running")
            if len(workers) >= self.n_workers or len(workers) == self._gave_up_at:
                return workers
            if time.monotonic() >= deadline:
                if not workers:
                    raise ClusterError(f"no running Dask worker after waiting {self.wait_s:g} s (worker_wait_s)")
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
        return np.asarray(model.predict(X, raw_score=True, num_threads=1),
                          dtype=np.float64) if booster else predict_model(model, X)

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



def _count_starts(block: dict[str, np.ndarray]) -> int:
    return len(block["start"])


def _query_block(x: np.ndarray) -> dict[str, np.ndarray]:
    """States ``x`` as a block whose ``start`` set they are (client-side predictions)."""
    return {"next": x[:0], "start": x, "start_pos": np.zeros(0, np.int64), "follows": np.zeros(0, bool),
            "action": np.zeros(0, np.int64), "X": np.zeros((0, x.shape[1]))}

