"""Episode-cost distributions and CVaR (:mod:`offline_adp.evaluation.risk`) against ground truth:
closed forms, and on a small tabular MDP the exact distribution of the episode cost, enumerated."""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp.envs.tabular import TabularMDP
from offline_adp.errors import InvalidArgumentError
from offline_adp.evaluation import ope, shift
from offline_adp.evaluation.offpolicy import logged_cost_distributions
from offline_adp.evaluation.risk import (
    cvar,
    distribution_summary,
    weighted_policy_distribution,
    weighted_quantiles,
)
from offline_adp.policies import EpsilonPolicy, TabularPolicy
from offline_adp.simulate import collect


def test_cvar_of_1_to_100_is_the_mean_of_the_worst_ten():
    c = np.arange(1.0, 101.0)
    assert cvar(c, 0.1) == pytest.approx(95.5)  # (91 + ... + 100) / 10
    assert cvar(np.random.default_rng(0).permutation(c), 0.1) == pytest.approx(95.5)  # order does not matter
    assert cvar(c, 1.0) == pytest.approx(c.mean())
    assert cvar(c, 0.01) == pytest.approx(100.0)
    assert cvar(c, 0.015) == pytest.approx((100.0 + 0.5 * 99.0) / 1.5)  # an atom straddling the tail counts in part


def test_weighted_cvar_equals_unweighted_for_equal_weights_and_repetition_for_integer_weights():
    rng = np.random.default_rng(1)
    c = rng.gamma(2.0, 3.0, 257)
    for alpha in (0.05, 0.1, 0.25, 0.5, 1.0):
        assert cvar(c, alpha, np.full(len(c), 7.0)) == pytest.approx(cvar(c, alpha))
    k = rng.integers(0, 4, len(c))
    for alpha in (0.05, 0.1, 0.3):
        assert cvar(c, alpha, k) == pytest.approx(cvar(np.repeat(c, k), alpha))
    assert weighted_quantiles(c, [0.0, 0.5, 1.0], k).tolist() == pytest.approx(
        weighted_quantiles(np.repeat(c, k), [0.0, 0.5, 1.0]).tolist())


def test_quantiles_and_summary_known_answers():
    c = np.arange(1.0, 11.0)
    assert weighted_quantiles(c, [0.0, 0.1, 0.5, 0.55, 1.0]).tolist() == [1.0, 1.0, 5.0, 6.0, 10.0]
    s = distribution_summary(c, alpha=0.2)
    assert s["mean"] == pytest.approx(5.5) and s["cvar"] == pytest.approx(9.5) and s["median"] == 5.0
    assert s["n_episodes"] == 10 and s["ess"] == pytest.approx(10.0) and s["max"] == 10.0
    assert s["cvar"] >= s["q90"] >= s["median"]
    for bad in ([], [1.0, np.nan]):
        with pytest.raises(InvalidArgumentError):
            cvar(bad)
    with pytest.raises(InvalidArgumentError, match="alpha"):
        cvar(c, 0.0)
    with pytest.raises(InvalidArgumentError, match="weights"):
        cvar(c, 0.1, -np.ones(10))


# --------------------------------------------------------------------------- exact, on a tabular MDP
T = 4
MDP = TabularMDP(5, 2, horizon=T, branching=2, seed=7)
OPT = MDP.optimal().policy


def exact_cost_distribution(pi) -> tuple[np.ndarray, np.ndarray]:
    """Every trajectory's probability and cost under ``pi``, enumerated (atoms of G)."""
    table = shift.policy_table(pi, MDP.n_states, T)  # (T, S, A)
    S = MDP.n_states
    prob, cost, state = MDP.initial_distribution.copy(), np.zeros(S), np.arange(S)
    for t in range(T):
        p = prob[:, None, None] * table[t][state][:, :, None] * MDP.P[:, state, :].transpose(1, 0, 2)  # (n, A, S)
        c = cost[:, None, None] + (MDP.gamma**t) * MDP.C[state][:, :, None] + np.zeros((1, 1, S))
        keep = p.ravel() > 0
        prob, cost = p.ravel()[keep], c.ravel()[keep]
        state = np.broadcast_to(np.arange(S), p.shape).ravel()[keep]
    return cost, prob


def test_enumeration_is_a_distribution_with_the_dp_value():
    from offline_adp import dp

    pi = EpsilonPolicy(TabularPolicy(OPT, 2), 0.3)
    g, p = exact_cost_distribution(pi)
    assert p.sum() == pytest.approx(1.0)
    V = dp.policy_evaluation_finite(MDP.P, MDP.C, shift.policy_table(pi, MDP.n_states, T), T).V[0]
    assert np.sum(p * g) == pytest.approx(float(MDP.initial_distribution @ V))


@pytest.mark.parametrize("eps_b, eps_pi", [(0.9, 0.4), (0.6, 0.2)])
def test_cvar_from_rollouts_and_from_weighted_logs_match_the_exact_one(eps_b, eps_pi):
    pib, pi = EpsilonPolicy(TabularPolicy(OPT, 2), eps_b), EpsilonPolicy(TabularPolicy(OPT, 2), eps_pi)
    g, p = exact_cost_distribution(pi)
    gb, pb = exact_cost_distribution(pib)
    truth, truth_b = cvar(g, 0.1, p), cvar(gb, 0.1, pb)
    assert truth > np.sum(p * g) + 0.1  # the tail is not the mean: the test can tell them apart
    # rollouts of pi: the unweighted distribution of its own episodes
    on = collect(MDP, pi, 20_000, np.random.default_rng(1), horizon=T).arrays()
    em_on = ope.EpisodeMatrix.build(on.episode, on.step, T)
    G_on = em_on.lay(on.cost) @ (MDP.gamma ** np.arange(T))
    assert distribution_summary(G_on)["cvar"] == pytest.approx(truth, abs=0.03)
    # logs of the behaviour: its own distribution, and pi's by importance weights
    a = collect(MDP, pib, 20_000, np.random.default_rng(2), horizon=T).arrays()
    rho = pi.probabilities(a.obs, a.step)[np.arange(len(a)), a.action] / a.behavior_prob
    em = ope.EpisodeMatrix.build(a.episode, a.step, T)
    d = logged_cost_distributions(em, a.cost, rho, MDP.gamma)
    assert d["behaviour_logged"]["cvar"] == pytest.approx(truth_b, abs=0.03)
    pol = d["policy_logs"]
    assert pol["usable"], pol
    assert pol["cvar"] == pytest.approx(truth, abs=0.05)
    assert pol["mean"] == pytest.approx(np.sum(p * g), abs=0.03)


def test_weighted_distribution_says_it_cannot_tell_when_the_weights_are_degenerate():
    rng = np.random.default_rng(3)
    G = rng.random(1000)
    W = np.zeros(1000)
    W[:3] = [50.0, 1.0, 1.0]  # three episodes carry the weight
    out = weighted_policy_distribution(G, W)
    assert out["usable"] is False and "effective sample size" in out["reason"]
    assert "cvar" not in out
    out = weighted_policy_distribution(G, np.zeros(1000))
    assert out["usable"] is False and "every importance weight is 0" in out["reason"]
    out = weighted_policy_distribution(G, np.ones(1000), comparable=False)
    assert out["usable"] is False and "past the logged episodes" in out["reason"]
    ok = weighted_policy_distribution(G, np.ones(1000))
    assert ok["usable"] and ok["cvar"] == pytest.approx(cvar(G, 0.1))
