"""Dask sessions: the extra's import check, ``[engine]`` settings, the client (a
LocalCluster on loopback or an existing scheduler), the dataset as a Dask DataFrame and a
task map for evaluation.

Pitfall (dask 2026.8): persisting the direct output of ``read_parquet(columns=...)``
breaks later computes; :func:`read_dataset_dask` inserts a ``map_partitions`` first.
"""

from __future__ import annotations

import contextlib
import functools
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any

from offline_adp.errors import ClusterError, DatasetNotFoundError, MissingExtraError


def _one_line(exc: BaseException, limit: int = 400) -> str:
    """An exception's text on one line (Dask's span lines and list every future), shortened."""
    text = " ".join(str(exc).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _require_dask() -> None:
    try:
        import dask  # noqa: F401
        import distributed  # noqa: F401
    except ImportError:
        raise MissingExtraError("the Dask engine needs the dask extra: pip install 'offline-adp[dask]'") from None


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
            raise ClusterError(f"cannot reach the Dask scheduler at {cfg.address}: {exc}") from None
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
        raise DatasetNotFoundError(f"{path}: no data parts (part-*.parquet); is it a dataset directory?")
    ddf = dd.read_parquet(parts, columns=columns, split_row_groups=False)
    # dask 2026.8: persisting read_parquet(columns=...) directly breaks later computes
    return ddf.map_partitions(lambda df: df.copy(), meta=ddf._meta)


def flat_columns(info: Any) -> dict[str, list[str]]:
    """Column names of observations and next observations in a dataset's Parquet parts."""
    from offline_adp.data import schema as S

    names = info.feature_names
    return {"obs": [f"{S.OBS_PREFIX}{n}" for n in names], "next_obs": [f"{S.NEXT_OBS_PREFIX}{n}" for n in names]}



def _on_worker(fn: Any, item: Any, **shared: Any) -> Any:
    """``fn(item, **shared)`` on a worker, without joblib's warning that a Dask worker (a
    daemon process) runs ``n_jobs`` estimators on one thread: a task uses its worker's
    thread, as intended (the results do not depend on ``n_jobs``)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Inside a Dask worker with daemon=True", category=UserWarning)
        return fn(item, **shared)


class DaskTaskMap:
    """A task map (:mod:`offline_adp.parallel`) on a Dask cluster: ``shared`` objects are
    broadcast to every worker once, each item is one task, results come back in item
    order (so the outcome does not depend on which worker ran what); each is fetched when its
    task ends and released on its worker."""

    def __init__(self, client: Any) -> None:
        self.client = client

    def __call__(self, fn: Any, items: Any, shared: dict[str, Any] | None = None, on_done: Any = None) -> list[Any]:
        from distributed import as_completed

        items = list(items)
        if not items:
            return []
        futures_shared = {k: self.client.scatter(v, broadcast=True, hash=False) for k, v in (shared or {}).items()}
        futures = self.client.map(functools.partial(_on_worker, fn), items, pure=False, **futures_shared)
        index = {f.key: i for i, f in enumerate(futures)}
        out: list[Any] = [None] * len(futures)
        # each result is fetched as its task ends and then released on the worker, so a large
        # one (a fitted FQE) does not stay in the worker's memory while it runs the next tasks
        for k, f in enumerate(as_completed(futures)):
            out[index[f.key]] = f.result()
            futures[index[f.key]] = None
            f.release()
            if on_done is not None:
                on_done(k)
        return out
