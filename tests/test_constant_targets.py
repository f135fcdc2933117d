"""A log whose every cost is alike and that never terminates (random play that never
reaches a goal): Q is constant, ``Q_k = sum_{j<=k} gamma^j c``, and the frozen fit's one-leaf
trees are exact. It converges by the distance bound as any fit does, instead of rebuilding
constant structures to the iteration cap and calling the result "still changing" (measured
on 50k MountainCar random-play transitions: 1,196 iterations, "within 0.0006 ... > tolerance 1").
"""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.algorithms.fqi_monitor import distance_bound
from offline_adp.cli.fit_commands import fit_summary_lines
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import ActionTable, DatasetInfo, Feature


def _walk(n_ep: int = 20, T: int = 50, seed: int = 0) -> TransitionDataset:
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(size=(n_ep, T + 1)), axis=1)
    info = DatasetInfo(features=(Feature("x"),), action_table=ActionTable.from_values([0.0, 1.0]), gamma=0.9, horizon=T)
    return TransitionDataset.from_arrays(
        info, episode_id=np.repeat(np.arange(n_ep).astype(str), T), step=np.tile(np.arange(T), n_ep),
        obs=x[:, :-1].reshape(-1, 1), action=rng.integers(0, 2, n_ep * T), cost=np.ones(n_ep * T),
        next_obs=x[:, 1:].reshape(-1, 1), terminated=np.zeros(n_ep * T, bool),
        truncated=np.tile(np.arange(T) == T - 1, n_ep))


@pytest.mark.parametrize("tol", [1e-2, 1e-4])
def test_constant_targets_converge_by_the_distance_bound(tol):
    est = FittedQIteration(gamma=0.9, tol=tol, random_state=0).fit(_walk())
    assert est.verdict_ == "converged", est.verdict_message_
    k = len(est.history_)
    # the first iteration whose bound gamma/(1-gamma) * gamma^(k-1) reaches tol (sup|dQ_k| = gamma^(k-1))
    first = next(j for j in range(1, 10_000) if distance_bound(0.9 ** (j - 1), 0.9) <= tol)
    assert first <= k <= first + 2
    q = est.q_function_.values(np.array([[0.0], [5.0]]), 0)
    assert np.allclose(q, 10.0, atol=tol * 1.01)  # the fixed point 1 / (1 - gamma), within tol


def test_the_fit_summary_shortens_a_long_list_of_builds():
    est = FittedQIteration(gamma=0.9, tol=1e-4, random_state=0).fit(_walk())
    lines = fit_summary_lines(est, "fqi")
    builds = next(ln for ln in lines if ln.startswith("tree structures"))
    assert "..." in builds and len(builds) < 300
