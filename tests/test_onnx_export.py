"""ONNX export: onnxruntime picks the same actions as ``policy.act`` on 10,000 states.

The reference is the library's own ``act`` / ``q_function_.values``. A disagreement is
allowed only where the reference Q-values (class probabilities for classifiers) of the
two actions tie to 1e-9 relative: the graph sums leaf values in another order, which can
flip an argmin between exact ties. Such ties are counted and printed (``pytest -s``).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
import onnxruntime as ort  # noqa: E402

from offline_adp.algorithms.fqi import FittedQIteration  # noqa: E402
from offline_adp.errors import OfflineADPError  # noqa: E402
from offline_adp.onnx_export import ExportError, onnx_metadata, policy_to_onnx, save_onnx  # noqa: E402
from offline_adp.policies import GreedyPolicy, MixturePolicy, PolicySignature, UniformPolicy  # noqa: E402
from offline_adp.simulate import simulate  # noqa: E402

N_STATES = 10_000
DATA = {"car_on_hill": (0, 60, None), "path_tracking": (6, 6, 60), "gridworld": (0, 40, 60), "tabular": (0, 80, None),
        "two_state": (0, 20, None)}


@pytest.fixture(scope="module")
def datasets():
    return {name: simulate(name, d, e, seed=3, horizon=h) for name, (d, e, h) in DATA.items()}


def _states(ds, n=N_STATES, seed=0):
    """Half uniform over the data's box (widened by 10%), half resampled data states."""
    rng = np.random.default_rng(seed)
    obs = ds.arrays().obs
    lo, hi = obs.min(axis=0), obs.max(axis=0)
    pad = 0.1 * (hi - lo) + 1e-3
    box = rng.uniform(lo - pad, hi + pad, size=(n // 2, obs.shape[1]))
    return np.vstack([box, obs[rng.integers(0, len(obs), n - n // 2)]])


def _run(model, X, t=None):
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    feeds = {"observation": X}
    if t is not None:
        feeds["t"] = np.asarray(t, np.int64)
    names = [o.name for o in sess.get_outputs()]
    return dict(zip(names, sess.run(None, feeds), strict=True))


def _check(kind, got, ref, scores, pick=np.argmin):
    """No disagreement except exact ties of the reference scores; returns (mismatches, ties)."""
    rows = np.arange(len(ref))
    bad = got != ref
    gap = np.abs(scores[rows, got] - scores[rows, ref])
    tie = bad & (gap <= 1e-9 * (1.0 + np.abs(scores).max(axis=1)))
    print(f"\nONNX agreement {kind}: {int((~bad).sum())}/{len(ref)} equal, {int(bad.sum())} differ, of which "
          f"{int(tie.sum())} at ties (|dQ| <= 1e-9 rel)")
    assert not (bad & ~tie).any(), f"{kind}: {int((bad & ~tie).sum())} disagreements away from ties"
    return int(bad.sum()), int(tie.sum())


@pytest.mark.parametrize("problem", sorted(DATA))
def test_fqi_extra_trees_agrees_on_every_reference_problem(datasets, problem):
    ds = datasets[problem]
    f = FittedQIteration(regressor="extra_trees", regressor_params={"n_estimators": 15}, n_iterations=8,
                         gamma=0.95).fit(ds)
    X = _states(ds)
    out = _run(policy_to_onnx(f.policy_), X)
    ref = f.policy_.act(X, return_index=True)
    q = f.q_function_.values(X)
    np.testing.assert_allclose(out["q_values"], q, rtol=1e-12, atol=1e-12)
    _check(f"FQI extra-trees {problem}", out["action_index"], ref, q)
    # the action value output is the action table's value of the index
    np.testing.assert_array_equal(out["action"], ds.info.action_table.values[out["action_index"]])


@pytest.mark.parametrize("problem,kw", [
    ("car_on_hill", {"regressor": "lightgbm", "regressor_params": {"n_estimators": 20, "n_jobs": 1}}),
    ("path_tracking", {"regressor": "lightgbm", "regressor_params": {"n_jobs": 1}, "mode": "warm_start",
                       "trees_per_iteration": 5}),
    ("car_on_hill", {"regressor": "random_forest", "regressor_params": {"n_estimators": 10, "n_jobs": 1}}),
    ("path_tracking", {"regressor": "extra_trees", "regressor_params": {"n_estimators": 10},
                       "action_encoding": "per_action",
                       "action_input": "onehot"}),
])
def test_fqi_lightgbm_random_forest_and_per_action_agree(datasets, problem, kw):
    ds = datasets[problem]
    f = FittedQIteration(n_iterations=6, gamma=0.95, **kw).fit(ds)
    X = _states(ds)
    out = _run(policy_to_onnx(f.policy_), X)
    q = f.q_function_.values(X)
    np.testing.assert_allclose(out["q_values"], q, rtol=1e-10, atol=1e-10)
    _check(f"FQI {kw.get('mode', 'refit')} {kw['regressor']} {kw.get('action_encoding', 'joint')} {problem}",
           out["action_index"], f.policy_.act(X, return_index=True), q)


def test_finite_horizon_fqi_is_time_indexed(datasets):
    ds = datasets["gridworld"]
    T = 5
    f = FittedQIteration(horizon=T, regressor="extra_trees", regressor_params={"n_estimators": 10}).fit(ds)
    X = _states(ds)
    t = np.random.default_rng(1).integers(0, T + 3, len(X))  # steps >= T use the last rule
    model = policy_to_onnx(f.policy_)
    out = _run(model, X, t)
    q = f.q_function_.values(X, t)
    np.testing.assert_allclose(out["q_values"], q, rtol=1e-12, atol=1e-12)
    _check("FQI finite-horizon (time-indexed) gridworld", out["action_index"], f.policy_.act(X, t, return_index=True),
           q)
    meta = {p.key: p.value for p in model.metadata_props}
    assert json.loads(meta["time_indexed"]) is True and json.loads(meta["n_steps"]) == T


def test_api_policy_agrees(datasets):
    from offline_adp.algorithms.api import ApproximatePolicyIteration
    from offline_adp.algorithms.fqe import FittedQEvaluation

    ds = datasets["car_on_hill"]
    fqe = FittedQEvaluation(regressor="extra_trees", regressor_params={"n_estimators": 10}, n_iterations=5, gamma=0.95)
    api = ApproximatePolicyIteration(fqe=fqe, n_iterations=2).fit(ds)
    X = _states(ds)
    out = _run(policy_to_onnx(api.policy_), X)
    q = api.policy_.q.values(X)
    _check("API car_on_hill", out["action_index"], api.policy_.act(X, return_index=True), q)


@pytest.mark.parametrize("learner", ["classification", "regression"])
def test_psdp_time_indexed_policy_agrees(learner):
    from offline_adp.algorithms.psdp import PSDP
    from offline_adp.envs import make_problem
    from offline_adp.features import drop_features

    m = make_problem("path_tracking")
    T = 4
    fmap = drop_features(m.feature_names, ["s"])
    p = PSDP(horizon=T, n_samples=150, n_rollouts=1, learner=learner, feature_map=fmap,
             learner_params={"n_estimators": 10}, random_state=0).fit(m, m.demonstrator())
    rng = np.random.default_rng(2)
    X = m.initial_states(N_STATES, rng) + rng.normal(0, 0.05, (N_STATES, len(m.feature_names)))
    t = rng.integers(0, T + 2, N_STATES)
    out = _run(policy_to_onnx(p.policy_), X, t)
    ref = p.policy_.act(X, t, return_index=True)
    if learner == "classification":  # scores: the forest's class probabilities (higher wins)
        from offline_adp.qfunctions import per_step

        def proba(k, x):
            clf = p.policy_.steps[k].classifier
            s = np.zeros((len(x), m.action_table.__len__()))
            s[:, clf.classes_] = -clf.predict_proba(fmap.transform(x))
            return s
        scores = per_step(X, t, T, len(m.action_table), proba)
    else:
        from offline_adp.qfunctions import per_step

        scores = per_step(X, t, T, len(m.action_table), lambda k, x: p.policy_.steps[k].q.values(x))
        np.testing.assert_allclose(out["q_values"], scores, rtol=1e-12, atol=1e-12)
    _check(f"PSDP {learner} path_tracking (T={T})", out["action_index"], ref, scores)


def test_saved_run_exports_via_cli(tmp_path, datasets):
    """`offline-adp export` on fit run directories (loaded artifacts: TreeEnsemble arrays, LightGBM text)."""
    from offline_adp.cli import main
    from offline_adp.deploy import load_run_policy
    from offline_adp.runs import fit_run

    ds = datasets["car_on_hill"]
    ds.save(tmp_path / "data")
    X = _states(ds)
    for reg in ("extra_trees", "lightgbm"):
        run = tmp_path / f"run-{reg}"
        fit_run(tmp_path / "data", run, params={"regressor": reg, "n_iterations": 3,
                                                "regressor_params": {"n_estimators": 10, "n_jobs": 1}})
        assert main(["export", str(run), "--format", "onnx", "--out", str(tmp_path / f"{reg}.onnx")]) == 0
        pi = load_run_policy(run)
        import onnx

        out = _run(onnx.load(str(tmp_path / f"{reg}.onnx")), X)
        _check(f"FQI {reg} car_on_hill (saved run, CLI)", out["action_index"], pi.act(X, return_index=True),
               pi.q.values(X))
        # the action output is the action value of the chosen index (which _check compared
        # with the policy's, allowing exact ties of Q, where either action is the greedy one)
        np.testing.assert_array_equal(out["action"][:, 0], ds.info.action_table.values[out["action_index"]].ravel())
        meta = onnx_metadata(tmp_path / f"{reg}.onnx")
        assert meta["feature_names"] == ["p", "s"] and meta["feature_units"] == ["m", "m/s"]
        assert meta["action_values"] == [[-4.0], [4.0]] and meta["action_units"] == ["N"]


def test_stochastic_and_unsigned_policies_are_refused_clearly(datasets, tmp_path):
    ds = datasets["car_on_hill"]
    sig = PolicySignature.from_info(ds.info)
    f = FittedQIteration(regressor="extra_trees", regressor_params={"n_estimators": 3}, n_iterations=2,
                         gamma=0.9).fit(ds)
    mix = MixturePolicy([f.policy_, UniformPolicy(2)], [0.5, 0.5])
    with pytest.raises(ExportError, match="stochastic"):
        policy_to_onnx(mix, sig)
    with pytest.raises(ExportError, match="no signature"):
        policy_to_onnx(GreedyPolicy(f.q_function_))
    knn = FittedQIteration(regressor="knn", n_iterations=2, gamma=0.9).fit(ds)
    with pytest.raises(ExportError, match="KNeighborsRegressor"):
        save_onnx(knn.policy_, tmp_path / "x.onnx")
    assert not (tmp_path / "x.onnx").exists()
    assert issubclass(ExportError, OfflineADPError)
