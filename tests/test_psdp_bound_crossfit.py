"""The evaluation's PSDP bound with eps_t measured out of sample (cross-fitted FQE), against
the exact suboptimality of FQI's greedy policy on seeded tabular MDPs (exact DP)."""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp import dp
from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.envs.tabular import TabularMDP
from offline_adp.evaluation import psdp_eps, shift
from offline_adp.evaluation.offpolicy import off_policy
from offline_adp.policies import EpsilonPolicy, TabularPolicy
from offline_adp.simulate import collect

T = 10
TABULAR_FQE = {"regressor": "tabular", "action_encoding": "per_action"}


def _case(seed: int, n: int = 300):
    mdp = TabularMDP(30, 3, horizon=T, seed=seed)
    opt = mdp.optimal()
    pib = EpsilonPolicy(TabularPolicy(opt.policy, 3), 0.8)
    ds = collect(mdp, pib, n, np.random.default_rng(100 + seed), horizon=T)
    pi = FittedQIteration(regressor="tabular", horizon=T).fit(ds).policy_
    V = dp.policy_evaluation_finite(mdp.P, mdp.C, shift.policy_table(pi, mdp.n_states, T), T).V[0]
    subopt = float(mdp.initial_distribution @ (V - opt.V[0]))
    return ds, pi, TabularPolicy(opt.policy, 3), subopt


@pytest.mark.parametrize("seed", range(8))
def test_crossfitted_bound_holds_for_fqi_and_is_not_zero(seed):
    ds, pi, ref, subopt = _case(seed)
    res = off_policy(ds, pi, fqe_params=TABULAR_FQE, ratio_regressor="tabular", reference_policies={"optimal": ref},
                     n_boot=0, n_boot_fqe=0, seed=seed)
    # in sample, FQI's greedy policy is optimal against the FQE fitted on the same data: eps = 0 by construction
    assert np.all(np.abs(res.eps_in_sample) < 1e-9)
    assert res.eps.sum() > 0 and res.eps_folds == 2
    bound = res.bounds["optimal"]["per_step"]
    assert subopt > 0
    assert subopt <= bound, (seed, subopt, bound)


def test_in_sample_option_still_available():
    ds, pi, ref, _ = _case(0, n=100)
    res = off_policy(ds, pi, fqe_params=TABULAR_FQE, ratio_regressor="tabular", n_boot=0, n_boot_fqe=0, psdp_folds=0)
    assert res.eps_folds == 0 and np.array_equal(res.eps, res.eps_in_sample)


def test_a_fold_that_cannot_be_fitted_is_our_error_not_a_traceback(monkeypatch):
    """per_action FQE on a fold that lacks a rare action raised a bare ValueError through the
    CLI; the cross-fit says which fold, and off_policy then reports eps as not measured."""
    import numpy as np

    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.envs import make_problem
    from offline_adp.simulate import simulate

    ds = simulate("tabular", 10, 10, seed=0)
    pol = make_problem("tabular").demonstrator()

    def fail(self, dataset, *a, **k):
        raise ValueError("action 2 never occurs in the data")

    monkeypatch.setattr(FittedQEvaluation, "fit", fail)
    ep = np.unique(np.asarray(ds.arrays().episode), return_inverse=True)[1]
    with pytest.raises(psdp_eps.CrossFitError, match="fold 1 of 2: action 2 never occurs"):
        psdp_eps.crossfit_residual_advantage(ds, pol, {"regressor": "tabular"}, None, 0.9, 5, ep, folds=2)
