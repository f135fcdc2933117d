"""``evaluate --simulator gym:ID`` measures the environment's own horizon (its registered time
limit), from env.reset(), and off-policy estimators that see only the logged horizon say so."""

from __future__ import annotations

import json

import gymnasium
import numpy as np
import pytest
from sklearn.linear_model import LinearRegression

from offline_adp.artifacts import save_policy
from offline_adp.cli import main
from offline_adp.envs.gym import record_random_log
from offline_adp.policies import GreedyPolicy
from offline_adp.qfunctions import QEncoder, RegressorQ
from tests.test_gym_simulator import SPEC, _log_table

NAMES = ["cart_x", "cart_v", "pole", "pole_rate"]


def _balancing_policy() -> GreedyPolicy:
    """Greedy in Q(x, left) = theta + 0.5 theta_dot = -Q(x, right): push right when theta + 0.5 theta_dot > 0."""
    X = np.random.default_rng(0).normal(size=(50, 4))
    s = X[:, 2] + 0.5 * X[:, 3]
    models = [LinearRegression().fit(X, s), LinearRegression().fit(X, -s)]
    return GreedyPolicy(RegressorQ(models, QEncoder(2, np.eye(2), True, None)))


def test_the_linear_controller_balances_500_steps_in_gymnasium():
    env = gymnasium.make("CartPole-v1")
    pi = _balancing_policy()
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        n, done = 0, False
        while not done:
            a = int(pi.actions(np.asarray(obs, np.float64)[None])[0])
            assert a == int(obs[2] + 0.5 * obs[3] > 0)
            obs, _, term, trunc, _ = env.step(a)
            n, done = n + 1, term or trunc
        assert n == 500 and not term


@pytest.fixture(scope="module")
def cartpole_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("gymh")
    log = record_random_log("CartPole-v1", 1500, seed=3)
    df = _log_table(log, NAMES, ("run", "tick", "push", "r", "fell", "time_up"))
    df.to_parquet(tmp / "cartpole.parquet")
    (tmp / "spec.toml").write_text(SPEC)
    ds, run = tmp / "ds", tmp / "run"
    assert main(["ingest", "parquet", str(tmp / "cartpole.parquet"), "--spec", str(tmp / "spec.toml"), "--out", str(ds),
                 "-q"]) == 0
    save_policy(_balancing_policy(), run / "model")
    (run / "run.json").write_text(json.dumps({"dataset": str(ds), "algorithm": "hand-written"}))
    logged = int(log["step"].max()) + 1
    assert logged < 200  # random play never balances long: the logs are far shorter than the time limit
    return run, logged


@pytest.mark.integration
def test_gym_evaluation_reports_the_500_step_value(cartpole_run, capsys):
    run, logged = cartpole_run
    assert main(["evaluate", str(run), "--simulator", "gym:CartPole-v1", "--episodes", "8", "--bootstrap", "5",
                 "--fqe-bootstrap", "0"]) == 0
    out, err = capsys.readouterr()
    # nobody asked for 500 steps, and the estimand is the 500-step value: no warning saying otherwise
    assert "asked for" not in err + out
    m = json.loads((run / "evaluation" / "metrics.json").read_text())
    r, p = m["rollout"], m["rollout"]["policy"]
    assert r["horizon"] == 500 and p["mean_length"] == 500 and p["terminated"] == 0
    g = 0.99  # the dataset's gamma; every step pays reward 1
    assert p["mean_discounted_cost"] == pytest.approx(-(1 - g**500) / (1 - g), rel=1e-9)
    est = m["estimand"]
    assert est["horizon"] == 500 and est["logged_horizon"] == logged
    assert (
        "over 500 steps from env.reset() of gym:CartPole-v1" in est["quantity"]
        and "data's start" not in est["quantity"]
    )
    assert r["estimand"] == est["quantity"] and est["quantity"] in out
    # the trajectory estimators see only the logged steps: not comparable, and they say so
    for name in ("is", "wis", "pdis", "dr", "mis"):
        o = m["ope"][name]
        assert o["comparable"] is False and any("not the 500-step value" in w for w in o["warnings"]), name


@pytest.mark.integration
def test_horizon_flag_overrides_the_time_limit(cartpole_run):
    run, logged = cartpole_run
    from offline_adp.evaluation.run import evaluate_run

    m = evaluate_run(run, simulator="gym:CartPole-v1", n_episodes=4, n_boot=5, n_boot_fqe=0, horizon=20)
    p = m["rollout"]["policy"]
    assert m["rollout"]["horizon"] == 20 and p["mean_length"] == 20
    assert p["mean_discounted_cost"] == pytest.approx(-(1 - 0.99**20) / (1 - 0.99), rel=1e-9)
    assert m["estimand"]["horizon"] == 20 and "over 20 steps from env.reset()" in m["estimand"]["quantity"]
    assert all(o["comparable"] is not False for o in m["ope"].values())  # 20 <= the logged horizon: all see it


def test_a_stationary_fqe_past_the_horizons_range_by_less_than_its_truncation_bound_is_usable():
    """A policy that balances forever: the stationary FQE reads about the infinite-horizon
    value (-1 / (1 - 0.99) = -100), below the 500-step floor (-99.34) by less than the
    truncation bound; it is reported at the floor and ranks as usable, not "outside the
    possible range". Farther out than the bound, it is left as it is (and not usable)."""
    from offline_adp.evaluation import ope
    from offline_adp.evaluation.estimand import Estimand, stationary_onto_range
    from offline_adp.evaluation.summary import rank_estimators

    gamma, H = 0.99, 500
    floor = -float(np.sum(gamma ** np.arange(H)))
    est = Estimand(H, gamma, "finite", "stationary", gamma**H / (1 - gamma), "t", (floor, 0.0))
    for value, moved in ((-99.89, True), (floor - 2 * est.tail_bound, False)):
        r = ope.OPEResult("fqe", value, (value - 0.5, -99.2), 100.0, 0.95)
        r = stationary_onto_range(r, est)
        assert (r.estimate == floor) is moved
        m = {"estimand": {"possible_range": [floor, 0.0]},
             "ope": {"fqe": {"estimate": r.estimate, "interval": [floor, -99.2], "level": 0.95}}}
        assert (rank_estimators(m)[0]["tier"] == 0) is moved
