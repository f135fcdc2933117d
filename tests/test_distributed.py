"""Dask engine on a LocalCluster (2 worker processes x 1 thread, loopback)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("distributed")
pytest.importorskip("dask.dataframe")

from offline_adp.algorithms.fqi import FittedQIteration  # noqa: E402
from offline_adp.data import schema as S  # noqa: E402
from offline_adp.engines.dask import (  # noqa: E402
    LOST_WORKER_TIMEOUT_S,
    DistributedFQI,
    EngineConfig,
    dask_client,
    read_dataset_dask,
)
from offline_adp.simulate import simulate  # noqa: E402


@pytest.fixture(scope="module")
def client():
    with dask_client(EngineConfig(kind="dask", n_workers=2, threads_per_worker=1, memory_limit="2GiB")) as c:
        yield c


@pytest.fixture(scope="module")
def coh(tmp_path_factory):
    ds = simulate("car_on_hill", 0, 150, seed=3, horizon=100)
    path = tmp_path_factory.mktemp("coh") / "ds"
    ds.save(path)
    return ds, path


def test_read_parquet_columns_then_persist_still_computes(client, coh):
    """The dask 2026.8 pitfall: read_parquet(columns=...) persisted directly breaks later computes."""
    ds, path = coh
    ddf = read_dataset_dask(path, columns=[S.COST, S.TERMINATED]).persist()
    assert float(ddf[S.COST].sum().compute()) == pytest.approx(float(ds.arrays().cost.sum()))
    assert len(ddf.compute()) == len(ds)


@pytest.fixture(scope="module")
def one_worker():
    with dask_client(EngineConfig(kind="dask", n_workers=1, threads_per_worker=1, memory_limit="2GiB")) as c:
        yield c


def _same_fit(a, b, x):
    """Equal Q on the states ``x`` and equal per-iteration diagnostics (not the clocks)."""
    np.testing.assert_array_equal(a.q_function_.values(x), b.q_function_.values(x))
    cols = ["iteration", "sup_dq", "mean_dq", "max_abs_q", "bellman_residual", "greedy_changed", "start_value"]
    ha, hb = (np.asarray(h.history_[cols], dtype=float) for h in (a, b))
    np.testing.assert_allclose(ha, hb, rtol=1e-12, atol=1e-12)  # reductions may sum in another order
    assert a.verdict_ == b.verdict_


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["refit", "warm_start", "fqe"])
def test_dask_fit_equals_the_in_process_fit_of_its_estimator(one_worker, coh, tmp_path, kind):
    """The oracle: on one worker (LightGBM then trains on one machine, as in-process) the
    Dask fit runs the same loop with the same targets, seeds and trees, so Q, the history
    and the verdict equal :meth:`DistributedFQI.estimator`'s in-process fit; a fit stopped
    after 2 iterations and resumed from its checkpoint gives that Q too."""
    from offline_adp.data.dataset import read_dataset
    from offline_adp.policies import UniformPolicy

    _, path = coh
    ds = read_dataset(path)
    params = {"n_estimators": 20, "num_leaves": 15, "n_jobs": 1}  # one LightGBM thread in-process, as on the worker
    kw = {"gamma": 0.95, "lgbm_params": params, "random_state": 4, "warm_start": kind == "warm_start",
          "policy": UniformPolicy(2) if kind == "fqe" else None}
    dist = DistributedFQI(n_iterations=4, **kw).fit(one_worker, path)
    local = dist.estimator().fit(ds)
    assert type(local).__name__ == ("FittedQEvaluation" if kind == "fqe" else "FittedQIteration")
    x = ds.arrays().obs
    _same_fit(dist, local, x)
    if kind == "fqe":
        assert dist.value_ == pytest.approx(local.value_, rel=1e-12)
    ck = tmp_path / "ck"
    DistributedFQI(n_iterations=2, **kw).fit(one_worker, path, checkpoint_dir=ck)
    seen: list[int] = []
    resumed = DistributedFQI(n_iterations=4, **kw).fit(one_worker, path, checkpoint_dir=ck, on_iteration=seen.append)
    assert seen == [3, 4]
    _same_fit(resumed, local, x)


def test_dask_finite_horizon_fit_equals_the_in_process_fit(one_worker, tmp_path):
    """gamma = 1 on a dataset with a 5-step horizon hint is Algorithm 10 (one Q per step):
    the same generic loop, so the Dask fit equals the in-process one step by step, and a
    checkpoint of the finished fit (a TimeIndexedQ) gives it back without refitting."""
    from offline_adp.data.dataset import read_dataset

    simulate("car_on_hill", 0, 60, seed=5, horizon=5).save(tmp_path / "ds")
    ds = read_dataset(tmp_path / "ds")
    kw = {"gamma": 1.0, "lgbm_params": {"n_estimators": 10, "num_leaves": 7, "n_jobs": 1}}
    dist = DistributedFQI(**kw).fit(one_worker, tmp_path / "ds", checkpoint_dir=tmp_path / "ck")
    local = dist.estimator().fit(ds)
    assert dist.estimator_.horizon_ == local.horizon_ == 5 and len(dist.history_) == 5
    x = ds.arrays().obs
    for t in range(5):
        np.testing.assert_array_equal(dist.q_function_.values(x, t), local.q_function_.values(x, t))
    seen: list[int] = []
    again = DistributedFQI(**kw).fit(one_worker, tmp_path / "ds", checkpoint_dir=tmp_path / "ck",
                                     on_iteration=seen.append)
    assert seen == []
    np.testing.assert_array_equal(again.q_function_.values(x, 2), local.q_function_.values(x, 2))


def test_two_distributed_iterations_agree_with_single_process(client, coh):
    ds, path = coh
    params = {"n_estimators": 50, "num_leaves": 15, "min_child_samples": 20}
    dist = DistributedFQI(gamma=0.95, n_iterations=2, lgbm_params=params).fit(client, path)
    local = FittedQIteration(gamma=0.95, regressor="lightgbm", regressor_params=params, n_iterations=2).fit(ds)
    x = ds.arrays().obs
    qd, ql = dist.q_function_.values(x), local.q_function_.values(x)
    assert np.corrcoef(qd.ravel(), ql.ravel())[0, 1] > 0.98


def test_a_worker_killed_mid_fit_does_not_stop_it(client, coh):
    """Kill one worker process after iteration 1: the nanny restarts it empty, the rows go
    back to their places (block i on the i-th worker) and the fit completes with the Q of
    an undisturbed fit."""
    import os

    ds, path = coh
    params = {"n_estimators": 50, "num_leaves": 15, "min_child_samples": 20}
    undisturbed = DistributedFQI(gamma=0.95, n_iterations=3, lgbm_params=params).fit(client, path)

    killed: list[str] = []

    def kill_one(k):
        if k == 1:
            victim = sorted(client.scheduler_info()["workers"])[0]
            try:  # the worker dies before it can answer
                client.run(os._exit, 1, workers=[victim])
            except Exception:
                pass
            killed.append(victim)

    # wait for the restart as long as the local cluster keeps the killed worker's nanny (a busy machine is slow)
    est = DistributedFQI(gamma=0.95, n_iterations=3, lgbm_params=params, worker_wait_s=LOST_WORKER_TIMEOUT_S).fit(
        client, path, on_iteration=kill_one)
    assert len(est.history_) == 3 and killed
    assert killed[0] not in client.scheduler_info()["workers"]  # the process really went away
    assert est.unplaced_iterations_ == []  # the restarted worker was back in time: every block on its worker
    x = ds.arrays().obs
    np.testing.assert_array_equal(est.q_function_.values(x), undisturbed.q_function_.values(x))
    client.wait_for_workers(2, timeout=60)


@pytest.mark.parametrize("bad", [-1, float("inf"), "60", True])
def test_a_bad_worker_wait_is_refused_before_anything_runs(client, coh, bad):
    _, path = coh
    with pytest.raises(ValueError, match="worker_wait_s must be a number of seconds"):
        DistributedFQI(gamma=0.95, n_iterations=1, worker_wait_s=bad).fit(client, path)


def test_a_worker_added_mid_fit_does_not_change_the_ranks(coh, tmp_path):
    """A fit started on one worker over two blocks (two Parquet parts), with a second worker
    joining after iteration 1: the blocks stay on as many workers as at the start (one
    LightGBM rank), so the Q is still the in-process fit's (the oracle) and no iteration
    is reported as unplaced. Spreading the blocks over the new worker would make two ranks."""
    import time

    from offline_adp.data.dataset import read_dataset

    ds, _ = coh
    path = tmp_path / "two_parts"
    ds.save(path, rows_per_part=len(ds) // 2 + 1)
    assert len(list((path / "data").glob("*.parquet"))) == 2
    params = {"n_estimators": 20, "num_leaves": 15, "n_jobs": 1}
    kw = {"gamma": 0.95, "lgbm_params": params, "random_state": 4, "n_iterations": 3}
    with dask_client(EngineConfig(kind="dask", n_workers=1, threads_per_worker=1, memory_limit="2GiB")) as c:
        def grow(k):
            if k == 1:
                c.cluster.scale(2)
                deadline = time.monotonic() + 120
                while len(c.scheduler_info()["workers"]) < 2 and time.monotonic() < deadline:
                    time.sleep(0.1)
                assert len(c.scheduler_info()["workers"]) == 2

        est = DistributedFQI(**kw).fit(c, path, on_iteration=grow)
    assert est.unplaced_iterations_ == []
    local = est.estimator().fit(read_dataset(path))
    _same_fit(est, local, ds.arrays().obs)


def test_a_worker_that_does_not_come_back_is_reported(coh):
    """A worker removed for good after iteration 1: after ``worker_wait_s`` the fit goes on
    with both blocks on the remaining worker, lists iterations 2 and 3 as trained away from
    their placement and warns that the Q may differ from an undisturbed fit's."""
    import time

    from offline_adp.errors import ClusterWarning

    ds, path = coh
    params = {"n_estimators": 20, "num_leaves": 15, "min_child_samples": 20}
    with dask_client(EngineConfig(kind="dask", n_workers=2, threads_per_worker=1, memory_limit="2GiB")) as c:
        undisturbed = DistributedFQI(gamma=0.95, n_iterations=3, lgbm_params=params).fit(c, path)
        assert undisturbed.unplaced_iterations_ == []

        def shrink(k):
            if k == 1:
                c.cluster.scale(1)  # the second worker is closed for good, not restarted
                deadline = time.monotonic() + 60
                while len(c.scheduler_info()["workers"]) > 1 and time.monotonic() < deadline:
                    time.sleep(0.1)

        with pytest.warns(ClusterWarning, match=r"iterations \[2, 3\]"):
            est = DistributedFQI(gamma=0.95, n_iterations=3, lgbm_params=params, worker_wait_s=1).fit(
                c, path, on_iteration=shrink)
        assert len(c.scheduler_info()["workers"]) == 1
    assert est.unplaced_iterations_ == [2, 3] and len(est.history_) == 3
    x = ds.arrays().obs
    qa, qb = est.q_function_.values(x), undisturbed.q_function_.values(x)
    cols = ["sup_dq", "mean_dq", "max_abs_q", "bellman_residual"]  # iteration 1 ran on both workers, undisturbed
    np.testing.assert_allclose(est.history_[cols].to_numpy()[0], undisturbed.history_[cols].to_numpy()[0], rtol=1e-12)
    assert np.corrcoef(qa.ravel(), qb.ravel())[0, 1] > 0.98  # the same problem, learnt on one machine from iteration 2


def test_distributed_ingestion_of_four_files_equals_local(client, tmp_path):
    from offline_adp.engines.dask import ingest_distributed
    from offline_adp.envs import make_problem
    from offline_adp.ingest.parquet import ingest_parquet
    from offline_adp.simulate import collect
    from offline_adp.simulate.raw import write_raw

    prob = make_problem("path_tracking")
    files = []
    for k in range(4):
        ds = collect(prob, prob.demonstrator(), 3, np.random.default_rng(k), horizon=30, episode_prefix=f"car{k}",
                     source="demonstration")
        path, spec = write_raw(ds, tmp_path / f"log{k}.parquet")
        files.append(path)
    local = ingest_parquet(files, spec, tmp_path / "local").dataset
    dist, reports = ingest_distributed(client, files, spec, tmp_path / "dist")
    assert dist.fingerprint() == local.fingerprint()
    assert list(dist.episode_ids) == list(local.episode_ids)
    assert (tmp_path / "dist" / "meta" / "info.json").exists() and reports.empty  # the doctor found nothing
    import pandas as pd

    from offline_adp.errors import LogWarning

    copy = pd.read_parquet(files[0])  # a file copied under new ids: a repeat across files, seen on the client
    copy["episode"] = "copy-" + copy["episode"].astype(str)
    copy.to_parquet(tmp_path / "copy.parquet")
    with pytest.warns(LogWarning, match="3 of 15 episodes repeat an earlier episode row for row"):
        ingest_distributed(client, [*files, tmp_path / "copy.parquet"], spec, tmp_path / "dist2")


def test_pipeline_with_dask_engine_matches_local(tmp_path):
    """`run --engine dask`: the data stage runs per file on the workers, the default fit
    (frozen extra-trees) on the cluster (run.json and the manifest say dask); the metrics
    equal the local run's."""
    import json

    from offline_adp.pipeline import run_pipeline
    from tests.test_pipeline import PIPELINES, SMALL, quiet

    small = {**SMALL["driving"], "evaluate.episodes": 10, "evaluate.bootstrap": 10, "evaluate.horizon": 10,
             "fit.params.n_iterations": 5}
    local = run_pipeline(PIPELINES / "driving.toml", out=tmp_path / "local", say=quiet, overrides=small)
    lines: list[str] = []
    dist = run_pipeline(PIPELINES / "driving.toml", out=tmp_path / "dask", say=lines.append, overrides=small,
                        engine={"kind": "dask", "n_workers": 2, "threads_per_worker": 1, "memory_limit": "2GiB"})
    stages = json.loads((dist / "manifest.json").read_text())["stages"]
    assert stages["data"]["engine"] == "dask" and stages["fit"]["engine"] == "dask"
    assert json.loads((dist / "fit" / "run.json").read_text())["engine"] == "dask"
    assert not any("client process" in s for s in lines)
    a, b = (json.loads((r / "metrics.json").read_text()) for r in (local, dist))
    for m in (a, b):
        m["dataset"].pop("path")
    assert a == b
    assert sorted(p.name for p in (dist / "figures").iterdir()) == sorted(p.name for p in (local / "figures").iterdir())


def test_checkpointed_distributed_fit_resumes(client, coh, tmp_path):
    """A fit stopped after 2 iterations continues from its checkpoint to 3 without redoing
    them, to the Q of an uninterrupted 3-iteration fit on two workers."""
    ds, path = coh
    params = {"n_estimators": 20, "num_leaves": 15}
    DistributedFQI(gamma=0.95, n_iterations=2, lgbm_params=params).fit(client, path, checkpoint_dir=tmp_path / "ck")
    seen: list[int] = []
    est = DistributedFQI(gamma=0.95, n_iterations=3,
                         lgbm_params=params).fit(client, path, checkpoint_dir=tmp_path / "ck",
                                                                           on_iteration=seen.append)
    assert seen == [3] and est.history_["iteration"].tolist() == [1, 2, 3]
    whole = DistributedFQI(gamma=0.95, n_iterations=3, lgbm_params=params).fit(client, path)
    x = ds.arrays().obs
    np.testing.assert_array_equal(est.q_function_.values(x), whole.q_function_.values(x))
    assert est.verdict_ == whole.verdict_
    # killed after the last checkpoint, before the caller saved the model: nothing is redone
    again: list[int] = []
    done = DistributedFQI(gamma=0.95, n_iterations=3,
                          lgbm_params=params).fit(client, path, checkpoint_dir=tmp_path / "ck",
                                                                            on_iteration=again.append)
    assert again == [] and done.history_["iteration"].tolist() == [1, 2, 3] and done.verdict_ == whole.verdict_
    np.testing.assert_array_equal(done.q_function_.values(x), whole.q_function_.values(x))


def test_distributed_fqe_of_a_fixed_policy_matches_local(client, coh):
    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.policies import UniformPolicy

    ds, path = coh
    params = {"n_estimators": 50, "num_leaves": 15, "min_child_samples": 20}
    pi = UniformPolicy(ds.n_actions)
    dist = DistributedFQI(gamma=0.95, n_iterations=3, lgbm_params=params, policy=pi).fit(client, path)
    local = FittedQEvaluation(policy=pi, gamma=0.95, regressor="lightgbm", regressor_params=params,
                              n_iterations=3).fit(ds)
    x = ds.arrays().obs
    assert np.corrcoef(dist.q_function_.values(x).ravel(), local.q_function_.values(x).ravel())[0, 1] > 0.98


def test_pipeline_fit_on_dask_with_lightgbm(tmp_path):
    import json

    from offline_adp.pipeline import run_pipeline
    from tests.test_pipeline import PIPELINES, quiet

    over = {"data.exploration": 40, "fit.params": {"regressor": "lightgbm", "n_iterations": 3,
                                                   "regressor_params": {"n_estimators": 20}},
            "evaluate.episodes": 20, "evaluate.bootstrap": 10, "evaluate.fqe_bootstrap": 0, "evaluate.horizon": 20,
            "evaluate.fqe_params": {"n_iterations": 5}}
    run = run_pipeline(PIPELINES / "car_on_hill.toml", out=tmp_path / "r", say=quiet, overrides=over,
                       engine={"kind": "dask", "n_workers": 2, "threads_per_worker": 1, "memory_limit": "2GiB"})
    st = json.loads((run / "manifest.json").read_text())["stages"]
    assert st["fit"]["engine"] == "dask" and st["fit"]["iterations"] == 3
    assert st["fit"]["verdict"] == "still changing"  # 3 iterations, no tol: the in-process verdict rule
    q_meta = json.loads((run / "fit" / "model" / "q.json").read_text())
    assert q_meta["verdict"] == "still changing"
    # every block trained on its own worker: recorded as such, in the manifest and in the run's run.json
    status = json.loads((run / "fit" / "run.json").read_text())
    assert st["fit"]["unplaced_iterations"] == [] and status["unplaced_iterations"] == [] and status["engine"] == "dask"
    assert (run / "report.html").exists()


def test_rollouts_and_fqe_replicates_on_workers_equal_local(client, coh):
    """Distributed evaluation: rollout pieces and FQE bootstrap replicates run on the
    workers give exactly the local results (the split and seeds do not depend on the engine)."""
    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.engines.dask import DaskTaskMap
    from offline_adp.envs import make_problem
    from offline_adp.evaluation import ope
    from offline_adp.evaluation.fqe_interval import REPLICATE_RTOL, _reweighted_replicate
    from offline_adp.policies import UniformPolicy
    from offline_adp.rollout import rollout, rollout_pieces

    ds, _ = coh
    problem = make_problem("car_on_hill")
    fqi = FittedQIteration(gamma=0.95, regressor="extra_trees", regressor_params={"n_estimators": 5}, mode="frozen",
                           n_iterations=5, random_state=0).fit(ds)
    policies = {"policy": fqi.policy_, "uniform": UniformPolicy(2)}
    x0 = problem.initial_states(60, np.random.default_rng(0))
    kw = {"horizon": 50, "gamma": 0.95, "record_states": True}
    local = rollout_pieces(problem, policies, x0, 7, **kw)
    dist = rollout_pieces(problem, policies, x0, 7, task_map=DaskTaskMap(client), **kw)
    for name in policies:
        np.testing.assert_array_equal(dist[name].discounted_cost, local[name].discounted_cost)
        assert all(np.array_equal(a, b) for a, b in zip(dist[name].states, local[name].states, strict=True))
    one = rollout_pieces(problem, policies, x0, 7, n_pieces=1, **kw)["policy"]  # one piece = one plain rollout
    plain = rollout(problem, fqi.policy_, 60, np.random.default_rng([7, 0]), start_states=x0, **kw)
    np.testing.assert_array_equal(one.discounted_cost, plain.discounted_cost)

    fqe = FittedQEvaluation(policy=UniformPolicy(2), gamma=0.95, regressor="extra_trees", mode="frozen",
                            regressor_params={"n_estimators": 5}, n_iterations=20, random_state=0).fit(ds)
    em = ope.EpisodeMatrix.build(ds.arrays().episode, ds.arrays().step, 100)
    counts = ope.bootstrap_counts(em.n_episodes, 4, seed=1)
    got = DaskTaskMap(client)(_reweighted_replicate, counts, shared={"fqe": fqe, "row_episode": em.row_episode})
    assert got == [_reweighted_replicate(c, fqe=fqe, row_episode=em.row_episode) for c in counts]  # run here
    assert got == [fqe.reweighted_value(c[em.row_episode], rtol=REPLICATE_RTOL) for c in counts]
    assert len(set(got)) == 4  # the replicates differ from one another


def test_a_lost_scheduler_gives_a_clear_error_and_the_fit_resumes_from_its_checkpoint(client, coh, tmp_path):
    """Scheduler and workers in their own processes; the scheduler is killed after
    iteration 1. The fit stops with an OfflineADPError naming the checkpoint, and a fit on
    another cluster continues from iteration 2, matching an undisturbed 3-iteration fit."""
    import subprocess
    import sys
    import time

    import dask
    from distributed import Client

    from offline_adp.errors import OfflineADPError

    ds, path = coh
    params = {"n_estimators": 30, "num_leaves": 15, "min_child_samples": 20}
    sf = tmp_path / "scheduler.json"
    cli = [sys.executable, "-m"]
    sched = subprocess.Popen(cli + ["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
                                    "--no-dashboard", "--scheduler-file", str(sf)],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers = subprocess.Popen(cli + ["distributed.cli.dask_worker", "--scheduler-file", str(sf), "--nworkers", "2",
                                      "--nthreads", "1", "--no-dashboard", "--memory-limit", "2GiB"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(300):
            if sf.exists():
                break
            time.sleep(0.1)
        remote = Client(scheduler_file=str(sf), timeout="3s")  # how long it tries to reconnect
        remote.wait_for_workers(2, timeout=60)

        def kill_scheduler(k):
            if k == 1:
                sched.kill()
                sched.wait()

        ck = tmp_path / "ck"
        with dask.config.set({"distributed.comm.timeouts.connect": "3s"}), \
                pytest.raises(OfflineADPError, match="lost the Dask cluster.*checkpoint") as lost:
            DistributedFQI(gamma=0.95, n_iterations=3, lgbm_params=params).fit(remote, path, checkpoint_dir=ck,
                                                                               on_iteration=kill_scheduler)
        assert "\n" not in str(lost.value)  # one line, whatever Dask's own text was
        remote.close(timeout=5)
    finally:
        for p in (sched, workers):
            p.kill()
            p.wait()
    seen: list[int] = []
    resumed = DistributedFQI(gamma=0.95, n_iterations=3, lgbm_params=params).fit(client, path, checkpoint_dir=ck,
                                                                               on_iteration=seen.append)
    assert seen == [2, 3]  # iteration 1 came from the checkpoint
    undisturbed = DistributedFQI(gamma=0.95, n_iterations=3, lgbm_params=params).fit(client, path)
    x = ds.arrays().obs  # two workers there and here: the same rows on each, the same Q
    np.testing.assert_array_equal(resumed.q_function_.values(x), undisturbed.q_function_.values(x))


def test_distributed_warm_start_agrees_with_local_warm_start_and_resumes(client, coh, tmp_path):
    """Warm start on Dask: Q_k = Q_{k-1} + a few trees, only the new trees evaluated.
    Close to the single-process warm-start mode on two workers; a checkpointed run
    continues to the same Q."""
    ds, path = coh
    params = {"num_leaves": 15, "min_child_samples": 20}
    dist = DistributedFQI(gamma=0.95, n_iterations=6, lgbm_params=params, warm_start=True,
                          trees_per_iteration=10).fit(client, path)
    local = FittedQIteration(gamma=0.95, regressor="lightgbm", regressor_params=params, mode="warm_start",
                             trees_per_iteration=10, n_iterations=6, random_state=0).fit(ds)
    x = ds.arrays().obs
    qd = dist.q_function_.values(x)
    assert len(dist.q_function_.boosters) == 6
    assert np.corrcoef(qd.ravel(), local.q_function_.values(x).ravel())[0, 1] > 0.98
    ck = tmp_path / "ck"
    DistributedFQI(gamma=0.95, n_iterations=3, lgbm_params=params, warm_start=True).fit(client, path, checkpoint_dir=ck)
    seen: list[int] = []
    resumed = DistributedFQI(gamma=0.95, n_iterations=6, lgbm_params=params, warm_start=True).fit(
        client, path, checkpoint_dir=ck, on_iteration=seen.append)
    assert seen == [4, 5, 6]
    np.testing.assert_array_equal(resumed.q_function_.values(x), qd)


def _files(run):
    return sorted(str(p.relative_to(run)) for p in run.rglob("*"))


def test_a_dask_fit_writes_the_run_directory_of_a_local_fit_and_resumes_in_it(one_worker, tmp_path):
    """One run writer: ``fit_run`` on the Dask engine writes the files a local fit writes
    (config.json, run.json, checkpoint/, model/), its model loads as the local one and, on
    one worker, equals it (the oracle: the same loop, seeds and trees); interrupted after
    2 iterations, ``--resume`` continues from its checkpoint to that Q."""
    from offline_adp.algorithms.fqi import load_fqi
    from offline_adp.engines.dask import DaskFit
    from offline_adp.runs import fit_run

    simulate("car_on_hill", 0, 40, seed=7, horizon=60).save(tmp_path / "ds")
    params = {"regressor": "lightgbm", "regressor_params": {"n_estimators": 10, "num_leaves": 7, "n_jobs": 1},
              "n_iterations": 4, "mode": "refit", "random_state": 2}
    fit_run(tmp_path / "ds", tmp_path / "local", params=params)
    fit_run(tmp_path / "ds", tmp_path / "dask", params=params, engine=DaskFit(one_worker))
    assert _files(tmp_path / "dask") == _files(tmp_path / "local")
    import json

    status = {n: json.loads((tmp_path / n / "run.json").read_text()) for n in ("local", "dask")}
    assert status["dask"]["engine"] == "dask" and status["dask"]["unplaced_iterations"] == []
    assert set(status["local"]) <= set(status["dask"]) and status["dask"]["status"] == "completed"
    assert (tmp_path / "dask" / "config.json").read_text() == (tmp_path / "local" / "config.json").read_text()
    local, dist = load_fqi(tmp_path / "local" / "model"), load_fqi(tmp_path / "dask" / "model")
    x = simulate("car_on_hill", 0, 5, seed=8, horizon=20).arrays().obs
    np.testing.assert_array_equal(dist.q_function_.values(x), local.q_function_.values(x))
    assert dist.verdict_ == local.verdict_ and len(dist.history_) == 4

    def stop_at_2(row):
        if row["iteration"] == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_run(tmp_path / "ds", tmp_path / "cut", params=params, engine=DaskFit(one_worker), on_iteration=stop_at_2)
    assert json.loads((tmp_path / "cut" / "run.json").read_text())["status"] == "interrupted"
    seen: list[int] = []
    fit_run(tmp_path / "ds", tmp_path / "cut", params=params, engine=DaskFit(one_worker), resume=True,
            on_iteration=lambda r: seen.append(r["iteration"]))
    assert seen == [3, 4]
    resumed = load_fqi(tmp_path / "cut" / "model")
    np.testing.assert_array_equal(resumed.q_function_.values(x), local.q_function_.values(x))


@pytest.mark.parametrize("damage", ["text in a number column", "missing column", "rows not the checkpoint's"])
def test_a_damaged_dask_checkpoint_is_one_error_naming_the_file(one_worker, tmp_path, damage):
    """The Dask engine reads its checkpoint with the run writer's checked codec: a damaged
    history.csv is an ArtifactError naming it (exit 2 on the CLI), before any cluster work."""
    from offline_adp.errors import ArtifactError

    simulate("car_on_hill", 0, 20, seed=9, horizon=30).save(tmp_path / "ds")
    kw = {"gamma": 0.95, "lgbm_params": {"n_estimators": 5, "num_leaves": 7}}
    ck = tmp_path / "ck"
    DistributedFQI(n_iterations=2, **kw).fit(one_worker, tmp_path / "ds", checkpoint_dir=ck)
    hist = ck / "history.csv"
    lines = hist.read_text().splitlines()
    head = lines[0].split(",")
    if damage == "text in a number column":
        j = head.index("sup_dq")
        cells = lines[2].split(",")
        cells[j] = "oops"
        lines[2] = ",".join(cells)
        match = r"history.csv: column 'sup_dq' must hold numbers, found 'oops'"
    elif damage == "missing column":
        j = head.index("mean_dq")
        lines = [",".join(c for i, c in enumerate(line.split(",")) if i != j) for line in lines]
        match = r"history.csv: no column \['mean_dq'\]"
    else:
        lines = lines[:2]
        match = r"history.csv: 1 history rows, but .*q.json was written after iteration 2"
    hist.write_text("\n".join(lines) + "\n")
    with pytest.raises(ArtifactError, match=match):
        DistributedFQI(n_iterations=3, **kw).fit(one_worker, tmp_path / "ds", checkpoint_dir=ck)
