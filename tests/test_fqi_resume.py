"""Kill-and-resume in every FQI mode gives the uninterrupted fit's Q (issue 14).

Two windows: an interruption after some checkpoint (Ctrl-C in ``fit_run``), and a kill
after the last checkpoint but before ``model/`` was written (simulated by removing
``model/`` of a finished run and marking it running, which is exactly what such a kill
leaves). Both with and without ``tol``.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from offline_adp.algorithms.fqi import load_fqi, structure_builds
from offline_adp.runs import fit_run
from offline_adp.simulate import simulate

BASE = {"n_iterations": 8, "regressor_params": {"n_estimators": 5, "n_jobs": 1}, "random_state": 4}
MODES = {
    "refit": {"mode": "refit"},
    "refit_noise": {"mode": "refit", "target_noise": 0.05, "next_state_noise": 0.05},
    "frozen": {"mode": "frozen", "n_structures": 2},  # builds at 1 and 5: tol can stop it at 6
    "warm_start": {"mode": "warm_start", "regressor": "lightgbm", "regressor_params": {"n_jobs": 1},
                   "trees_per_iteration": 3},
    "finite_frozen": {"mode": "frozen", "horizon": 5},
    # builds screened on 2 of 6 trees: kept small (tol huge), or grown to 6 by warm start (tol tiny)
    "frozen_screen_kept": {"mode": "frozen", "n_structures": 2, "regressor_params": {"n_estimators": 6, "n_jobs": 1},
                           "screen_trees": 2, "screen_tol": 1e9},
    "frozen_screen_grown": {"mode": "frozen", "n_structures": 2, "regressor_params": {"n_estimators": 6, "n_jobs": 1},
                            "screen_trees": 2, "screen_tol": 1e-12},
    # builds at 1, 3 and 6; at gamma 0.5 the first two are early (2 trees), the last grows all 6
    "frozen_early": {"mode": "frozen", "n_structures": 3, "gamma": 0.5,
                     "regressor_params": {"n_estimators": 6, "n_jobs": 1},
                     "early_build_trees": 2},
}


@pytest.fixture(scope="module")
def pt_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("pt") / "ds"
    simulate("path_tracking", 8, 8, seed=5, horizon=40).save(d)
    return d


@pytest.fixture(scope="module")
def obs():
    return simulate("path_tracking", 2, 2, seed=9, horizon=15).arrays().obs


def _params(name: str, tol: bool) -> dict:
    p = {**BASE, **MODES[name]}
    if tol:
        p["tol"] = 1e9  # converged as soon as the mode allows: the resumed fit must stop at the same iteration
    return p


def _same(a, b, obs, horizon=None):
    for t in range(horizon or 1):
        np.testing.assert_array_equal(a.predict(obs, t), b.predict(obs, t))
    np.testing.assert_array_equal(a.history_["sup_dq"].to_numpy(), b.history_["sup_dq"].to_numpy())


@pytest.mark.parametrize("tol", [False, True])
@pytest.mark.parametrize("name", list(MODES))
def test_interrupted_then_resumed_equals_uninterrupted(tmp_path, pt_dir, obs, name, tol):
    params = _params(name, tol)
    ref = fit_run(pt_dir, tmp_path / "ref", params=params)
    stop_at = 2 if tol and name != "finite_frozen" else 3

    def interrupt(row):
        if row["iteration"] == stop_at:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_run(pt_dir, tmp_path / "run", params=params, on_iteration=interrupt)
    est = fit_run(pt_dir, tmp_path / "run", params=params, resume=True)
    _same(est, ref, obs, params.get("horizon"))
    _same(load_fqi(tmp_path / "run" / "model"), ref, obs, params.get("horizon"))
    assert est.verdict_ == ref.verdict_
    if "screen" in name:  # the screen's decisions and values survive the interruption
        trees = ref.history_["structure_trees"].to_numpy()
        assert set(trees) == ({2} if name.endswith("kept") else {6})
        np.testing.assert_array_equal(est.history_["structure_trees"].to_numpy(), trees)
        np.testing.assert_array_equal(est.history_["structure_screen"].to_numpy(),
                                      ref.history_["structure_screen"].to_numpy())
    if name == "frozen_early":  # the early builds' smaller forests survive the interruption too
        builds = structure_builds(ref.history_)
        assert [(b["iteration"], b["trees"]) for b in builds] == [(1, 2), (3, 2), (6, 6)]
        np.testing.assert_array_equal(est.history_["structure_trees"].to_numpy(),
                                      ref.history_["structure_trees"].to_numpy())
    if tol and "horizon" not in params:  # a finite horizon runs its T steps whatever tol says
        assert ref.verdict_ == "converged" and len(ref.history_) < BASE["n_iterations"]


@pytest.mark.parametrize("tol", [False, True])
@pytest.mark.parametrize("name", ["refit", "frozen", "warm_start"])
def test_killed_after_the_last_checkpoint_resumes_without_an_extra_iteration(tmp_path, pt_dir, obs, name, tol):
    params = _params(name, tol)
    run = tmp_path / "run"
    ref = fit_run(pt_dir, run, params=params)
    n = len(ref.history_)
    # the last iteration is checkpointed
    assert json.loads((run / "checkpoint" / "q.json").read_text())["iteration"] == n
    shutil.rmtree(run / "model")  # what a kill between the last checkpoint and the final write leaves
    status = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**status, "status": "running"}))
    seen = []
    est = fit_run(pt_dir, run, params=params, resume=True, on_iteration=seen.append)
    assert seen == []  # nothing left to do
    _same(est, ref, obs)
    _same(load_fqi(run / "model"), ref, obs)
    done = json.loads((run / "run.json").read_text())
    assert done["status"] == "completed" and done["iterations"] == n and done["verdict"] == ref.verdict_
    assert done["fit_cpu_seconds"] >= 0


def test_frozen_resume_without_compiled_trees_takes_the_numpy_lookups(tmp_path, pt_dir, obs, monkeypatch):
    """Restoring a frozen structure looks leaves up with scikit-learn's compiled trees
    rebuilt from the saved arrays; where this scikit-learn's tree layout is unknown it
    falls back to the numpy traversal. Both give the uninterrupted fit's Q."""
    from offline_adp.trees import ensemble, loaded

    params = _params("frozen", False)
    ref = fit_run(pt_dir, tmp_path / "ref", params=params)
    calls = []

    def interrupt(row):
        if row["iteration"] == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_run(pt_dir, tmp_path / "run", params=params, on_iteration=interrupt)
    # (checkpoint writes are paced by their cost, so the resume may start from an earlier iteration)
    monkeypatch.setattr(ensemble.TreeEnsemble, "compiled_trees", lambda self: None)  # "an unknown scikit-learn layout"
    monkeypatch.setattr(loaded.LoadedEnsemble, "compiled_trees", lambda self: None)  # (a checkpoint's structure)
    per_tree = ensemble.per_tree_leaves
    monkeypatch.setattr(ensemble, "per_tree_leaves", lambda f: calls.append(f) or per_tree(f))
    est = fit_run(pt_dir, tmp_path / "run", params=params, resume=True)
    assert calls  # restore took the numpy fallback
    _same(est, ref, obs)
