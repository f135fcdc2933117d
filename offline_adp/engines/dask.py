"""Scale-out on Dask (``pip install offline-adp[dask]``): data-parallel FQI targets and
distributed LightGBM (``lightgbm.dask``). Single-process stays the default.

What scales here: reading the dataset's Parquet parts as a Dask DataFrame (one partition
per part), the per-iteration targets ``y_i = c_i + gamma (1 - term_i) min_a' Q(x'_i, a')``
computed with ``map_partitions`` against the previous Q broadcast to every worker, and
the regression itself with ``DaskLGBMRegressor``. What does not: extra-trees (scikit-learn)
stay single-node.

Pitfall (dask 2026.8): persisting the direct output of ``read_parquet(columns=...)``
breaks later computes; :func:`read_dataset_dask` inserts a ``map_partitions`` first.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from offline_adp.errors import OfflineADPError


def _require_dask() -> None:
    try:
        import dask  # noqa: F401
        import distributed  # noqa: F401
    except ImportError:
        raise OfflineADPError("the Dask engine needs the dask extra: pip install 'offline-adp[dask]'") from None


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
    with LocalCluster(n_workers=cfg.n_workers, threads_per_worker=cfg.threads_per_worker, processes=True,
                      host="127.0.0.1", dashboard_address=":0" if cfg.dashboard else None,
                      memory_limit=cfg.memory_limit) as cluster, Client(cluster) as client:
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


def spread(client: Any, ddf: Any) -> Any:
    """Persist with at least one partition per worker and check every worker holds some
    (a dataset of one Parquet part would otherwise sit on a single worker)."""
    import dask.dataframe as dd
    from distributed import wait

    workers = sorted(client.scheduler_info()["workers"])
    if ddf.npartitions < len(workers):
        ddf = ddf.repartition(npartitions=len(workers))
    # partition i on worker i mod n, so every worker holds data (deterministic placement)
    # (a preference, not a restriction: if that worker dies, Dask recomputes the partition elsewhere)
    parts = [client.persist(ddf.partitions[i], workers=[workers[i % len(workers)]], allow_other_workers=True)
             for i in range(ddf.npartitions)]
    ddf = dd.concat(parts)
    wait(ddf)
    holders = {w for ws in client.who_has(ddf).values() for w in ws}
    if set(workers) - holders:
        raise OfflineADPError(f"workers {sorted(set(workers) - holders)} hold no data "
                              f"({ddf.npartitions} partitions); use fewer workers or more parts")
    return ddf


def _targets_partition(df: pd.DataFrame, q: Any, gamma: float, obs_cols: list[str], next_cols: list[str],
                       policy: Any = None) -> pd.Series:

    if not len(df):
        return pd.Series(np.zeros(0), index=df.index, dtype=np.float64)
    return _backup(df, q.values(df[next_cols].to_numpy(dtype=np.float64)), gamma, next_cols, policy)


def _backup(df: pd.DataFrame, qn: np.ndarray, gamma: float, next_cols: list[str], policy: Any) -> pd.Series:
    """``c + gamma (1 - term) v(x')`` with ``v`` = min_a' Q(x', a') (FQI) or the policy's
    average (FQE), given ``qn = Q(x', .)`` for the partition's rows."""
    from offline_adp.data import schema as S

    v = qn.min(axis=1) if policy is None else (policy.probabilities(df[next_cols].to_numpy(dtype=np.float64), 0) * qn).sum(axis=1)
    term = df[S.TERMINATED].to_numpy(dtype=bool)
    y = df[S.COST].to_numpy(dtype=np.float64) + gamma * np.where(term, 0.0, v)
    return pd.Series(y, index=df.index, dtype=np.float64)


def distributed_targets(client: Any, ddf: Any, q: Any, gamma: float, info: Any, policy: Any = None) -> Any:
    """``y_i = c_i + gamma (1 - term_i) min_a' Q(x'_i, a')`` per partition (with ``policy``:
    the FQE backup ``sum_a' pi(a'|x'_i) Q(x'_i, a')``); Q (and pi) broadcast once."""
    cols = flat_columns(info)
    q_future = client.scatter(q, broadcast=True, hash=False)
    p_future = client.scatter(policy, broadcast=True, hash=False) if policy is not None else None
    return ddf.map_partitions(_targets_partition, q_future, gamma, cols["obs"], cols["next_obs"], p_future,
                              meta=pd.Series(dtype=np.float64))


def _inputs_partition(df: pd.DataFrame, obs_cols: list[str], action_features: np.ndarray) -> pd.DataFrame:
    from offline_adp.data import schema as S

    a = df[S.ACTION].to_numpy(dtype=np.int64)
    X = np.hstack([df[obs_cols].to_numpy(dtype=np.float64), action_features[a]])
    return pd.DataFrame(X, index=df.index, columns=[f"x{j}" for j in range(X.shape[1])])


class DistributedFQI:
    """Fitted Q-iteration (Algorithm 11) with LightGBM trained by ``lightgbm.dask``.

    Per iteration: targets with :func:`distributed_targets` (previous Q broadcast), then
    ``DaskLGBMRegressor.fit`` on the joint inputs ``[x, action value]``; the fitted booster
    becomes the next Q (a :class:`~offline_adp.qfunctions.RegressorQ`).

    With ``warm_start=True`` (the FQI issue's warm-start mode, distributed): each
    iteration adds ``trees_per_iteration`` trees boosted from ``init_score = Q_{k-1}(x_i,
    a_i)``, so ``Q_k = Q_{k-1} + new trees`` (a :class:`~offline_adp.learners.BoostedSumQ`).
    Every partition keeps its rows' cached ``Q_{k-1}(x_i, a_i)`` and ``Q_{k-1}(x'_i, a')``
    next to the data on its worker; an iteration evaluates only the new trees there, so
    its cost does not grow with the number of iterations.

    Parameters
    ----------
    gamma : float, optional
        Default: the dataset's hint, else 0.95 (:func:`offline_adp.data.discount.resolve_discount`).
    n_iterations : int
    lgbm_params : dict
        LightGBM parameters (default: the ``lightgbm`` registry entry's).
    time_out : int
        Minutes LightGBM's Dask network setup may wait (so nothing hangs for hours).
    retries : int
        Times an iteration whose LightGBM training lost a worker is retried.
    random_state : int
    policy : Policy, optional
        Evaluate this policy (FQE backup) instead of the greedy one.
    warm_start : bool
        Boost each Q from the previous one (see above).
    trees_per_iteration : int
        New trees per iteration with ``warm_start``.
    """

    def __init__(self, gamma: float | None = None, n_iterations: int = 10, lgbm_params: dict | None = None,
                 time_out: int = 2, retries: int = 2, random_state: int = 0, policy: Any = None,
                 warm_start: bool = False, trees_per_iteration: int = 10) -> None:
        self.gamma, self.n_iterations, self.lgbm_params = gamma, n_iterations, lgbm_params
        self.time_out, self.retries, self.random_state, self.policy = time_out, retries, random_state, policy
        self.warm_start, self.trees_per_iteration = warm_start, trees_per_iteration

    def fit(self, client: Any, dataset_dir: str | PathLike[str], on_iteration: Any = None,
            checkpoint_dir: str | PathLike[str] | None = None) -> DistributedFQI:
        """Fit on a dataset directory; ``on_iteration(k)`` is called after iteration k.

        Tasks lost with a worker are recomputed by Dask; a LightGBM training that fails
        because a worker vanished mid-way is retried (``retries`` times) on the workers
        left, from the same Q: the iteration's inputs do not depend on which worker ran it.
        With ``checkpoint_dir`` the Q of every completed iteration is written there
        (atomically) and a later ``fit`` continues from it, e.g. after the scheduler was
        lost. With ``policy`` this is fitted Q *evaluation* of that policy (Algorithm 13).
        """
        try:
            with client.as_current():  # every compute goes to this client, even when others exist
                return self._fit(client, dataset_dir, on_iteration, checkpoint_dir)
        except (OSError, TimeoutError) as exc:  # CommClosedError is an OSError
            where = f"; re-run to continue from the checkpoint in {checkpoint_dir}" if checkpoint_dir else ""
            raise OfflineADPError(f"lost the Dask cluster during fitted Q-iteration ({type(exc).__name__}: {exc}){where}") from exc

    def _fit(self, client: Any, dataset_dir: str | PathLike[str], on_iteration: Any,
             checkpoint_dir: str | PathLike[str] | None) -> DistributedFQI:
        from lightgbm.dask import DaskLGBMRegressor

        from offline_adp.data.discount import resolve_discount
        from offline_adp.data.info import DatasetInfo
        from offline_adp.qfunctions import QEncoder, RegressorQ

        info = DatasetInfo.from_dict(json.loads((Path(dataset_dir) / "meta" / "info.json").read_text()))
        self.gamma_ = resolve_discount(info, self.gamma).gamma  # the package's one rule (no finite horizon here)
        ddf = spread(client, read_dataset_dask(dataset_dir))
        cols = flat_columns(info)
        af = np.asarray(info.action_table.values, dtype=np.float64)
        enc = QEncoder(len(af), af)
        meta = pd.DataFrame({f"x{j}": pd.Series(dtype=np.float64) for j in range(len(cols["obs"]) + af.shape[1])})
        X = ddf.map_partitions(_inputs_partition, cols["obs"], af, meta=meta)
        Xa = X.to_dask_array(lengths=True).persist()
        q: Any = _ZeroQ(len(af))
        self.history_ = []
        start = 0
        ck = Path(checkpoint_dir) if checkpoint_dir is not None else None
        if ck is not None and (ck / "q.json").exists():
            from offline_adp.artifacts import load_q

            q, meta_ck = load_q(ck)
            start = int(meta_ck["iteration"])
            self.history_ = pd.read_csv(ck / "history.csv").to_dict("records")
        params = {"n_estimators": 100, "num_leaves": 31, "learning_rate": 0.1, "verbose": -1, **(self.lgbm_params or {})}
        params.pop("n_jobs", None)  # workers decide their threads
        if self.warm_start:
            params["n_estimators"] = self.trees_per_iteration
            boosters = [getattr(b, "booster", b) for b in getattr(q, "boosters", [])]
            ddf = self._cache(client, ddf, boosters, cols, af, fresh=True)
        self.retried_ = 0
        for k in range(start, self.n_iterations):
            t0 = time.perf_counter()
            for attempt in range(self.retries + 1):
                try:
                    if self.warm_start:
                        y = ddf.map_partitions(_cached_targets, self.gamma_, len(af), cols["next_obs"],
                                               client.scatter(self.policy, broadcast=True, hash=False)
                                               if self.policy is not None else None, meta=pd.Series(dtype=np.float64))
                        # the residual y - Q_{k-1}(x_i, a_i), boosted from its mean (as the local warm start)
                        y = y - ddf[_CACHE_SA]
                        init = {}
                    else:
                        y = distributed_targets(client, ddf, q, self.gamma_, info, self.policy)
                        init = {}
                    model = DaskLGBMRegressor(client=client, time_out=self.time_out,
                                              random_state=self.random_state + (k if self.warm_start else 0), **params)
                    # arrays: the local booster then predicts on numpy without feature-name warnings
                    model.fit(Xa, y.to_dask_array(lengths=True), **init)
                    break
                except Exception as exc:  # a worker lost during LightGBM's collective training
                    if client.status != "running":  # the scheduler itself is gone: nothing to retry on
                        raise OSError(f"no connection to the scheduler: {exc}") from exc
                    if attempt == self.retries:
                        raise OfflineADPError(f"iteration {k + 1} failed {attempt + 1} times on the Dask cluster: {exc}") from exc
                    self.retried_ += 1
                    ddf = spread(client, read_dataset_dask(dataset_dir))
                    Xa = ddf.map_partitions(_inputs_partition, cols["obs"], af, meta=meta).to_dask_array(lengths=True).persist()
                    if self.warm_start:
                        ddf = self._cache(client, ddf, boosters, cols, af, fresh=True)
            if self.warm_start:
                from offline_adp.learners import BoostedSumQ

                boosters.append(model.booster_)
                ddf = self._cache(client, ddf, [model.booster_], cols, af)
                q = BoostedSumQ(list(boosters), enc)
            else:
                local = model.to_local()
                local.set_params(n_jobs=1)
                q = RegressorQ([local], enc)
            self.history_.append({"iteration": k + 1, "wall_time": time.perf_counter() - t0})
            if ck is not None:
                from offline_adp.artifacts import save_q
                from offline_adp.data.io import atomic_directory

                with atomic_directory(ck, overwrite=True) as tmp:
                    save_q(q, tmp, extra={"iteration": k + 1})
                    pd.DataFrame(self.history_).to_csv(tmp / "history.csv", index=False)
            if on_iteration is not None:
                on_iteration(k + 1)
        self.q_function_ = q
        return self


    @staticmethod
    def _cache(client: Any, ddf: Any, boosters: list[Any], cols: dict[str, list[str]], af: np.ndarray,
               fresh: bool = False) -> Any:
        """Add the predictions of ``boosters`` to each partition's cached Q columns (``fresh``:
        start the cache at 0), persisted where the partitions are."""
        from distributed import wait

        b = client.scatter([list(boosters)], broadcast=True, hash=False)[0]  # one future holding the list
        meta = ddf._meta if not fresh else _add_predictions(ddf._meta, [], cols["obs"], cols["next_obs"], af, True)
        out = ddf.map_partitions(_add_predictions, b, cols["obs"], cols["next_obs"], af, fresh, meta=meta).persist()
        wait(out)
        return out


_CACHE_SA = "_q_sa"


def _cache_next(j: int) -> str:
    return f"_q_next{j}"


def _add_predictions(df: pd.DataFrame, boosters: list[Any], obs_cols: list[str], next_cols: list[str], af: np.ndarray,
                     fresh: bool) -> pd.DataFrame:
    """``df`` with its cached ``Q(x_i, a_i)`` and ``Q(x'_i, a')`` columns increased by the
    boosters' raw predictions (single-threaded: a worker's thread budget is its own)."""
    from offline_adp.data import schema as S

    df = df.copy()
    A = len(af)
    if fresh:
        df[_CACHE_SA] = 0.0
        for j in range(A):
            df[_cache_next(j)] = 0.0
    if not len(df) or not boosters:
        return df
    x = df[obs_cols].to_numpy(dtype=np.float64)
    nxt = df[next_cols].to_numpy(dtype=np.float64)
    a = df[S.ACTION].to_numpy(dtype=np.int64)
    for bst in boosters:
        df[_CACHE_SA] += bst.predict(np.hstack([x, af[a]]), raw_score=True, num_threads=1)
        for j in range(A):
            xa = np.hstack([nxt, np.broadcast_to(af[j], (len(nxt), af.shape[1]))])
            df[_cache_next(j)] += bst.predict(xa, raw_score=True, num_threads=1)
    return df


def _cached_targets(df: pd.DataFrame, gamma: float, n_actions: int, next_cols: list[str], policy: Any) -> pd.Series:
    """Targets from the cached ``Q_{k-1}(x'_i, a')`` (min over a', or the policy's average)."""
    if not len(df):
        return pd.Series(np.zeros(0), index=df.index, dtype=np.float64)
    return _backup(df, df[[_cache_next(j) for j in range(n_actions)]].to_numpy(dtype=np.float64), gamma, next_cols, policy)


class _ZeroQ:
    """Q_0 = 0."""

    def __init__(self, n_actions: int) -> None:
        self.n_actions = n_actions

    def values(self, obs: np.ndarray, t: Any = 0) -> np.ndarray:
        return np.zeros((len(obs), self.n_actions))


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
