"""A continuous policy that deploys (issue #41): FQI over exact commands -> ``offline-adp
distill`` -> ``load_policy`` / ONNX, which agree; bounds, the rate limit, artifacts."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
import onnxruntime as ort  # noqa: E402

from offline_adp import load_policy  # noqa: E402
from offline_adp.algorithms.fqi import FittedQIteration  # noqa: E402
from offline_adp.artifacts import load_index_policy, save_policy  # noqa: E402
from offline_adp.cli import main  # noqa: E402
from offline_adp.data.dataset import TransitionDataset  # noqa: E402
from offline_adp.data.info import ACTION_VALUE_PREFIX, Action, ActionTable, DatasetInfo, Feature  # noqa: E402
from offline_adp.distill import DistilledCommandPolicy, advantage_weights, distill_policy  # noqa: E402
from offline_adp.errors import ArtifactError, InvalidArgumentError, SchemaError  # noqa: E402
from offline_adp.onnx_export import ExportError, onnx_metadata, policy_to_onnx  # noqa: E402

N_STATES = 10_000


def command_dataset(obs, u, cost, next_obs, episode, step, low, high, dims, units=None, n_bins=5, terminated=None,
                    truncated=None):
    """A dataset with exact commands (``action_value.<dim>``) and, as ``action``, the
    nearest of ``n_bins`` representative commands per row (a coarse table: the discrete view)."""
    u = np.asarray(u, np.float64).reshape(len(obs), -1)
    reps = np.linspace(low, high, n_bins)
    span = np.asarray(high, np.float64) - np.asarray(low, np.float64)
    idx = np.argmin((((u[:, None, :] - reps[None]) / span) ** 2).sum(axis=2), axis=1)
    table = ActionTable(actions=tuple(Action(f"a{b}", tuple(float(x) for x in reps[b])) for b in range(n_bins)),
                        dims=tuple(dims), units=tuple(units or ()), kind="continuous",
                        low=tuple(float(x) for x in low), high=tuple(float(x) for x in high))
    info = DatasetInfo(features=tuple(Feature(f"o{j}", unit="m" if j == 0 else "") for j in range(obs.shape[1])),
                       action_table=table, gamma=0.95, name="commands")
    n = len(obs)
    return TransitionDataset.from_arrays(
        info, episode_id=np.char.zfill(np.asarray(episode).astype(int).astype(str), 6), step=step, obs=obs,
        action=idx, cost=cost, next_obs=next_obs,
        terminated=np.zeros(n, bool) if terminated is None else np.asarray(terminated, bool),
        truncated=np.zeros(n, bool) if truncated is None else np.asarray(truncated, bool),
        extra={ACTION_VALUE_PREFIX + d: u[:, j] for j, d in enumerate(dims)})


@pytest.fixture(scope="module")
def pendulum(tmp_path_factory):
    """Pendulum-v1 random play (10,000 transitions), FQI over the exact torque, saved as a run."""
    from offline_adp.envs.gym import record_random_log

    root = tmp_path_factory.mktemp("pendulum")
    log = record_random_log("Pendulum-v1", N_STATES, seed=1)
    ds = command_dataset(log["obs"], log["action"], -log["reward"], log["next_obs"], log["episode"], log["step"],
                         [-2.0], [2.0], ["torque"], ["N m"], terminated=log["terminated"],
                         truncated=log["truncated"].astype(bool) & ~log["terminated"].astype(bool))
    ds.save(root / "data")
    (root / "fqi.toml").write_text("[fqi]\nn_iterations = 3\nregressor_params = {n_estimators = 20}\n")
    assert main(["fit", str(root / "data"), "--config", str(root / "fqi.toml"), "--out", str(root / "run"), "-q"]) == 0
    return root, ds


@pytest.fixture(scope="module")
def planar():
    """Two-component commands with different bounds on a small synthetic system."""
    rng = np.random.default_rng(0)
    n = 2000
    x = rng.uniform(-1, 1, (n, 2))
    u = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(0, 2, n)])
    nxt = x + 0.1 * np.column_stack([u[:, 0], u[:, 1] - 1.0])
    cost = (x ** 2).sum(axis=1) + 0.1 * ((u - [0.0, 1.0]) ** 2).sum(axis=1)
    ds = command_dataset(x, u, cost, nxt, np.arange(n) // 20, np.arange(n) % 20, [-1.0, 0.0], [1.0, 2.0],
                         ["ux", "uy"], ["m/s", "m/s"])
    q = FittedQIteration(n_iterations=3, mode="refit", regressor_params={"n_estimators": 10}).fit(ds).q_function_
    from offline_adp.policies import GreedyCommandPolicy, attach_signature

    return ds, attach_signature(GreedyCommandPolicy(q), ds)


def _onnx(model, X):
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    outs = [o.name for o in sess.get_outputs()]
    assert outs == ["command"] and sess.get_inputs()[0].name == "observation"
    return sess.run(None, {"observation": X})[0]


def test_distill_export_agrees_with_load_policy(pendulum, tmp_path):
    """The CLI path: distill the run, export it with float32 input; onnxruntime and
    load_policy(RUN_DISTILLED).act agree to 1e-5 on the 10,000 logged states."""
    root, ds = pendulum
    out = tmp_path / "distilled"
    assert main(["distill", str(root / "run"), "--out", str(out), "--max-rate", "0.5", "--n-estimators", "30",
                 "-q"]) == 0
    pi = load_policy(out)
    assert isinstance(pi, DistilledCommandPolicy) and pi.max_rate.tolist() == [0.5]
    report = json.loads((out / "run.json").read_text())["distill"]
    print(f"\ndistilled vs greedy on {report['rows']} logged states: mean |diff| {report['mean_abs_diff']} "
          f"(held out {report['heldout_mean_abs_diff']}), "
          f"step change {report['mean_step_change']}, Q increase {report['q_increase']}")
    assert report["rows"] == len(ds) and report["mean_abs_diff"][0] < 1.0 and report["heldout_mean_abs_diff"][0] < 1.5
    for dtype in ("float32", "float64"):
        path = tmp_path / f"policy_{dtype}.onnx"
        assert main(["export", str(out), "--out", str(path), "--input-dtype", dtype, "-q"]) == 0
        import onnx

        X = ds.arrays().obs[:N_STATES].astype(dtype)
        assert len(X) == N_STATES
        got = _onnx(onnx.load(str(path)), X)
        ref = pi.act(X.astype(np.float64))
        assert got.shape == (N_STATES, 1)
        np.testing.assert_allclose(got[:, 0], ref, rtol=0, atol=1e-5)
        meta = onnx_metadata(path)
        assert meta["command_low"] == [-2.0] and meta["command_high"] == [2.0] and meta["max_rate"] == [0.5]
        assert meta["action_dims"] == ["torque"] and meta["action_units"] == ["N m"]
        assert meta["feature_names"] == ["o0", "o1", "o2"] and meta["inputs"]["observation"]["dtype"] == dtype
        assert meta["rate_limit_in_graph"] is False and meta["policy_kind"] == "DistilledCommandPolicy"


def test_greedy_command_policy_exports_exactly(pendulum, tmp_path):
    """The greedy policy itself (nearest logged states, their commands, the first minimum
    of Q): `offline-adp export RUN` with float32 input agrees with load_policy(RUN).act to
    1e-5 on the 10,000 logged states (run in batches: the exact search holds a batch's
    distances to every logged state)."""
    import onnx

    root, ds = pendulum
    path = tmp_path / "greedy.onnx"
    assert main(["export", str(root / "run"), "--out", str(path), "--input-dtype", "float32", "-q"]) == 0
    X = ds.arrays().obs[:N_STATES].astype(np.float32)
    model = onnx.load(str(path))
    got = np.vstack([_onnx(model, X[i:i + 1000]) for i in range(0, len(X), 1000)])
    ref = load_policy(root / "run").act(X.astype(np.float64))
    np.testing.assert_allclose(got[:, 0], ref, rtol=0, atol=1e-5)
    assert onnx_metadata(path)["policy_kind"] == "GreedyCommandPolicy"


def test_two_component_greedy_export(planar):
    ds, greedy = planar
    X = ds.arrays().obs[:500].astype(np.float32)
    got = _onnx(policy_to_onnx(greedy, input_dtype="float32"), X)
    np.testing.assert_allclose(got, greedy.act(X.astype(np.float64)), rtol=0, atol=1e-5)


def test_time_indexed_greedy_command_export_refused(planar):
    from offline_adp.policies import GreedyCommandPolicy, attach_signature
    from offline_adp.qfunctions import TimeIndexedQ

    ds, greedy = planar
    pi = attach_signature(GreedyCommandPolicy(TimeIndexedQ([greedy.q, greedy.q])), ds)
    with pytest.raises(ExportError, match="time-indexed") as e:
        policy_to_onnx(pi)
    # the refusal must not send the user to distill, which refuses it too (they pointed at each other)
    assert "offline-adp distill" not in str(e.value) and "fit a stationary policy" in str(e.value)
    from offline_adp.distill import distill_policy
    from offline_adp.errors import SchemaError

    with pytest.raises(SchemaError, match="time-varying"):
        distill_policy(pi, ds)


def test_two_components_bounds_and_onnx(planar):
    ds, greedy = planar
    pi = distill_policy(greedy, ds, n_estimators=20)
    X = ds.arrays().obs
    lo, hi = ds.info.action_table.bounds()
    for obs in (X, 10 * X, np.random.default_rng(1).normal(0, 100, X.shape)):  # far outside the data too
        u = pi.act(obs)
        assert u.shape == (len(obs), 2) and (u >= lo).all() and (u <= hi).all()
    assert len(pi.report["mean_abs_diff"]) == 2
    X32 = X.astype(np.float32)
    np.testing.assert_allclose(_onnx(policy_to_onnx(pi, input_dtype="float32"), X32), pi.act(X32.astype(np.float64)),
                               rtol=0, atol=1e-5)
    # the greedy commands the forest was fitted on are within bounds too (the clip is not hiding a bad fit)
    assert np.abs(pi.commands(X) - greedy.commands(X)).mean() < 0.5


def test_rate_limit(planar):
    ds, greedy = planar
    pi = distill_policy(greedy, ds, n_estimators=10, max_rate=[0.05, 0.1])
    X = ds.arrays().obs[:500]
    prev = np.full(2, np.nan)
    steps = []
    for x in X:  # a controller loop: one observation a step, the previous command fed back
        u = pi.act(x, previous=prev)
        if np.isfinite(prev).all():
            steps.append(np.abs(u - prev))
        prev = u
    steps = np.array(steps)
    assert (steps <= np.array([0.05, 0.1]) + 1e-12).all() and steps.max(axis=0)[0] == pytest.approx(0.05)
    # batched: rows with a NaN previous are not limited; without previous no limit at all
    free = pi.act(X[:4])
    prev = np.vstack([np.full((2, 2), [0.0, 1.0]), np.full((2, 2), np.nan)])  # the middle of the bounds, then none
    lim = pi.act(X[:4], previous=prev)
    np.testing.assert_allclose(lim[2:], free[2:])
    assert (np.abs(lim[:2] - prev[:2]) <= [0.05, 0.1 + 1e-12]).all()
    # one number for a two-component command is refused (it was applied to both), and so are wrong shapes

    for bad in (0.3, np.zeros(3), np.zeros((3, 2)), np.zeros((4, 3))):
        with pytest.raises(InvalidArgumentError, match="previous"):
            pi.act(X[:4], previous=bad)
    np.testing.assert_allclose(pi.act(X[:4], previous=np.array([0.0, 1.0])), pi.act(X[:4], previous=prev[[0, 0, 0, 0]]))
    lo, hi = ds.info.action_table.bounds()
    assert (lim >= lo).all() and (lim <= hi).all()
    with pytest.raises(SchemaError):
        distill_policy(greedy, ds, n_estimators=2, max_rate=[0.1, 0.0])


def test_no_observations_no_commands(planar):
    ds, greedy = planar
    assert greedy.commands(np.zeros((0, ds.arrays().obs.shape[1]))).shape == (0, 2)
    assert np.shape(greedy.act(np.zeros((0, ds.arrays().obs.shape[1])))) == (0, 2)


def test_artifact_round_trip(planar, tmp_path):
    ds, greedy = planar
    pi = distill_policy(greedy, ds, n_estimators=10, max_rate=0.2)
    save_policy(pi, tmp_path / "m")
    got = load_index_policy(tmp_path / "m")
    X = ds.arrays().obs
    assert isinstance(got, DistilledCommandPolicy)
    np.testing.assert_array_equal(got.commands(X), pi.commands(X))
    assert got.max_rate.tolist() == [0.2, 0.2] and got.low.tolist() == [-1.0, 0.0] and got.n_features == 2
    assert got.report["mean_abs_diff"] == pi.report["mean_abs_diff"]
    spec = json.loads((tmp_path / "m" / "policy.json").read_text())["policy"]
    assert spec["kind"] == "distilled_command" and spec["models"][1].get("structure") == "p.u0"  # one shared structure


def _rewrite(src, dst, edit_arrays=None, edit_spec=None):
    import shutil

    shutil.copytree(src, dst)
    with np.load(dst / "policy.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    if edit_arrays:
        edit_arrays(arrays)
    np.savez_compressed(dst / "policy.npz", **arrays)
    spec = json.loads((dst / "policy.json").read_text())
    if edit_spec:
        edit_spec(spec["policy"])
    (dst / "policy.json").write_text(json.dumps(spec))
    return dst


@pytest.mark.parametrize("case", ["low_shape", "rate_shape", "threshold_shape", "negative_rate", "inverted_bounds",
                                  "pickled_model", "width"])
def test_crafted_artifacts_refused(planar, tmp_path, case):
    ds, greedy = planar
    pi = distill_policy(greedy, ds, n_estimators=3, max_rate=0.2)
    save_policy(pi, tmp_path / "ok")
    edits = {
        "low_shape": ({"p.low": np.zeros(3)}, None),
        "rate_shape": ({"p.max_rate": np.ones((2, 1))}, None),
        "threshold_shape": ({"p.u0.threshold": np.zeros(2, np.float32)}, None),
        "negative_rate": ({"p.max_rate": np.array([0.2, -1.0])}, None),
        "inverted_bounds": ({"p.low": np.array([2.0, 0.0])}, None),
        "pickled_model": (None, lambda s: s["models"].__setitem__(0, {"kind": "sklearn", "class": "Ridge",
                                                                      "params": {}, "attrs": {}})),
        "width": (None, lambda s: s.__setitem__("n_features", 5)),
    }[case]
    bad = _rewrite(tmp_path / "ok", tmp_path / "bad", (lambda a: a.update(edits[0])) if edits[0] else None, edits[1])
    with pytest.raises(ArtifactError):
        load_index_policy(bad)


def test_distill_refuses_discrete_policies_and_weights_rule(tmp_path):
    from offline_adp.policies import UniformPolicy
    from offline_adp.simulate import simulate

    ds = simulate("two_state", 0, 5, seed=0)
    with pytest.raises(SchemaError, match="continuous"):
        distill_policy(UniformPolicy(2), ds)
    w = advantage_weights(np.array([[1.0, 1.0], [0.0, 2.0], [0.0, 4.0]]))
    np.testing.assert_allclose(w, [0.1, 0.1 + 0.9 * 1 / 1.0, 0.1 + 0.9 * 2 / 1.0])
    np.testing.assert_allclose(advantage_weights(np.ones((3, 4))), 1.0)


def test_greedy_export_agrees_where_logged_states_tie():
    """A robot reset to one pose: 200 logged states at exactly the same point, more than the
    candidates. The neighbours are ordered by (squared distance, row) in the library and in
    the graph, so both pick the same command there (and at a state far from every log)."""
    from offline_adp.policies import attach_signature
    from offline_adp.qfunctions import NeighbourCommands

    rng = np.random.default_rng(0)
    n = 2000
    x = rng.uniform(-1, 1, (n, 2))
    x[::10] = 0.0
    u = rng.uniform(-1, 1, (n, 1))
    ds = command_dataset(x, u, (x ** 2).sum(axis=1), x + 0.1 * u, np.arange(n) // 20, np.arange(n) % 20, [-1.0], [1.0],
                         ["u"])
    pol = attach_signature(FittedQIteration(n_iterations=5, regressor_params={"n_estimators": 10}).fit(ds).policy_, ds)
    np.testing.assert_array_equal(NeighbourCommands.from_data(x, u, 16).neighbours(np.zeros((1, 2)))[1][0],
                                  np.arange(0, 160, 10))  # the tied rows, lowest first
    X = np.vstack([x[:500], np.zeros((3, 2)), [[1e30, 0.0]]]).astype(np.float32)
    got = _onnx(policy_to_onnx(pol, input_dtype="float32"), X)
    np.testing.assert_allclose(got[:, 0], pol.act(X.astype(np.float64)), rtol=0, atol=1e-5)
    with pytest.raises(SchemaError, match="finite values only"):
        pol.act(np.array([[np.nan, 0.0]]))


def test_distill_overwrite_interrupted_keeps_the_previous_run(pendulum, tmp_path, monkeypatch):
    """`distill --overwrite` removed the old run, then renamed the new one into place: killed
    in between, neither was left (a crash audit). Now the new run is renamed over the old one
    (atomic_directory): failing at the swap itself leaves the previous run whole. A distill
    into the run distilled is refused."""
    import offline_adp.data.files as files
    from offline_adp.deploy import distill_run
    from offline_adp.errors import WriteError

    root, ds = pendulum
    out = tmp_path / "d"
    distill_run(root / "run", out, n_estimators=3)
    before = load_policy(out).act(ds.arrays().obs[:50])
    real, calls = files.os.replace, []

    def failing(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:  # the new run onto `out`, after the old one was set aside
            raise KeyboardInterrupt
        return real(src, dst)

    monkeypatch.setattr(files.os, "replace", failing)
    with pytest.raises(KeyboardInterrupt):
        distill_run(root / "run", out, n_estimators=5, overwrite=True)
    monkeypatch.setattr(files.os, "replace", real)
    np.testing.assert_array_equal(load_policy(out).act(ds.arrays().obs[:50]), before)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]  # nothing left beside it
    with pytest.raises(WriteError, match="lies inside the run directory"):
        distill_run(root / "run", root / "run" / "d2")
