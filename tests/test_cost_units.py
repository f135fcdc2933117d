"""Costs in any unit: with every cost multiplied by ``2^k`` a fit and an evaluation are the same,
with ``2^k`` times every cost-valued number, exactly. The oracle is the unscaled run (a
metamorphic test): multiplying by a power of two is exact in float64, so any absolute constant
left in the code (a jitter, a tolerance, a node-purity threshold read in the costs' units) shows
as a difference.

Before 2026-11-29 three constants were absolute: a build's tie jitter ``1e-6 (1 + std y)``, the
builders' purity threshold (a node whose target variance is at most float64 eps is a leaf), and
the evaluation's solve tolerance ``1e-7 (1 + max|v|)``; the model's cost-and-termination trees
weighed the two by their raw variances. On path tracking with the costs scaled by 1e-6 (max|c|
5e-5, no scale warning) the default fit's policy drove at 7.3 against 5.0 in the simulator (4
learner seeds), and at 2^-20 the greedy actions agreed with the unscaled fit's on 32% of the
logged states.
Now every one reads the costs' size, the power of two :func:`cost_unit`.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.algorithms.fqi_data import cost_unit
from offline_adp.data.dataset import TransitionDataset
from offline_adp.evaluation.fqe_interval import DEFAULT_FQE
from offline_adp.evaluation.model_rollouts import LoggedDynamics
from offline_adp.simulate import simulate


@pytest.fixture(scope="module")
def pt() -> TransitionDataset:
    return simulate("path_tracking", 8, 8, seed=11, horizon=60)  # costs 0 to 50 (a failure), ties


def scaled(ds: TransitionDataset, s: float) -> TransitionDataset:
    df = ds.to_pandas()
    df["cost"] = df["cost"] * s
    return TransitionDataset.from_pandas(df, ds.info)


def test_cost_unit_is_the_power_of_two_below_the_largest_cost():
    assert cost_unit(np.array([1.0, -0.5])) == 1.0 and cost_unit(np.array([50.0, -3.0])) == 32.0
    assert cost_unit(np.array([-0.75])) == 0.5 and cost_unit(np.array([3 * 2.0**-30])) == 2.0**-29
    assert cost_unit(np.zeros(3)) == 1.0 and cost_unit(np.array([np.inf])) == 1.0 and cost_unit(np.zeros(0)) == 1.0
    for m in np.random.default_rng(0).lognormal(0.0, 20.0, 200):
        u = cost_unit(np.array([m]))
        assert u <= m < 2 * u and math.frexp(u)[0] == 0.5


@pytest.mark.parametrize("k", [-40, 17])
def test_the_default_fit_is_the_same_in_any_power_of_two_of_the_unit(pt, k):
    s = 2.0**k
    params = {"regressor_params": {"n_estimators": 10}}
    a = FittedQIteration(**params).fit(pt)
    b = FittedQIteration(**params).fit(scaled(pt, s))
    assert a.mode_ == b.mode_ == "frozen" and len(a.history_) == len(b.history_) and a.verdict_ == b.verdict_
    x = pt.arrays().obs
    qa, qb = a.q_function_.values(x), b.q_function_.values(x)
    np.testing.assert_array_equal(qb, qa * s)  # exactly, not within a tolerance
    np.testing.assert_array_equal(b.policy_.probabilities(x, 0), a.policy_.probabilities(x, 0))
    np.testing.assert_array_equal(b.history_["sup_dq"].to_numpy(), a.history_["sup_dq"].to_numpy() * s)


@pytest.mark.parametrize("k", [-40, 17])
def test_fqe_and_the_logged_model_are_the_same_in_any_power_of_two_of_the_unit(pt, k):
    s = 2.0**k
    policy = FittedQIteration(regressor_params={"n_estimators": 5}).fit(pt).policy_
    other = scaled(pt, s)
    fqe = [FittedQEvaluation(policy=policy, **DEFAULT_FQE).fit(d) for d in (pt, other)]
    sweeps = [f.settle() for f in fqe]  # the solve's default tolerance: in the costs' unit
    assert sweeps[0] == sweeps[1] > 1 and fqe[1].value_ == fqe[0].value_ * s
    w = np.random.default_rng(1).poisson(1.0, len(fqe[0].fit_state_.data.train.cost)).astype(float)
    assert fqe[1].reweighted_value(w, rtol=1e-5) == fqe[0].reweighted_value(w, rtol=1e-5) * s  # a bootstrap replicate
    models = [LoggedDynamics(random_state=0).fit(d) for d in (pt, other)]
    arr = pt.arrays()
    states, actions = arr.obs[:300], arr.action[:300]
    steps = [m.step(states, actions, np.random.default_rng(2)) for m in models]
    np.testing.assert_array_equal(steps[1].next_states, steps[0].next_states)
    np.testing.assert_array_equal(steps[1].terminated, steps[0].terminated)
    np.testing.assert_array_equal(steps[1].costs, steps[0].costs * s)
    assert np.ptp(steps[0].costs) > 0


_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:e[-+]?\d+)?")


def _same_up_to_the_unit(a, b, s, path, found):
    """Walk two metrics.json trees: every number equal or exactly ``s`` times; every text the
    same once its numbers are blanked."""
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for key in a:
            if key not in ("path", "fingerprint"):
                _same_up_to_the_unit(a[key], b[key], s, f"{path}/{key}", found)
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _same_up_to_the_unit(x, y, s, f"{path}[{i}]", found)
    elif isinstance(a, str):
        assert _NUMBER.sub("#", a) == _NUMBER.sub("#", b), path
    elif isinstance(a, bool) or a is None:
        assert a == b, path
    else:
        assert b == a or b == a * s, f"{path}: {a} and {b} (costs x {s})"
        found[b == a * s and b != a] += 1


def test_evaluate_prints_every_cost_in_the_unit_of_the_logs(pt, tmp_path):
    """The whole evaluation (FQE and its bootstrap, the model rollouts, importance sampling, the
    shift diagnostics, the verdict) on logs whose costs are in 2^-40 of the unit (max|c| 4.5e-11: a
    tolerance of 1e-9 in absolute units, as the verdict's was, calls every side indistinguishable)."""
    from offline_adp.evaluation.run import evaluate_run
    from offline_adp.runs import fit_run

    s = 2.0**-40
    params = {"regressor_params": {"n_estimators": 5, "n_jobs": 1}}
    metrics = []
    for name, ds in (("x1", pt), ("small", scaled(pt, s))):
        ds.save(tmp_path / name)
        fit_run(tmp_path / name, tmp_path / f"run_{name}", params=params)
        evaluate_run(tmp_path / f"run_{name}", simulator="none", bootstrap=20, fqe_bootstrap=20, model_particles=50)
        metrics.append(json.loads((tmp_path / f"run_{name}" / "evaluation" / "metrics.json").read_text()))
    found = {True: 0, False: 0}
    _same_up_to_the_unit(metrics[0], metrics[1], s, "", found)
    assert found[True] > 50  # the estimates, intervals, logged costs and bounds did scale


def test_tiny_costs_warn_only_where_the_learner_reads_them_raw(pt):
    import warnings

    from offline_adp.errors import ScaleWarning

    tiny = scaled(pt, 1e-9)  # max|c| 5e-8: a node of such targets is "pure" to a raw tree builder
    with warnings.catch_warnings():
        warnings.simplefilter("error", ScaleWarning)
        FittedQIteration(regressor_params={"n_estimators": 3}).fit(tiny)  # the frozen default reads y / cost_unit
    with pytest.warns(ScaleWarning, match="the costs are at most 5e-08 in size"):
        FittedQIteration(mode="refit", n_iterations=2, regressor_params={"n_estimators": 3}).fit(tiny)


@pytest.mark.parametrize("k", [-60, -40, 0, 40])
def test_the_verdicts_tolerances_are_relative(k):
    """A side is claimed from the numbers' own size: at costs x 2^-40 a tolerance of 1e-9 in absolute
    units called every interval "not distinguishable" from the behaviour's cost."""
    from offline_adp.evaluation.verdict import logged_side, side_of_behaviour

    s = 2.0**k
    assert side_of_behaviour(2.3 * s, 2.6 * s, 4 * s) == "better"
    assert side_of_behaviour(4.1 * s, 5 * s, 4 * s) == "worse"
    assert side_of_behaviour(3 * s, 5 * s, 4 * s) == "indistinguishable"
    assert side_of_behaviour(1.0 * s, 1.0 * s, sum([0.1] * 10) * s) == "indistinguishable"  # equal up to rounding
    beh = {"mean": 4 * s, "interval": [3.5 * s, 4.5 * s]}
    assert logged_side(2.3 * s, 3.4 * s, beh) == "better" and logged_side(4.6 * s, 5 * s, beh) == "worse"
    assert logged_side(3.4 * s, 3.6 * s, beh) == "indistinguishable"


def test_policy_iteration_stops_alike_in_any_power_of_two_of_the_unit(pt):
    """API's "no improvement" stop compares evaluations with a relative tolerance: at costs x 2^-40
    an absolute 1e-9 never saw a rise and ran every iteration."""
    from offline_adp.algorithms.api import ApproximatePolicyIteration

    s = 2.0**-40
    a = ApproximatePolicyIteration(random_state=0).fit(pt)
    b = ApproximatePolicyIteration(random_state=0).fit(scaled(pt, s))
    assert len(a.history_) == len(b.history_) < 10 and a.verdict_ == b.verdict_  # stopped before the cap, alike
    x = pt.arrays().obs
    np.testing.assert_array_equal(b.q_function_.values(x), a.q_function_.values(x) * s)
    assert b.value_ == a.value_ * s
