"""Algorithms that cannot learn over continuous commands say so before they fit (a
continuous-command audit, 2026-11-29): the Python PSDP learned over the simulator's bins
behind the user's back (the CLI refused), IteratedFQI failed in its second round telling
the user to validate a dataset it had written itself, API with a finite-horizon evaluator
failed after its first round's fits, and ``action_input="onehot"`` was silently ignored."""

from __future__ import annotations

import pytest

from offline_adp.algorithms.api import ApproximatePolicyIteration
from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.algorithms.iterated_fqi import IteratedFQI
from offline_adp.algorithms.psdp import PSDP
from offline_adp.envs import make_problem
from offline_adp.errors import IncompatibleError, InvalidArgumentError
from offline_adp.simulate import simulate


@pytest.fixture(scope="module")
def ptc():
    ds = simulate("path_tracking", 3, 3, seed=0, horizon=30, problem_options={"commands": "continuous"})
    assert ds.info.action_table.continuous and ds.commands() is not None
    return ds, make_problem("path_tracking", commands="continuous")


def test_psdp_refuses_a_dataset_of_continuous_commands(ptc):
    ds, sim = ptc
    with pytest.raises(IncompatibleError, match="does not take continuous commands"):
        PSDP(horizon=3, n_samples=20, random_state=0).fit(sim, ds)


def test_iterated_fqi_refuses_them_before_its_first_round(ptc):
    ds, sim = ptc
    it = IteratedFQI(FittedQIteration(n_iterations=2), n_rounds=2, episodes_per_round=2, n_eval_episodes=2,
                     horizon=10)
    with pytest.raises(IncompatibleError, match="logs no exact commands"):
        it.fit(sim, ds)
    assert not hasattr(it, "history_")


def test_api_with_a_finite_horizon_evaluator_is_refused_over_commands(ptc, tmp_path, capsys):
    from offline_adp.cli import main

    ds, _ = ptc
    api = ApproximatePolicyIteration(fqe=FittedQEvaluation(horizon=5, n_iterations=2), n_iterations=2)
    with pytest.raises(IncompatibleError, match="needs an evaluator with horizon=None"):
        api.fit(ds)
    # through the CLI: one line, no traceback (a scikit-learn error type gave one)
    ds.save(tmp_path / "d")
    (tmp_path / "api.toml").write_text("[api]\nn_iterations = 2\n[api.fqe]\nhorizon = 5\n")
    assert main(["fit", str(tmp_path / "d"), "--algorithm", "api", "--config", str(tmp_path / "api.toml"),
                 "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "needs an evaluator with horizon=None" in err and "Traceback" not in err


def test_onehot_action_input_is_refused_over_commands(ptc):
    ds, _ = ptc
    with pytest.raises(InvalidArgumentError, match="action_input='value'"):
        FittedQIteration(action_input="onehot", n_iterations=2).fit(ds)


def test_a_scikit_learn_parameter_error_inside_a_command_is_one_line(tmp_path, capsys, monkeypatch):
    """The safety net under the refusals above: scikit-learn's InvalidParameterError raised in
    a fit (a setting the configuration check let through) is an error line, not a traceback."""
    from sklearn.utils._param_validation import InvalidParameterError

    import offline_adp.runs as runs
    from offline_adp.cli import main

    def bad(*a, **k):
        raise InvalidParameterError("The 'fqe' parameter of X must be something. Got 1 instead.")

    monkeypatch.setattr(runs, "fit_run", bad)
    simulate("gridworld", 1, 1, seed=0, horizon=5).save(tmp_path / "d")
    assert main(["fit", str(tmp_path / "d"), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "error: The 'fqe' parameter of X must be something" in err and "Traceback" not in err
