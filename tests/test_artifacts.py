"""Saved Q-functions predict exactly like the fitted ones, and loading runs no code."""

from __future__ import annotations

import json

import numpy as np
import pytest
from sklearn.preprocessing import StandardScaler

from offline_adp.algorithms.fqi import FittedQIteration, load_fqi, save_fqi
from offline_adp.artifacts import ArtifactError, load_q


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(regressor="extra_trees", regressor_params={"n_estimators": 5, "n_jobs": 1}),
        dict(regressor="extra_trees", regressor_params={"n_estimators": 5, "n_jobs": 1}, mode="frozen"),
        dict(regressor="lightgbm", mode="warm_start", trees_per_iteration=3),
        dict(regressor="lightgbm", regressor_params={"n_estimators": 10}),
        dict(regressor="ridge", action_encoding="per_action", feature_map=StandardScaler()),
        dict(regressor="knn"),
        dict(regressor="mlp", regressor_params={"max_iter": 20, "hidden_layer_sizes": (8,)}),
        dict(regressor="tabular", horizon=3),
    ],
    ids=["trees", "frozen", "warm_start", "lightgbm", "ridge+scaler", "knn", "mlp", "finite"],
)
@pytest.mark.slow
def test_round_trip_predictions_identical(tmp_path, small_pt, kwargs):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tiny MLP budgets do not converge
        f = FittedQIteration(n_iterations=3, **kwargs).fit(small_pt)
    save_fqi(f, tmp_path / "run", dataset_fingerprint=small_pt.fingerprint())
    g = load_fqi(tmp_path / "run")
    obs = small_pt.arrays().obs[::7]
    for t in (0, 1, 2):
        np.testing.assert_array_equal(g.predict(obs, t), f.predict(obs, t))
        np.testing.assert_array_equal(g.policy_.act(obs, t, return_index=True),
                                      f.policy_.act(obs, t, return_index=True))
    assert g.dataset_fingerprint_ == small_pt.fingerprint()
    assert len(g.history_) == len(f.history_)


def test_loading_refuses_unknown_classes(tmp_path, small_pt):
    f = FittedQIteration(regressor="ridge", n_iterations=1).fit(small_pt)
    save_fqi(f, tmp_path / "run")
    spec = json.loads((tmp_path / "run" / "q.json").read_text())
    spec["q"]["models"][0]["steps"][1][1]["class"] = "os.system"
    (tmp_path / "run" / "q.json").write_text(json.dumps(spec))
    with pytest.raises(ArtifactError, match="allow-list"):
        load_q(tmp_path / "run")


def test_other_versions_warn_for_q_functions_and_policies(tmp_path, small_pt):
    from offline_adp.artifacts import load_index_policy, save_policy
    from offline_adp.errors import FormatVersionWarning

    f = FittedQIteration(regressor="tabular", n_iterations=1).fit(small_pt)
    save_fqi(f, tmp_path / "q")
    save_policy(f.policy_, tmp_path / "p")
    for path, _name in ((tmp_path / "q" / "q.json", "q"), (tmp_path / "p" / "policy.json", "p")):
        spec = json.loads(path.read_text())
        spec["versions"]["scikit-learn"] = "0.0.1"
        path.write_text(json.dumps(spec))
    with pytest.warns(FormatVersionWarning, match="scikit-learn"):
        load_q(tmp_path / "q")
    with pytest.warns(FormatVersionWarning, match="scikit-learn"):
        load_index_policy(tmp_path / "p")
