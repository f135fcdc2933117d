"""`offline-adp fit`: run directories, checkpoints, kill and resume to the same result."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from offline_adp.algorithms.fqi import load_fqi
from offline_adp.cli import main
from offline_adp.runs import fit_run
from offline_adp.simulate import simulate

PARAMS = {"n_iterations": 25, "regressor_params": {"n_estimators": 30, "n_jobs": 1}, "random_state": 3}


@pytest.fixture(scope="module")
def pt_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("pt") / "ds"
    simulate("path_tracking", 25, 25, seed=2, horizon=80).save(d)
    return d


def _checkpoint_iteration(run) -> int:
    try:
        return json.loads((run / "checkpoint" / "q.json").read_text())["iteration"]
    except (FileNotFoundError, json.JSONDecodeError, KeyError):
        return 0


def test_killed_fit_resumes_to_the_uninterrupted_result(tmp_path, pt_dir):
    # refit: every iteration grows its trees, so the kill lands inside the run even when this
    # process is starved of CPU (frozen iterations between builds take milliseconds: on a loaded
    # machine the fit reached its 25th checkpoint before the kill; frozen resume: test_fqi_resume)
    ref = fit_run(pt_dir, tmp_path / "ref", params={**PARAMS, "mode": "refit"})
    cfg = tmp_path / "fqi.toml"
    cfg.write_text('[fqi]\nn_iterations = 25\nmode = "refit"\nrandom_state = 3\n'
                   '[fqi.regressor_params]\nn_estimators = 30\nn_jobs = 1\n')
    run = tmp_path / "run"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "offline_adp", "fit", str(pt_dir), "--config", str(cfg), "--out",
                             str(run), "-q"], env=env)
    deadline = time.time() + 120
    while _checkpoint_iteration(run) < 3 and proc.poll() is None and time.time() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the fit finished before it could be killed"
    k = _checkpoint_iteration(run)
    assert 3 <= k < 25
    assert json.loads((run / "run.json").read_text())["status"] == "running"
    assert not (run / "model").exists()
    assert main(["fit", str(pt_dir), "--out", str(run), "--resume", "-q"]) == 0
    res = load_fqi(run / "model")
    obs = simulate("path_tracking", 3, 3, seed=9, horizon=20).arrays().obs
    np.testing.assert_array_equal(res.predict(obs), ref.predict(obs))
    assert len(res.history_) == 25
    np.testing.assert_allclose(res.history_["sup_dq"], ref.history_["sup_dq"], rtol=0, atol=0)


def test_ctrl_c_on_finite_horizon_then_resume(tmp_path, pt_dir):
    params = {"horizon": 6, "regressor_params": {"n_estimators": 10, "n_jobs": 1}}
    ref = fit_run(pt_dir, tmp_path / "ref", params=params)

    def interrupt(row):
        if row["iteration"] == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_run(pt_dir, tmp_path / "run", params=params, on_iteration=interrupt)
    assert json.loads((tmp_path / "run" / "run.json").read_text())["status"] == "interrupted"
    est = fit_run(pt_dir, tmp_path / "run", params=params, resume=True)
    obs = simulate("path_tracking", 2, 2, seed=4, horizon=10).arrays().obs
    for t in range(6):
        np.testing.assert_array_equal(est.predict(obs, t), ref.predict(obs, t))


def test_fit_cli_errors(tmp_path, pt_dir, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[fqi]\nn_iteration = 3\n")
    assert main(["fit", str(pt_dir), "--config", str(cfg), "--out", str(tmp_path / "r"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "fqi.n_iteration: unknown key (did you mean 'n_iterations'?)" in err and "valid keys are" in err
    assert main(["fit", str(pt_dir), "--out", str(tmp_path / "nothing"), "--resume", "-q"]) == 2


def test_fit_cli_other_algorithms_write_policies(tmp_path, pt_dir, capsys):
    from offline_adp.artifacts import load_index_policy

    fqi_run = tmp_path / "fqi"
    assert main(["fit", str(pt_dir), "--out", str(fqi_run), "-q", "--config",
                 str(_cfg(tmp_path, "fqi", "n_iterations = 3\n[fqi.regressor_params]\nn_estimators = 5\n"))]) == 0
    cfgs = {
        "fqe": 'policy = "fqi/model"\nn_iterations = 3\nmode = "frozen"\n',
        "api": 'n_iterations = 2\n[api.fqe]\nn_iterations = 3\nmode = "frozen"\n',
        "cpi": 'n_iterations = 2\nstep_sizes = [0.5, 1.0]\n[cpi.fqe]\nn_iterations = 3\nmode = "frozen"\n',
        "psdp": 'simulator = "path_tracking"\nhorizon = 4\nn_samples = 30\nlearner = "regression"\n'
                'baseline_source = "demonstration"\ndrop_features = ["s"]\n[psdp.learner_params]\nn_estimators = 5\n',
    }
    obs = simulate("path_tracking", 2, 2, seed=4, horizon=10).arrays().obs
    for alg, body in cfgs.items():
        out = tmp_path / alg
        assert main(["fit", str(pt_dir), "--algorithm", alg, "--config", str(_cfg(tmp_path, alg, body)), "--out",
                     str(out), "-q"]) == 0, alg
        pi = load_index_policy(out / "model")
        assert pi.act(obs, 0, np.random.default_rng(0), return_index=True).shape == (len(obs),)
        assert json.loads((out / "run.json").read_text())["status"] == "completed"


def test_fqe_of_a_psdp_classifier_policy_saves_and_a_run_that_cannot_save_says_failed(tmp_path, pt_dir, monkeypatch):
    """An audit: FQE of a PSDP run's policy (a loaded forest classifier) could not be saved,
    and run.json stayed "running". The loaded classifier saves again (the same probabilities),
    and a model that cannot be saved fails the run, saying why."""
    from offline_adp.artifacts import load_index_policy

    psdp = tmp_path / "psdp"
    body = 'simulator = "path_tracking"\nhorizon = 4\nn_samples = 30\n[psdp.learner_params]\nn_estimators = 5\n'
    assert main(["fit", str(pt_dir), "--algorithm", "psdp", "--config", str(_cfg(tmp_path, "psdp", body)), "--out",
                 str(psdp), "-q"]) == 0
    fqe = tmp_path / "fqe"
    cfg = _cfg(tmp_path, "fqe", f'policy = "{psdp / "model"}"\nn_iterations = 3\nmode = "frozen"\n')
    assert main(["fit", str(pt_dir), "--algorithm", "fqe", "--config", str(cfg), "--out", str(fqe), "-q"]) == 0
    obs = simulate("path_tracking", 2, 2, seed=4, horizon=10).arrays().obs
    for t in range(3):
        np.testing.assert_array_equal(load_index_policy(fqe / "model").probabilities(obs, t),
                                      load_index_policy(psdp / "model").probabilities(obs, t))
    import offline_adp.runs as runs
    from offline_adp.errors import ArtifactError

    def refuse(*a, **k):
        raise ArtifactError("cannot save this")

    monkeypatch.setattr(runs, "_save_model", refuse)
    with pytest.raises(ArtifactError):
        fit_run(pt_dir, tmp_path / "nosave", algorithm="fqe",
                params={"policy": str(psdp / "model"), "n_iterations": 2, "mode": "frozen"})
    status = json.loads((tmp_path / "nosave" / "run.json").read_text())
    assert status["status"] == "failed" and "cannot save this" in status["error"]


def _cfg(tmp_path, alg, body):
    p = tmp_path / f"{alg}.toml"
    p.write_text(f"[{alg}]\n{body}")
    return p


def test_fit_cli_names_the_mode_that_ran_and_warns_only_for_warm_start(tmp_path, pt_dir, capsys):
    default = _cfg(tmp_path, "fqi", "n_iterations = 3\n[fqi.regressor_params]\nn_estimators = 5\nn_jobs = 1\n")
    assert main(["fit", str(pt_dir), "--out", str(tmp_path / "a"), "--config", str(default)]) == 0
    cap = capsys.readouterr()
    assert "fitted fqi (frozen mode, auto): 3 iterations" in cap.out and "warning" not in cap.err
    assert json.loads((tmp_path / "a" / "run.json").read_text())["mode"] == "frozen"
    warm = _cfg(tmp_path, "fqi", 'n_iterations = 2\nmode = "warm_start"\nregressor = "lightgbm"\n'
                                 '[fqi.regressor_params]\nn_estimators = 5\n')
    assert main(["fit", str(pt_dir), "--out", str(tmp_path / "b"), "--config", str(warm)]) == 0
    assert "warning: mode = 'warm_start' did not hold the refit score" in capsys.readouterr().err
    assert main(["fit", str(pt_dir), "--out", str(tmp_path / "c"), "--config", str(warm), "-q"]) == 0
    assert capsys.readouterr().err == ""  # -q: errors only


@pytest.mark.parametrize("value", ['"bogus"', "2.5", "[0.5, 0.0]"])
def test_fit_cli_refuses_a_bad_structure_max_samples_in_one_line(tmp_path, pt_dir, capsys, value):
    cfg = _cfg(tmp_path, "fqi", f"n_iterations = 2\nstructure_max_samples = {value}\n")
    assert main(["fit", str(pt_dir), "--out", str(tmp_path / "r"), "--config", str(cfg), "-q"]) == 2
    err = capsys.readouterr().err
    assert "structure_max_samples must be" in err and len(err.strip().splitlines()) == 1


def test_fit_cli_reports_each_frozen_build_and_its_tree_count(tmp_path, pt_dir, capsys):
    body = ("n_iterations = 3\nn_structures = 2\nscreen_trees = 2\nscreen_tol = 1e-12\n"
            "[fqi.regressor_params]\nn_estimators = 5\nn_jobs = 1\n")
    assert main(["fit", str(pt_dir), "--out", str(tmp_path / "a"), "--config", str(_cfg(tmp_path, "fqi", body))]) == 0
    out = capsys.readouterr().out
    # tol tiny: every build grows all 5
    assert (
        "tree structures: 2 built (iterations 1, 2), trees 5/5, grown by compiled (the screen: can cost score;" in out
    )
    builds = json.loads((tmp_path / "a" / "run.json").read_text())["structure_builds"]
    assert [(b["iteration"], b["trees"]) for b in builds] == [(1, 5), (2, 5)] and all(b["screen"] > 0 for b in builds)


def test_fit_cli_reports_early_builds_with_their_caveat(tmp_path, pt_dir, capsys):
    body = ("n_iterations = 6\nn_structures = 3\ngamma = 0.3\nearly_build_trees = 2\n"
            "[fqi.regressor_params]\nn_estimators = 5\nn_jobs = 1\n")
    assert main(["fit", str(pt_dir), "--out", str(tmp_path / "a"), "--config", str(_cfg(tmp_path, "fqi", body))]) == 0
    out = capsys.readouterr().out
    assert (
        "tree structures: 3 built (iterations 1, 3, 5), trees 2/2/5, grown by compiled (early builds: can cost score;"
        in out
    )
    builds = json.loads((tmp_path / "a" / "run.json").read_text())["structure_builds"]
    assert [(b["iteration"], b["trees"]) for b in builds] == [(1, 2), (3, 2), (5, 5)]
    # at gamma 0.99 no build is early: the line carries no caveat
    assert main(["fit", str(pt_dir), "--out", str(tmp_path / "b"),
                 "--config", str(_cfg(tmp_path, "fqi", body.replace("gamma = 0.3", "gamma = 0.99")))]) == 0
    out = capsys.readouterr().out
    assert "trees 5/5/5, grown by compiled\n" in out and "early builds" not in out


def test_a_whole_float_for_an_integer_key_runs_as_that_integer(tmp_path, pt_dir):
    """TOML ``screen_trees = 2.0``: checked as the integer 2 and run as 2 (not refused mid-run)."""
    body = (
        "n_iterations = 2\nscreen_trees = 2.0\nscreen_tol = 1e9\n[fqi.regressor_params]\nn_estimators = 5\nn_jobs = 1\n"
    )
    assert main(["fit", str(pt_dir), "--out", str(tmp_path / "a"), "--config", str(_cfg(tmp_path, "fqi", body)),
                 "-q"]) == 0
    run = json.loads((tmp_path / "a" / "run.json").read_text())
    assert run["status"] == "completed" and {b["trees"] for b in run["structure_builds"]} == {2}


def test_whole_floats_are_validated_integers_in_nested_and_pipeline_fqe_params():
    from offline_adp.algorithms.registry import get_algorithm

    out = get_algorithm("api").check_params({"n_iterations": 2.0, "fqe": {"n_iterations": 3.0, "gamma": 0.9}})
    assert out["n_iterations"] == 2 and type(out["n_iterations"]) is int
    assert out["fqe"] == {"n_iterations": 3, "gamma": 0.9} and type(out["fqe"]["n_iterations"]) is int


def test_a_pipeline_passes_on_validated_fit_and_fqe_numbers():
    from offline_adp.pipeline import load_pipeline
    from tests.test_pipeline import PIPELINES

    spec = load_pipeline(PIPELINES / "car_on_hill.toml", overrides={"fit.params": {"n_iterations": 3.0},
                                                                    "evaluate.fqe_params": {"n_iterations": 5.0}})
    assert type(spec["fit"]["params"]["n_iterations"]) is int and spec["fit"]["params"]["n_iterations"] == 3
    assert (
        type(spec["evaluate"]["fqe_params"]["n_iterations"]) is int
        and spec["evaluate"]["fqe_params"]["n_iterations"] == 5
    )


def test_api_run_records_its_verdict_and_evaluates_with_fqis_schedule(tmp_path, pt_dir):
    """``fit --algorithm api``: run.json holds the fit's verdict (issue #44); the evaluator
    runs FittedQIteration's tree schedule (frozen) under the ``[api.fqe]`` table's keys."""
    from offline_adp.algorithms.api import EVALUATOR_DEFAULTS
    from offline_adp.evaluation.summary import fit_convergence
    from offline_adp.runs import fit_run

    est = fit_run(pt_dir, tmp_path / "a", algorithm="api",
                  params={"n_iterations": 2, "fqe": {"regressor_params": {"n_estimators": 5, "n_jobs": 1}}})
    p = est.fqe_.get_params()
    assert est.fqe_.mode_ == "frozen" and p["mode"] == EVALUATOR_DEFAULTS["mode"] == "auto"
    assert p["structure_max_samples"] == "auto" and p["n_structures"] is None and p["early_build_trees"] == "auto"
    assert est.history_["cpu_seconds"].notna().all() and est.history_["evaluation"].notna().all()
    run = json.loads((tmp_path / "a" / "run.json").read_text())
    assert run["verdict"] == est.verdict_ in ("converged", "still changing") and run["verdict_message"]
    assert run.get("value") == est.value_ or (est.value_ is None and "value" not in run)  # the returned policy's
    assert fit_convergence(tmp_path / "a")["source"] == "run.json"


def test_api_reads_the_greedy_actions_at_next_states_from_the_evaluations_own_lookups(pt_dir):
    """The next-state values API takes from its evaluation's frozen structure give the
    greedy policy's own actions there (the same trees and leaves, summed in another order)."""
    from offline_adp.algorithms.api import _next_state_q, default_evaluator
    from offline_adp.data.dataset import read_dataset
    from offline_adp.policies import GreedyPolicy, UniformPolicy

    ds = read_dataset(pt_dir)
    nxt = ds.arrays().next_obs
    fqe = default_evaluator(policy=UniformPolicy(ds.n_actions), regressor_params={"n_estimators": 5}).fit(ds)
    q = _next_state_q(fqe, nxt)
    assert q is not None and q.shape == (len(ds), ds.n_actions)
    np.testing.assert_array_equal(q.argmin(axis=1), GreedyPolicy(fqe.q_function_).actions(nxt))
    assert _next_state_q(fqe, nxt[::-1].copy()) is None  # other states: none
