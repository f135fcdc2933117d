"""The evaluation on Dask (issue #44): the main FQE fit, the cross-fitted FQE's folds, the
model rollouts and the density ratios as tasks on the workers (evaluation/batch.py); the
metrics equal the local evaluation's on one worker, and two runs on two workers agree."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("distributed")

from offline_adp.engines.dask import DaskTaskMap, EngineConfig, dask_client  # noqa: E402
from offline_adp.evaluation.run import evaluate_run  # noqa: E402
from offline_adp.runs import fit_run  # noqa: E402
from offline_adp.simulate import simulate  # noqa: E402

#: Small enough for a test, with every stage the batch runs: model rollouts, two folds,
#: the recursion, pooled, demonstrator and classifier ratios, 10 FQE replicates.
SETTINGS = {"episodes": 8, "bootstrap": 10, "fqe_bootstrap": 10, "model_particles": 20, "horizon": 15}


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    root = tmp_path_factory.mktemp("daskeval")
    simulate("car_on_hill", 0, 60, seed=3, horizon=100).save(root / "ds")
    fit_run(root / "ds", root / "run", params={"gamma": 0.95, "n_iterations": 3, "regressor_params": {"n_jobs": 1}})
    return root / "ds", root / "run"


def _evaluate(fitted, task_map=None, lines=None):
    ds, run = fitted
    evaluate_run(run, dataset=ds, task_map=task_map, progress=None if lines is None else lines.append, **SETTINGS)
    return json.loads((run / "evaluation" / "metrics.json").read_text())


def _on_cluster(fitted, n_workers):
    lines: list[str] = []
    cfg = EngineConfig(kind="dask", n_workers=n_workers, threads_per_worker=1, memory_limit="2GiB")
    with dask_client(cfg) as client:
        m = _evaluate(fitted, DaskTaskMap(client), lines)
    assert any(s.startswith("fits on the task map: fqe, fold 1, fold 2, model, self, pooled, ref:demonstrator, "
                            "classifier") for s in lines), lines
    return m


@pytest.mark.slow
def test_a_dask_evaluation_equals_the_local_one_and_is_reproducible(fitted):
    local = _evaluate(fitted)
    assert "estimate" in local["ope"]["fqe"]["model_rollouts"]  # the model rollouts ran (in the batch on Dask)
    assert _on_cluster(fitted, 1) == local  # metrics.json holds no timings
    two = _on_cluster(fitted, 2)
    assert _on_cluster(fitted, 2) == two
    assert two == local  # no seed depends on where a task ran


def test_the_batch_on_the_local_task_map_equals_the_stages_inline(fitted):
    """The batch path (any task map; here the plain loop) gives the inline path's numbers."""
    from offline_adp.parallel import local_map

    assert _evaluate(fitted, local_map) == _evaluate(fitted)


def test_a_fitted_frozen_fqe_pickles_with_the_standard_pickle(fitted):
    """Dask sends a task's result with pickle (arrays out of band) unless it fails; then
    cloudpickle copies every array into its stream (a 1M-row FQE: 2.5 -> 7.9 GiB)."""
    import pickle

    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.data.dataset import read_dataset
    from offline_adp.policies import UniformPolicy

    ds = read_dataset(fitted[0])
    fqe = FittedQEvaluation(policy=UniformPolicy(ds.n_actions), gamma=0.95, mode="frozen", n_iterations=4,
                            regressor_params={"n_estimators": 3}).fit(ds)
    back = pickle.loads(pickle.dumps(fqe, protocol=5))
    x = ds.arrays().obs[:50]
    assert (back.q_function_.values(x, 0) == fqe.q_function_.values(x, 0)).all()
