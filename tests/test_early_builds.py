"""Early frozen builds grow fewer trees (issue 14): the weight rule against its closed form,
the decisions it makes on the suite's schedules, and what a fit records and does with them."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from offline_adp.algorithms.fqi import FittedQIteration, structure_builds
from offline_adp.learn import build_weight
from offline_adp.simulate import simulate


def _closed_form(s: int, e: int, gamma: float, K: int) -> float:
    """sum_{j=s..e} gamma^(K-j), a geometric series."""
    return gamma ** (K - e) * (1 - gamma ** (e - s + 1)) / (1 - gamma)


@settings(max_examples=60, deadline=None)
@given(gamma=st.floats(0.05, 0.999), K=st.integers(2, 300), data=st.data())
def test_weight_is_the_ratio_of_geometric_sums(gamma, K, data):
    sched = sorted(data.draw(st.sets(st.integers(1, K), min_size=1, max_size=12)) | {1})
    # a scheduled build, or one re-triggered the iteration after a build on constant targets
    k = data.draw(st.sampled_from(sched)) + data.draw(st.integers(0, 1))
    w = build_weight(k, sched, gamma, K)
    later = [s for s in sched if s > k]
    if not later or k >= K:
        assert w == 1.0
        return
    expected = _closed_form(k, later[0] - 1, gamma, K) / _closed_form(sched[-1], K, gamma, K)
    assert w == pytest.approx(expected, rel=1e-9)


def test_a_later_build_weighs_more_than_an_earlier_one_of_the_same_length():
    sched = [1, 11, 21, 31]
    w = [build_weight(k, sched, 0.9, 40) for k in sched]
    assert w[0] < w[1] < w[2] < w[3] == 1.0


@pytest.mark.parametrize(("gamma", "K", "early"), [
    (0.95, 50, [1, 13, 26]),  # car-on-the-hill: all but the last
    (0.99, 50, []),  # every build's error still reaches the end
    (0.99, 100, [1, 13, 26]),
    (0.99, 200, [1, 13, 26, 38, 51, 63, 76, 88, 101, 113, 126]),
])
def test_which_builds_are_early_on_the_default_schedules(gamma, K, early):
    sched = list(FittedQIteration(gamma=gamma, n_iterations=K)._schedule())
    assert [k for k in sched if build_weight(k, sched, gamma, K) < 0.5] == early


@pytest.fixture(scope="module")
def pt():
    return simulate("path_tracking", 4, 6, seed=3, horizon=30)


def _fit(ds, **kw):
    base = {"n_iterations": 20, "gamma": 0.8, "n_structures": 4, "random_state": 1,
            "regressor_params": {"n_estimators": 8, "n_jobs": 1}}
    return FittedQIteration(**{**base, **kw}).fit(ds)


def test_a_fit_grows_early_builds_small_and_the_last_whole(pt):
    f = _fit(pt, early_build_trees=3)
    builds = structure_builds(f.history_)
    sched = [b["iteration"] for b in builds]
    assert sched == [1, 6, 11, 16]
    # weights 0.035, 0.107, 0.33 and 1 (sums of 0.8^(20 - j) over each build's iterations)
    assert [b["trees"] for b in builds] == [3, 3, 3, 8]
    full = _fit(pt, early_build_trees=None)
    assert [b["trees"] for b in structure_builds(full.history_)] == [8, 8, 8, 8]


def test_an_early_build_is_the_smaller_forest_it_names(pt):
    """Until the last build, a fit whose early builds grow 2 of 8 trees is the fit of a
    2-tree forest, iteration for iteration (the same seeds, the same first trees); at the
    last build it grows all 8 and parts from it."""
    a = _fit(pt, gamma=0.3, early_build_trees=2)
    small = _fit(pt, gamma=0.3, early_build_trees=None, regressor_params={"n_estimators": 2, "n_jobs": 1})
    assert [x["trees"] for x in structure_builds(a.history_)] == [2, 2, 2, 8]
    da, ds = a.history_["sup_dq"].to_numpy(), small.history_["sup_dq"].to_numpy()
    np.testing.assert_array_equal(da[:15], ds[:15])
    assert not np.array_equal(da[15:], ds[15:])


def test_a_finite_horizon_grows_every_build_whole(pt):
    """Each iterate of a finite-horizon fit is the policy at one step: nothing is damped."""
    f = FittedQIteration(horizon=10, gamma=0.5, mode="frozen", n_structures=4, early_build_trees=2,
                         regressor_params={"n_estimators": 6, "n_jobs": 1}).fit(pt)
    assert {b["trees"] for b in structure_builds(f.history_) if not b["constant"]} == {6}


@pytest.mark.parametrize("bad", [0, -1, 2.5, True, "10"])
def test_bad_early_build_trees_are_refused_before_fitting(pt, bad):
    with pytest.raises(ValueError, match="early_build_trees"):
        _fit(pt, early_build_trees=bad)
