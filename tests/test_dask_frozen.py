"""The default FQI mode (frozen extra-trees) on a Dask LocalCluster (threads in this
process, loopback): trees grown on the workers, leaf sums per segment of rows."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("distributed")

from distributed import Client, LocalCluster  # noqa: E402

from offline_adp.algorithms.fqi import FittedQIteration, load_fqi  # noqa: E402
from offline_adp.data.dataset import read_dataset  # noqa: E402
from offline_adp.engines.dask import DaskFit, DistributedFQI  # noqa: E402
from offline_adp.runs import fit_run  # noqa: E402
from offline_adp.simulate import simulate  # noqa: E402

#: small forests, one thread in-process (the workers use their own one): the numbers do not depend on it
PARAMS = {"n_estimators": 8, "n_jobs": 1}
HIST = ["iteration", "sup_dq", "mean_dq", "max_abs_q", "bellman_residual", "greedy_changed", "start_value",
        "structure", "structure_trees"]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Path tracking (continuous costs, 7 actions) in four parts: blocks of unequal rows,
    and with two workers segments of one block each; ``structure_max_samples`` makes every
    build a bootstrap of part of the rows (as the default does above 131,072 rows)."""
    path = tmp_path_factory.mktemp("pt") / "ds"
    simulate("path_tracking", 0, 40, seed=3, horizon=40).save(path, rows_per_part=400)
    return read_dataset(path), path


def _cluster(n):
    return LocalCluster(n_workers=n, threads_per_worker=1, processes=False, dashboard_address=":0")


@pytest.fixture(scope="module")
def one():
    with _cluster(1) as c, Client(c) as cl:
        yield cl


@pytest.fixture(scope="module")
def two():
    with _cluster(2) as c, Client(c) as cl:
        yield cl


KW = {"gamma": 0.9, "n_iterations": 14, "regressor_params": PARAMS, "random_state": 5, "n_structures": 3,
      "structure_max_samples": 0.6}


def _dask_fit(client, path, **kw):
    est = FittedQIteration(**{**KW, **kw})
    rows = list(DaskFit(client).fit_iter(est, path))
    assert len(rows) == len(est.history_)
    return est


def _queries(ds):
    x = ds.arrays().obs
    rng = np.random.default_rng(0)
    return np.vstack([x, rng.uniform(x.min(axis=0), x.max(axis=0), size=(300, x.shape[1]))])


def _same(a, b, x):
    np.testing.assert_array_equal(a.q_function_.values(x), b.q_function_.values(x))
    np.testing.assert_array_equal(a.history_[HIST].to_numpy(float), b.history_[HIST].to_numpy(float))
    assert a.verdict_ == b.verdict_ and a.mode_ == b.mode_ == "frozen"


def test_one_worker_equals_the_local_default_fit(one, data):
    """The oracle: the same builds (seeds, bootstrap rows, jitter), leaves and sums in row
    order, so Q at the data and at random states, and every history value, are the local
    fit's bit for bit."""
    ds, path = data
    local = FittedQIteration(**KW).fit(ds)
    dist = _dask_fit(one, path)
    assert local.history_["structure"].nunique() == 3 and set(local.history_["structure_builder"]) == {"compiled"}
    _same(dist, local, _queries(ds))


def test_two_workers_are_reproducible_and_equal_local(two, data):
    """Trees are grown on both workers (tree t from (seed, t) and all rows) and each leaf's
    sum continues from the previous segment's: the structure is local's for any worker
    count and so is Q, bit for bit; a second run gives the same."""
    ds, path = data
    local = FittedQIteration(**KW).fit(ds)
    a, b = _dask_fit(two, path), _dask_fit(two, path)
    x = _queries(ds)
    _same(a, b, x)
    _same(a, local, x)
    ea, el = a.q_function_.models[0], local.q_function_.models[0]
    for k in ("left", "right", "feature", "threshold", "value", "roots"):
        np.testing.assert_array_equal(getattr(ea, k), getattr(el, k))


def test_distributed_fqi_with_extra_trees_on_constant_targets(one, tmp_path):
    """``DistributedFQI(regressor="extra_trees")`` runs the frozen mode; the gridworld's costs
    are constant, so the first targets are (one-leaf trees, made on the client and sent to
    the workers; the next iteration builds again): the local fit's Q and history."""
    simulate("gridworld", 0, 20, seed=2, horizon=50).save(tmp_path / "ds", rows_per_part=300)
    ds = read_dataset(tmp_path / "ds")
    dist = DistributedFQI(gamma=0.95, n_iterations=4, regressor="extra_trees", regressor_params=PARAMS,
                          random_state=1).fit(one, tmp_path / "ds")
    local = dist.estimator().fit(ds)
    built = local.history_["structure_on_constant"].tolist()
    assert built[0] and not built[-1]  # a constant structure first, then real builds
    _same(dist.estimator_, local, _queries(ds))


def test_resume_from_a_checkpoint_equals_an_uninterrupted_run(two, data, tmp_path):
    """The run writer on the Dask engine: stopped after iteration 6 (after the second
    build), resumed from the checkpoint (its structure looked up again on the workers),
    it ends at the uninterrupted run's Q and history; run.json says dask."""
    ds, path = data
    params = {**KW, "n_iterations": 10}
    whole = fit_run(path, tmp_path / "whole", params=params, engine=DaskFit(two))

    def stop_at_6(row):
        if row["iteration"] == 6:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_run(path, tmp_path / "cut", params=params, engine=DaskFit(two), on_iteration=stop_at_6)
    seen: list[int] = []
    fit_run(path, tmp_path / "cut", params=params, engine=DaskFit(two), resume=True,
            on_iteration=lambda r: seen.append(r["iteration"]))
    assert seen == [7, 8, 9, 10]
    a, b = load_fqi(tmp_path / "cut" / "model"), load_fqi(tmp_path / "whole" / "model")
    x = _queries(ds)
    np.testing.assert_array_equal(a.q_function_.values(x), b.q_function_.values(x))
    np.testing.assert_array_equal(a.history_[HIST].to_numpy(float), b.history_[HIST].to_numpy(float))
    assert json.loads((tmp_path / "cut" / "run.json").read_text())["engine"] == "dask"
    np.testing.assert_array_equal(whole.q_function_.values(x), b.q_function_.values(x))


def test_screen_is_refused_and_refit_extra_trees_too(one, data):
    from offline_adp.errors import InvalidArgumentError

    _, path = data
    with pytest.raises(InvalidArgumentError, match="screen_trees"):
        _dask_fit(one, path, screen_trees=4)
    with pytest.raises(InvalidArgumentError, match="frozen"):
        _dask_fit(one, path, mode="refit")


@pytest.mark.parametrize("kw", [{"action_input": "onehot"}, {"validation_fraction": 0.25},
                                {"regressor": "lightgbm", "mode": "frozen"}, {"horizon": 5},
                                {"action_encoding": "per_action", "mode": "frozen"}])
def test_what_the_engine_would_not_honour_is_refused_before_anything_is_written(one, data, tmp_path, kw):
    """A parameter the engine does not read (its data preparation has no one-hot inputs,
    no validation split), LightGBM in the frozen mode, or trees under a finite horizon
    (refit): one InvalidArgumentError before the run directory exists, never a silently
    different fit."""
    from offline_adp.errors import InvalidArgumentError

    _, path = data
    with pytest.raises(InvalidArgumentError, match="Dask engine cannot run"):
        _dask_fit(one, path, **kw)
    out = tmp_path / "run"
    with pytest.raises(InvalidArgumentError, match="dask engine cannot run"):
        fit_run(path, out, algorithm="fqi", params={**KW, **kw}, engine=DaskFit(one))
    assert not out.exists()


def test_the_pipeline_fits_a_finite_horizon_dataset_locally_and_says_so(one, tmp_path):
    """The dataset's own hints (gamma 1 and a horizon) make the default mode refit, which
    the engine does not run: the pipeline's fit stage takes the local engine, with a line."""
    from offline_adp.algorithms.registry import get_algorithm
    from offline_adp.pipeline import _fit_dask

    path = tmp_path / "ds"
    simulate("tabular", 4, 4, seed=0).save(path)
    assert read_dataset(path).info.horizon is not None
    lines: list[str] = []
    assert _fit_dask(get_algorithm("fqi"), {}, path, one, lines.append) is None
    assert len(lines) == 1 and "client process" in lines[0] and "refit" in lines[0]
    assert isinstance(_fit_dask(get_algorithm("fqi"), {"gamma": 0.9}, path, one, lines.append), DaskFit)


def test_frozen_fqe_on_one_worker_equals_local(one, data):
    """``DaskFit`` runs a frozen FQE (the evaluation's default FQE mode) with the same
    learner: Q and the value estimate are the local fit's."""
    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.policies import UniformPolicy

    ds, path = data
    kw = {"policy": UniformPolicy(ds.n_actions), "gamma": 0.9, "mode": "frozen", "n_iterations": 6,
          "regressor_params": PARAMS, "random_state": 2}
    local = FittedQEvaluation(**kw).fit(ds)
    est = FittedQEvaluation(**kw)
    for _ in DaskFit(one).fit_iter(est, path):
        pass
    x = _queries(ds)
    np.testing.assert_array_equal(est.q_function_.values(x), local.q_function_.values(x))
    assert est.value_ == local.value_


def test_the_cluster_warns_of_the_logs_as_the_local_fit_does(two, data, tmp_path):
    """A time limit flagged as terminal and a feature spanning less than the tree builders
    resolve: the same warnings (split over the blocks' rows) as in process; none on good logs."""
    import warnings

    from offline_adp.data import schema as S
    from offline_adp.errors import LogWarning, ScaleWarning

    ds, path = data
    df = ds.to_pandas()
    k = int(df.groupby("episode_id")["step"].max().min()) + 1
    df = df[df["step"] < k].copy()  # every episode k steps long, "terminal" at that time limit
    df["terminated"], df["truncated"] = (df["step"] == k - 1).to_numpy(), False
    name = ds.info.feature_names[0]
    for col in (S.obs_column(name), S.next_obs_column(name)):
        df[col] = 1.0 + 1e-6 * df[col] / df[col].abs().max()  # spans at most 2e-6
    bad = type(ds).from_pandas(df, ds.info)
    bad.save(tmp_path / "bad", rows_per_part=400)
    for fit in (lambda: FittedQIteration(**KW).fit(bad), lambda: _dask_fit(two, tmp_path / "bad")):
        with pytest.warns(LogWarning) as got:
            fit()
        said = " ".join(str(w.message) for w in got)
        assert "as a time limit would cut them" in said and f"feature {name!r} spans only" in said
        assert any(issubclass(w.category, ScaleWarning) for w in got)
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogWarning)
        _dask_fit(two, path)
