"""Scale-out on Dask (``pip install offline-adp[dask]``): distributed ingestion, FQI and
FQE (LightGBM trained by ``lightgbm.dask``, or the default frozen extra-trees mode), and
task maps for evaluation. Single-process stays the default.

The modules: :mod:`~offline_adp.engines.dask.cluster` (the client, ``[engine]``
settings, task maps), :mod:`~offline_adp.engines.dask.ingest` (one ingestion task per
file), :mod:`~offline_adp.engines.dask.blocks` (the dataset's rows placed on the
workers), :mod:`~offline_adp.engines.dask.learner` (LEARN with ``lightgbm.dask``),
:mod:`~offline_adp.engines.dask.frozen` (the frozen-structure LEARN: trees grown and leaf
values averaged on the workers) and :mod:`~offline_adp.engines.dask.fqi`
(:class:`DistributedFQI`, and :class:`DaskFit`, the engine of the run writer
:func:`offline_adp.runs.fit_run`). What scales: the regression (data-parallel LightGBM;
extra-trees split by tree over the workers), the leaf lookups and the predictions over
every block; the targets are O(n) vector arithmetic on the client. Checkpoints are
written and read by the one codec, :mod:`offline_adp.algorithms.checkpoint`.
"""

from offline_adp.engines.dask.cluster import (
    LOST_WORKER_TIMEOUT_S,
    DaskTaskMap,
    EngineConfig,
    dask_client,
    flat_columns,
    read_dataset_dask,
)
from offline_adp.engines.dask.fqi import DaskFit, DistributedFQI
from offline_adp.engines.dask.frozen import DaskFrozenLearner
from offline_adp.engines.dask.ingest import ingest_distributed
from offline_adp.engines.dask.learner import DaskLearner

__all__ = ["LOST_WORKER_TIMEOUT_S", "DaskFit", "DaskFrozenLearner", "DaskLearner", "DaskTaskMap", "DistributedFQI",
           "EngineConfig",
           "dask_client", "flat_columns", "ingest_distributed", "read_dataset_dask"]
