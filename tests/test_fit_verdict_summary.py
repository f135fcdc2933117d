"""The evaluation summary quotes the fit's own convergence verdict (``run.json``'s
``verdict`` and ``verdict_message``), falling back to the history/tol rule only for run
directories written before the verdict was stored."""

from __future__ import annotations

import json

import pytest

from offline_adp.evaluation.summary import fit_convergence
from offline_adp.runs import fit_run


@pytest.fixture(scope="module")
def grid_dir(tmp_path_factory):
    from offline_adp.simulate import simulate

    root = tmp_path_factory.mktemp("verdict")
    simulate("gridworld", 4, 4, seed=7, horizon=30).save(root / "ds")
    return root / "ds"


def _fit(grid_dir, out, **params):
    return fit_run(grid_dir, out, params={"regressor_params": {"n_estimators": 5}, **params})


def test_tol_reached_reads_converged_from_the_stored_verdict(grid_dir, tmp_path):
    est = _fit(grid_dir, tmp_path / "run", n_iterations=20, tol=1e9)  # any change is below tol
    assert est.verdict_ == "converged"
    c = fit_convergence(tmp_path / "run")
    assert c["verdict"] == "converged" and c["source"] == "run.json"
    assert c["text"] == f"fit converged: {est.verdict_message_}"
    assert "< tol = 1e+09" in c["text"]


def test_still_changing_reads_not_converged_with_the_fits_message(grid_dir, tmp_path):
    est = _fit(grid_dir, tmp_path / "run", n_iterations=2, tol=1e-12)
    assert est.verdict_ == "still changing"
    c = fit_convergence(tmp_path / "run")
    assert c["verdict"] == "still changing" and c["source"] == "run.json"
    assert c["text"] == f"fit did NOT converge: {est.verdict_message_}"


def test_old_run_directory_without_a_stored_verdict_falls_back_to_history_and_tol(grid_dir, tmp_path):
    _fit(grid_dir, tmp_path / "run", n_iterations=20, tol=1e9)
    p = tmp_path / "run" / "run.json"
    info = json.loads(p.read_text())
    for k in ("verdict", "verdict_message"):
        info.pop(k)
    p.write_text(json.dumps(info))
    c = fit_convergence(tmp_path / "run")
    assert c["verdict"] == "converged" and c["source"] == "history.csv"
    assert c["text"].startswith("fit converged: last change")


def test_stored_diverging_verdict_says_not_to_trust_the_fit(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"status": "completed", "diverged": True, "verdict": "diverging",
                                              "verdict_message": "max|Q| grew 1e+06x in 30 iterations"}))
    c = fit_convergence(run)
    assert c["verdict"] == "diverging"
    assert c["text"] == ("fit DIVERGED: max|Q| grew 1e+06x in 30 iterations; its policy and values are not to "
                         "be trusted")
