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


def test_api_with_a_finite_horizon_evaluator_is_refused_over_commands(ptc):
    from sklearn.utils._param_validation import InvalidParameterError

    ds, _ = ptc
    api = ApproximatePolicyIteration(fqe=FittedQEvaluation(horizon=5, n_iterations=2), n_iterations=2)
    with pytest.raises(InvalidParameterError, match="horizon=None over continuous commands"):
        api.fit(ds)


def test_onehot_action_input_is_refused_over_commands(ptc):
    ds, _ = ptc
    with pytest.raises(InvalidArgumentError, match="action_input='value'"):
        FittedQIteration(action_input="onehot", n_iterations=2).fit(ds)
