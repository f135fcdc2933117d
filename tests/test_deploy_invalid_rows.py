"""What a deployed policy does with inputs it cannot act on (an export audit, 2026-11-29).

A NaN or infinite sensor value and a negative time step: ``policy.act`` refuses them
(``SchemaError`` naming the observation and feature), and the exported ONNX graph, which
cannot raise, gives those rows ``action_index`` -1 and NaN values (a NaN command for a
continuous policy), never a plausible action. Before, a LightGBM Q's graph and its Python
policy chose different actions on 737 of 1,400 states with one NaN feature (LightGBM reads
NaN as 0 or to a default side, the graph's TreeEnsemble to the right), a continuous
policy's graph returned an in-bounds command for ``[nan, v]``, and ``act(X, t=-1)`` read
the *last* step's rule while the graph clamped to the first.

Ground truth: the same graph's output on the valid rows equals ``policy.act`` there (so the
invalid rows change nothing else), and the invalid rows are the ones we made invalid."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
import onnxruntime as ort  # noqa: E402

from offline_adp.algorithms.fqi import FittedQIteration  # noqa: E402
from offline_adp.errors import SchemaError  # noqa: E402
from offline_adp.onnx_export import policy_to_onnx  # noqa: E402
from offline_adp.simulate import simulate  # noqa: E402


@pytest.fixture(scope="module")
def pt():
    return simulate("path_tracking", 4, 4, seed=5, horizon=40)


def _run(model, feeds):
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    names = [o.name for o in sess.get_outputs()]
    return dict(zip(names, sess.run(None, feeds), strict=True))


def _spoiled(X, rng, n_bad):
    """``X`` with one value made NaN, +inf or -inf in ``n_bad`` random rows; their indices."""
    X = X.copy()
    rows = rng.choice(len(X), n_bad, replace=False)
    X[rows, rng.integers(0, X.shape[1], n_bad)] = rng.choice([np.nan, np.inf, -np.inf], n_bad)
    return X, rows


@pytest.mark.parametrize("regressor", ["lightgbm", "extra_trees"])
def test_discrete_graph_marks_nonfinite_rows_and_act_refuses_them(pt, regressor):
    f = FittedQIteration(regressor=regressor, regressor_params={"n_estimators": 10}, n_iterations=4,
                         gamma=0.9).fit(pt)
    pi = f.policy_
    rng = np.random.default_rng(0)
    X, bad = _spoiled(pt.arrays().obs[:400], rng, 60)
    out = _run(policy_to_onnx(pi), {"observation": X})
    good = np.setdiff1d(np.arange(len(X)), bad)
    assert (out["action_index"][bad] == -1).all()
    assert np.isnan(out["action"][bad]).all() and np.isnan(out["q_values"][bad]).all()
    np.testing.assert_array_equal(out["action_index"][good], pi.act(X[good], return_index=True))
    np.testing.assert_array_equal(out["action"][good], pt.info.action_table.values[out["action_index"][good]])
    assert np.isfinite(out["q_values"][good]).all()
    i = int(bad.min())
    j = int(np.flatnonzero(~np.isfinite(X[i]))[0])
    with pytest.raises(SchemaError, match=f"observation {i}: '{pt.feature_names[j]}' is"):
        pi.act(X)
    with pytest.raises(SchemaError, match="finite values only"):
        pi.act(dict(zip(pt.feature_names, X[i], strict=True)))


def test_time_indexed_graph_and_act_refuse_negative_steps(pt):
    T = 4
    f = FittedQIteration(horizon=T, regressor="extra_trees", regressor_params={"n_estimators": 5}).fit(pt)
    pi = f.policy_
    X = pt.arrays().obs[:300]
    t = np.random.default_rng(1).integers(-3, T + 3, len(X))
    out = _run(policy_to_onnx(pi), {"observation": X, "t": t.astype(np.int64)})
    neg, ok = t < 0, t >= 0
    assert neg.any() and (out["action_index"][neg] == -1).all() and np.isnan(out["action"][neg]).all()
    np.testing.assert_array_equal(out["action_index"][ok], pi.act(X[ok], t[ok], return_index=True))
    with pytest.raises(SchemaError, match="t must be >= 0"):
        pi.act(X, t)
    with pytest.raises(SchemaError, match="t must be >= 0"):
        pi.act(X[0], -1)
    with pytest.raises(SchemaError, match="non-negative integer"):
        pi.act(X[:3], np.array([0.5, 1.0, 2.0]))
    with pytest.raises(SchemaError, match="one per observation"):
        pi.act(X[:3], np.array([0, 1]))


def test_continuous_graph_gives_nan_commands_where_act_refuses():
    from offline_adp.data.dataset import TransitionDataset
    from offline_adp.data.info import ACTION_VALUE_PREFIX, Action, ActionTable, DatasetInfo, Feature
    from offline_adp.policies import GreedyCommandPolicy, attach_signature

    rng = np.random.default_rng(0)
    n = 1500
    x = rng.uniform(-1, 1, (n, 2))
    u = rng.uniform(-1, 1, (n, 1))
    table = ActionTable(actions=tuple(Action(f"a{b}", (float(v),)) for b, v in enumerate(np.linspace(-1, 1, 5))),
                        dims=("u",), kind="continuous", low=(-1.0,), high=(1.0,))
    info = DatasetInfo(features=(Feature("e"), Feature("v")), action_table=table, gamma=0.9, name="c")
    ds = TransitionDataset.from_arrays(
        info, episode_id=np.char.zfill((np.arange(n) // 15).astype(str), 4), step=np.arange(n) % 15, obs=x,
        action=np.clip(np.rint((u[:, 0] + 1) * 2), 0, 4).astype(int), cost=(x ** 2).sum(axis=1) + 0.1 * u[:, 0] ** 2,
        next_obs=x + 0.1 * np.column_stack([x[:, 1], u[:, 0]]), terminated=np.zeros(n, bool),
        truncated=np.zeros(n, bool), extra={ACTION_VALUE_PREFIX + "u": u[:, 0]})
    q = FittedQIteration(n_iterations=3, mode="refit", regressor_params={"n_estimators": 5}).fit(ds).q_function_
    pi = attach_signature(GreedyCommandPolicy(q), ds)
    X, bad = _spoiled(x[:200], rng, 30)
    cmd = _run(policy_to_onnx(pi), {"observation": X})["command"]
    good = np.setdiff1d(np.arange(len(X)), bad)
    assert np.isnan(cmd[bad]).all()
    np.testing.assert_allclose(cmd[good, 0], pi.act(X[good]), rtol=0, atol=1e-12)
    with pytest.raises(SchemaError, match="finite values only"):
        pi.act(X)
