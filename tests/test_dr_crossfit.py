"""DR and WDR use a cross-fitted Q (docs/evaluation.md, section 2).

With the in-sample FQE of small-leaf trees, Q reproduces the logged returns: evaluating the
logging policy itself (every weight 1) the DR corrections cancel, each bootstrap replicate
reads about the same number, and a 95% interval of width ~1e-4 missed the truth
(car_on_hill: [0.1294, 0.1296] against 0.127). Cross-fitted (each episode's Q from an FQE
fitted without it), the interval has the spread of the logged returns.
"""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp.envs import make_problem
from offline_adp.evaluation.offpolicy import off_policy
from offline_adp.rollout import rollout
from offline_adp.simulate import simulate

pytestmark = pytest.mark.slow


def test_dr_on_the_logging_policy_has_the_spread_of_its_returns():
    prob = make_problem("car_on_hill")
    ds = simulate("car_on_hill", 0, 150, seed=4)
    pi = prob.exploration()
    res = off_policy(ds, pi, n_boot=100, seed=0, model_particles=0)
    in_sample = off_policy(ds, pi, n_boot=100, seed=0, model_particles=0, psdp_folds=0)
    T = res.estimand.horizon
    truth = rollout(prob, pi, 4000, np.random.default_rng(9), horizon=T, gamma=res.gamma)
    slack = 3 * truth.discounted_cost.std() / np.sqrt(4000)  # the truth's own Monte-Carlo error
    for name in ("dr", "wdr"):
        r, r0 = res.estimates[name], in_sample.estimates[name]
        lo, hi = r.interval if r.level is not None else r.percentile_interval
        lo0, hi0 = r0.interval if r0.level is not None else r0.percentile_interval
        assert "cross-fitted" in r.interval_method and "same episodes" in r0.interval_method
        assert hi - lo > 5 * (hi0 - lo0), (name, (lo, hi), (lo0, hi0))  # the in-sample one collapses
        assert lo - slack <= truth.mean <= hi + slack
