"""Evaluating a continuous-command policy from the logs (issue #41 item 4), against the
scalar linear-quadratic closed form of :mod:`tests.test_continuous_commands`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from offline_adp.cli import main
from offline_adp.evaluation import continuous
from offline_adp.evaluation.continuous import command_support
from offline_adp.evaluation.run import evaluation_metrics
from offline_adp.policies import CommandPolicy, attach_signature

from .test_continuous_commands import GAMMA, U_MAX, LinearPolicy, discounted_cost, linear_value, lq_dataset


class Constant(CommandPolicy):
    def __init__(self, u: float) -> None:
        self.u = u

    def commands(self, obs, t=0):
        return np.full((len(np.asarray(obs)), 1), self.u)


@pytest.fixture(scope="module")
def lq():
    return lq_dataset(150, steps=60)  # gamma^60 < 0.01: the stationary FQE, structure-conditional bootstrap


def test_fqe_over_commands_reads_the_closed_form_with_its_measured_level(lq):
    pol = attach_signature(LinearPolicy(0.5), lq)
    m, res, _, _ = evaluation_metrics(lq, pol, None, fqe_bootstrap=30, bootstrap=0, model_particles=0)
    assert res is None and set(m["ope"]) == {"fqe"}
    fq = m["ope"]["fqe"]
    x0 = lq.arrays().obs[lq.arrays().step == 0, 0]
    truth = float(np.mean(linear_value(0.5) * x0 ** 2 * (1 - (GAMMA * 0.25) ** 60)))
    assert fq["estimate"] == pytest.approx(truth, rel=0.12)
    # the level the coverage suite measured (evaluation/continuous.py LEVEL), kept: the commands are supported
    assert fq["level"] == continuous.LEVEL == 0.95 and np.isfinite(fq["interval"]).all() and "level_note" not in fq
    assert fq["interval"][0] <= truth <= fq["interval"][1]
    assert m["behaviour"]["support_violations"]["fraction"] <= 0.05
    assert m["behaviour"]["replayed_commands"]["fraction"] == 0.0
    assert m["estimand"]["fqe_form"] == "stationary"
    assert (
        any("importance" in w["message"] for w in m["warnings"]) and "model rollouts of the logs" not in m["not_usable"]
    )
    best = m["headline"]["best"]
    assert best["name"] == "fqe" and best["level"] == 0.95 and best["interval"] == fq["interval"]
    # logs only, no model rollouts (turned off): support cannot be shown, so no side is claimed
    assert (
        "cannot tell" in m["headline"]["verdict"]["text"]
        or m["headline"]["verdict"]["performance"] == "indistinguishable"
    )


def test_model_rollouts_over_commands_read_the_closed_form(lq):
    """The discrete evaluation's model rollouts, over the exact commands: a second reading
    near the truth, the exit mass of a policy the logs cover small, FQE's interval hulled."""
    pol = attach_signature(LinearPolicy(0.5), lq)
    m, _, _, _ = evaluation_metrics(lq, pol, None, fqe_bootstrap=30, bootstrap=0, model_particles=300)
    fq = m["ope"]["fqe"]
    mr = fq["model_rollouts"]
    x0 = lq.arrays().obs[lq.arrays().step == 0, 0]
    truth = float(np.mean(linear_value(0.5) * x0 ** 2 * (1 - (GAMMA * 0.25) ** 60)))
    assert mr["n_particles"] == 300 and mr["exit_mass"] < 0.1
    assert mr["estimate"] == pytest.approx(truth, rel=0.25)
    assert fq["interval"][0] <= min(mr["interval"][0], fq["estimate"]) and fq["interval"][1] >= mr["interval"][1]
    assert fq["level"] == 0.95
    # the model's own interval (its bootstrap over episodes), an estimator of its own: labelled, it covers
    # the closed form (with 300 particles, 30 per replicate, it is about as wide as FQE's hull here)
    model = m["ope"]["model"]
    assert model["level"] == 0.95 and model["interval"][0] <= truth <= model["interval"][1]
    assert mr["bootstrap"]["replicates"] == 10 and len(mr["bootstrap"]["readings"]) == 10


@pytest.mark.parametrize("gain", [0.5, 0.9])
def test_the_models_interval_over_commands_covers_the_closed_form_over_data_seeds(gain):
    """Over independent logs, the model's bootstrap interval over commands holds the true
    value of a linear policy (the known system rolled out: the oracle) at least 5 of 6 times
    (two misses of a 95% interval in six are 3% likely)."""
    from offline_adp.evaluation.model_bootstrap import model_estimate

    covered = 0
    for seed in range(6):
        ds = lq_dataset(40, steps=60, seed=100 + seed)
        x0 = ds.arrays().obs[ds.arrays().step == 0, 0]
        pol = attach_signature(LinearPolicy(gain), ds)
        truth = float(np.mean(discounted_cost(pol, x0, steps=60)))  # the system is known: exact
        mr = continuous.command_model_rollouts(ds, pol, 60, GAMMA, n=300, level=0.95, seed=seed)
        lo, hi = model_estimate(mr, 0.95).interval
        covered += lo <= truth <= hi
        assert hi - lo < 2.5 * truth  # an interval that says something (refits on the wrong commands: ~30x wider)
    assert covered >= 5


@pytest.mark.parametrize("cap", [None, 400])
def test_every_refit_of_the_model_over_commands_reads_its_rows_own_commands(lq, monkeypatch, cap):
    """The main fit and each bootstrap refit see, for every row they fit on, that row's logged
    command (not its bin, not another row's), also when the fit samples its rows."""
    from offline_adp.evaluation import model_rollouts as mrmod

    if cap:
        monkeypatch.setattr(mrmod, "MAX_FIT_ROWS", cap)
    seen = []
    fit = continuous.CommandDynamics.fit_predictors

    def spy(self, a, rows):
        F, dx = fit(self, a, rows)
        seen.append((rows, F[:, 1:] * self.command_sd_))
        return F, dx

    monkeypatch.setattr(continuous.CommandDynamics, "fit_predictors", spy)
    pol = attach_signature(LinearPolicy(0.5), lq)
    continuous.command_model_rollouts(lq, pol, 60, GAMMA, n=40, level=0.95, seed=0, replicates=3)
    u = np.asarray(lq.commands(), np.float64).reshape(len(lq), -1)
    assert len(seen) == 4  # the main fit, three refits
    for rows, commands in seen:
        assert np.allclose(commands, u[rows])
    assert len(seen[0][0]) == (cap or len(lq)) and all(np.isin(r, seen[0][0]).all() for r, _ in seen[1:])


def test_the_models_level_over_commands_needs_supported_commands_and_no_replay():
    mr = {"estimate": 6.0, "exit_mass": 0.02, "n_particles": 1000, "fqe_interval": [3.0, 20.0],
          "bootstrap": {"interval": [5.0, 7.0], "method": "m"}}
    fine, replay_none = {"fraction": 0.01}, {"fraction": None}
    assert continuous.command_model_estimate(mr, fine, {"fraction": 0.0}).level == 0.95
    assert continuous.command_model_estimate(mr, fine, replay_none).level == 0.95
    unsupported = continuous.command_model_estimate(mr, {"fraction": 0.3}, replay_none)
    assert unsupported.level is None and "unsupported at 30%" in unsupported.level_note
    replays = continuous.command_model_estimate(mr, fine, {"fraction": 0.9})
    assert replays.level is None and "replays" in replays.level_note and replays.interval == (5.0, 7.0)
    assert continuous.command_model_estimate({"skipped": "off"}, fine, replay_none) is None
    # a level the model's own rule already withheld keeps its reason and gains the commands'
    left = {**mr, "exit_mass": 0.5}
    both = continuous.command_model_estimate(left, {"fraction": 0.3}, replay_none)
    assert both.level is None and "past the logged states" in both.level_note
    assert "unsupported at 30%" in both.level_note
    assert continuous.command_model_estimate(left, fine, replay_none).level_note.count(";") == 0


def test_level_withdrawn_where_commands_are_unsupported(lq):
    """A policy commanding what the logs never tried near the states: its interval is shown
    without a level, never quoted, and the verdict cannot tell (the discrete rule: more
    than 5% of the logged states see unsupported commands)."""
    m, _, _, _ = evaluation_metrics(lq, attach_signature(Constant(3 * U_MAX), lq), None, fqe_bootstrap=20, bootstrap=0,
                                    model_particles=0)
    fq = m["ope"]["fqe"]
    assert m["behaviour"]["support_violations"]["fraction"] == 1.0
    assert fq["level"] is None and fq["nominal_level"] == 0.95 and "left the data's support" in fq["level_note"]
    assert fq["withdrawn_by"] == "support"
    assert m["headline"]["best"] is None and "cannot tell" in m["headline"]["verdict"]["text"]


def test_level_withdrawn_for_a_replay_of_the_logs(lq):
    """The command logged at the nearest logged state (a one-nearest-neighbour clone): at
    every logged state it commands that state's own logged command, so what the logs show
    it doing is the logged episodes, not what it does in a new one: no level."""
    from offline_adp.policies import NearestCommandPolicy
    from offline_adp.qfunctions import NeighbourCommands

    a = lq.arrays()
    clone = attach_signature(NearestCommandPolicy(NeighbourCommands.from_data(a.obs, lq.commands(), 1)), lq)
    rep = continuous.replayed_commands(lq, clone)
    assert rep["fraction"] == 1.0 and rep["rows_checked"] == len(lq)
    m, _, _, _ = evaluation_metrics(lq, clone, None, fqe_bootstrap=20, bootstrap=0, model_particles=0)
    fq = m["ope"]["fqe"]
    assert fq["level"] is None and fq["nominal_level"] == 0.95 and "replays the logs" in fq["level_note"]
    assert fq["withdrawn_by"] == "replay"
    assert m["headline"]["best"] is None
    assert continuous.replayed_commands(lq, attach_signature(LinearPolicy(0.5), lq))["fraction"] == 0.0


def test_a_stochastic_command_policy_is_refused(lq):
    from offline_adp.errors import InvalidArgumentError
    from offline_adp.policies import GaussianCommandPolicy

    noisy = GaussianCommandPolicy(lambda x, t: -0.5 * x[:, :1], [0.1], [-U_MAX], [U_MAX])
    with pytest.raises(InvalidArgumentError, match="samples its commands"):
        evaluation_metrics(lq, noisy, None, fqe_bootstrap=0, bootstrap=0, model_particles=0)
    quiet = GaussianCommandPolicy(lambda x, t: -0.5 * x[:, :1], [0.0], [-U_MAX], [U_MAX])  # no noise: deterministic
    assert continuous.is_deterministic(quiet) and continuous.is_deterministic(LinearPolicy(0.5))
    assert not continuous.is_deterministic(noisy)


def test_command_support_separates_logged_from_foreign_commands(lq):
    inside = command_support(lq, attach_signature(LinearPolicy(0.5), lq))
    assert inside["fraction"] < 0.1
    outside = command_support(lq, Constant(3 * U_MAX))  # beyond every logged command
    assert outside["fraction"] == 1.0


def test_evaluate_and_report_a_continuous_run(lq, tmp_path):
    lq.save(tmp_path / "data")
    (tmp_path / "fqi.toml").write_text("[fqi]\nn_iterations = 20\nregressor_params = {n_estimators = 10}\n")
    assert main(["fit", str(tmp_path / "data"), "--config", str(tmp_path / "fqi.toml"), "--out", str(tmp_path / "run"),
                 "-q"]) == 0
    assert main(["evaluate", str(tmp_path / "run"), "--fqe-bootstrap", "10", "--bootstrap", "0", "-q"]) == 0
    m = json.loads((tmp_path / "run" / "evaluation" / "metrics.json").read_text())
    fq = m["ope"]["fqe"]
    assert m["commands"]["dims"] == ["u"] and (fq["level"] == 0.95 or fq.get("level_note"))  # a level, or why not
    assert main(["report", str(tmp_path / "run"), "-q"]) == 0
    figs = {p.name for p in (tmp_path / "run" / "report" / "figures").iterdir()}
    assert "commands.png" in figs  # (one state feature: no two-feature policy map)
    html = (tmp_path / "run" / "report" / "report.html").read_text()
    assert "Not computed for continuous commands" in html and "<style" in html
    assert ("(95%)" in html) == (fq["level"] == 0.95)  # an interval is printed with the level it has
    import re

    bounds = re.search(r"bounds \[([^\]]*)\] to \[([^\]]*)\]", html)  # at 4 digits, not float reprs
    lo, hi = m["commands"]["low"][0], m["commands"]["high"][0]
    assert bounds and bounds.groups() == (f"{lo:.4g}", f"{hi:.4g}")


def test_review_cases_through_the_cli(lq, tmp_path, capsys):
    """API over commands saves and loads its policy; FQE of a continuous policy is refused
    before any fit; a binned fit of a continuous log reports; a continuous run evaluates
    on another log of the same commands (its coarse bins differ)."""
    from offline_adp.algorithms.fqe import FittedQEvaluation

    lq.save(tmp_path / "data")
    lq_dataset(150, steps=60, seed=5).save(tmp_path / "other")
    (tmp_path / "api.toml").write_text("[api]\nn_iterations = 2\n[api.fqe]\nn_iterations = 10\n"
                                       "regressor_params = {n_estimators = 5}\n")
    assert main(["fit", str(tmp_path / "data"), "--algorithm", "api", "--config", str(tmp_path / "api.toml"),
                 "--out", str(tmp_path / "api"), "-q"]) == 0
    from offline_adp import load_policy

    assert load_policy(tmp_path / "api").act(np.zeros((3, 1))).shape == (3,)
    (tmp_path / "fqe.toml").write_text(f'[fqe]\npolicy = "{tmp_path / "api" / "model"}"\n')
    capsys.readouterr()
    assert main(["fit", str(tmp_path / "data"), "--algorithm", "fqe", "--config", str(tmp_path / "fqe.toml"),
                 "--out", str(tmp_path / "fqe"), "-q"]) == 2
    assert "continuous policy" in capsys.readouterr().err
    (tmp_path / "binned.toml").write_text("[fqi]\nn_iterations = 5\ncommands = \"binned\"\n")
    assert main(["fit", str(tmp_path / "data"), "--config", str(tmp_path / "binned.toml"), "--out",
                 str(tmp_path / "binned"), "-q"]) == 0
    assert main(["evaluate", str(tmp_path / "binned"), "--fqe-bootstrap", "0", "--bootstrap", "20", "-q"]) == 0
    assert main(["report", str(tmp_path / "binned"), "-q"]) == 0
    assert main(["evaluate", str(tmp_path / "api"), "--dataset", str(tmp_path / "other"), "--fqe-bootstrap", "0",
                 "--bootstrap", "0", "-q"]) == 0
    with pytest.raises(ValueError, match="commands"):  # a table policy cannot be evaluated over commands
        from offline_adp.policies import UniformPolicy

        FittedQEvaluation(policy=UniformPolicy(lq.n_actions), commands="continuous", n_iterations=2).fit(lq)


def test_truncated_command_logs_give_no_side_against_the_logged_cost():
    """Half the episodes cut at step 5 without a terminal state: the logged mean counts their
    missing steps as zero, so the continuous evaluation marks it not the T-step value (a
    reviewer saw "not distinguishable from the behaviour" read against it)."""
    from offline_adp.algorithms.fqi import FittedQIteration
    from offline_adp.evaluation.continuous import continuous_offpolicy
    from offline_adp.evaluation.settings import EvaluationSettings
    from offline_adp.policies import GreedyCommandPolicy, attach_signature
    from tests.test_continuous_deploy import command_dataset

    rng = np.random.default_rng(0)
    ep, st, X, U, C, NX, TR = [], [], [], [], [], [], []
    for e in range(40):
        L = 12 if e % 2 == 0 else 5
        s = rng.uniform(-1, 1, 2)
        for t in range(L):
            u = np.array([rng.uniform(-1, 1), rng.uniform(0, 2)])
            nx = s + 0.1 * np.array([u[0], u[1] - 1.0])
            ep.append(e), st.append(t), X.append(s), U.append(u), NX.append(nx), TR.append(t == L - 1)
            C.append((s**2).sum() + 0.1 * ((u - [0, 1]) ** 2).sum())
            s = nx
    ds = command_dataset(np.array(X), np.array(U), np.array(C), np.array(NX), np.array(ep), np.array(st),
                         [-1.0, 0.0], [1.0, 2.0], ["ux", "uy"], truncated=np.array(TR))
    q = FittedQIteration(n_iterations=2, mode="refit", regressor_params={"n_estimators": 5}).fit(ds).q_function_
    pi = attach_signature(GreedyCommandPolicy(q), ds)
    cfg = EvaluationSettings.resolve(None, {"fqe_bootstrap": 5, "bootstrap": 5, "model_particles": 0,
                                            "fqe_params": {"regressor_params": {"n_estimators": 5}}})
    bv = continuous_offpolicy(ds, pi, cfg, target_horizon=None, start=None)["behaviour_value"]
    assert bv["comparable"] is False and "20 of 40 logged episodes stop before step 12" in bv["not_comparable"]


def test_the_infinite_horizon_value_over_commands_carries_no_level_and_a_possible_range(lq):
    """FQE's level over commands was measured on finite estimands; an audit's infinite-horizon
    intervals over commands missed the exact LQ truth on 3 of 3 logs, labelled 95%. The
    estimand's possible range is recorded (it was null) and the intervals clipped to it."""
    pol = attach_signature(LinearPolicy(0.5), lq)
    m, _, _, _ = evaluation_metrics(lq, pol, None, estimand="infinite", fqe_bootstrap=10, bootstrap=0,
                                    model_particles=0)
    fq = m["ope"]["fqe"]
    assert m["estimand"]["form"] == "infinite" and fq["level"] is None
    assert "coverage has not been measured" in fq["level_note"] and "95%" not in m["headline"]["verdict"]["lines"][0]
    lo, hi = m["estimand"]["possible_range"]
    c = lq.arrays().cost
    assert 0.0 <= lo <= c.min() / (1 - GAMMA) and hi == pytest.approx(c.max() / (1 - GAMMA))  # costs >= 0
    assert lo <= fq["interval"][0] <= fq["interval"][1] <= hi
    finite, _, _, _ = evaluation_metrics(lq, pol, None, fqe_bootstrap=10, bootstrap=0, model_particles=0)
    assert finite["ope"]["fqe"]["level"] == 0.95 and finite["estimand"]["possible_range"] is not None
    # without replicates there is no interval and no level to withdraw (it raised a TypeError formatting None)
    bare, _, _, _ = evaluation_metrics(lq, pol, None, estimand="infinite", fqe_bootstrap=0, bootstrap=0,
                                       model_particles=0)
    iv = bare["ope"]["fqe"]["interval"]
    assert (iv is None or np.isnan(iv).all()) and bare["ope"]["fqe"]["level"] is None
    assert np.isfinite(bare["ope"]["fqe"]["estimate"])


def test_a_simulator_s_start_states_are_named_in_every_form_of_the_estimand(lq):
    from offline_adp.evaluation.estimand import declare_estimand

    pol = attach_signature(LinearPolicy(0.5), lq)
    for form in ("finite", "infinite"):  # finite: the stationary form here (gamma^60 < 0.01), which dropped it
        est = declare_estimand(lq, pol, None, form, start="env.reset() of gym:LQ-v0")
        assert est.start == "env.reset() of gym:LQ-v0" and est.describe().endswith("from env.reset() of gym:LQ-v0")


def test_model_rollouts_over_commands_say_their_progress(lq):
    """A rosbag audit waited 127 s in silence after "model rollouts over commands": the steps
    and the bootstrap refits are said now (and the numbers do not depend on saying them)."""
    from offline_adp.evaluation.continuous import command_model_rollouts

    pol = attach_signature(LinearPolicy(0.5), lq)
    said: list[str] = []
    kw = {"n": 100, "level": 0.95, "seed": 0, "replicates": 3}
    loud = command_model_rollouts(lq, pol, 20, GAMMA, say=said.append, **kw)
    quiet = command_model_rollouts(lq, pol, 20, GAMMA, **kw)
    assert any("step 20/20" in s for s in said) and any("3 bootstrap refits" in s for s in said)
    assert loud["estimate"] == quiet["estimate"] and loud["bootstrap"]["readings"] == quiet["bootstrap"]["readings"]


def test_the_report_of_a_held_out_run_overlays_the_held_out_commands(lq, tmp_path, monkeypatch):
    """A run fitted with --holdout is evaluated on its held-out episodes; the report's command
    figures overlay those episodes' logged commands (they were silently dropped: the whole
    dataset's fingerprint is not the evaluated episodes')."""
    import offline_adp.evaluation.report as report

    lq.save(tmp_path / "data")
    (tmp_path / "fqi.toml").write_text("[fqi]\nn_iterations = 5\nregressor_params = {n_estimators = 5}\n")
    assert main(["fit", str(tmp_path / "data"), "--config", str(tmp_path / "fqi.toml"), "--holdout", "0.3",
                 "--out", str(tmp_path / "run"), "-q"]) == 0
    assert main(["evaluate", str(tmp_path / "run"), "--fqe-bootstrap", "0", "--bootstrap", "0",
                 "--model-particles", "0", "-q"]) == 0
    seen = {}
    monkeypatch.setattr(report, "command_figures", lambda *a: seen.setdefault("logged", a[-1]))
    report.build_report(tmp_path / "run")
    ids = json.loads((tmp_path / "run" / "run.json").read_text())["holdout"]["ids"]
    want = lq.select_episodes(ids).commands()
    assert seen["logged"] is not None and len(seen["logged"]) == len(want) < len(lq)
    np.testing.assert_array_equal(np.sort(seen["logged"], axis=0), np.sort(want, axis=0))
