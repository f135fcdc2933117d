"""Logs with one action (the chapter's two-state chain): the behaviour is that action with
probability 1. A classifier fitted on one class answered two columns and the evaluation
stopped with a numpy shape error (found by a review)."""

import numpy as np

from offline_adp.evaluation.behaviour import estimate_behaviour


def test_the_behaviour_of_one_action_is_that_action_with_probability_one():
    obs = np.random.default_rng(0).normal(size=(50, 2))
    for n_actions, a in ((1, 0), (3, 2)):  # the only action in the table, or the only one taken of three
        est = estimate_behaviour(obs, np.full(50, a), n_actions)
        assert est.all_probs.shape == (50, n_actions)
        assert np.allclose(est.all_probs.sum(axis=1), 1.0)
        assert np.all(est.all_probs[:, a] >= est.all_probs.max(axis=1))  # the action taken has the mass
        assert np.allclose(est.logged_prob, est.all_probs[:, a]) and est.logged_prob.min() > 0.99


def test_a_two_state_evaluation_reads_the_chain_exactly(tmp_path, capsys):
    """Every cost of the chain is 0: the simulator, FQE and the verdict say 0 and 'not distinguishable'."""
    import json

    from offline_adp.cli import main

    d, r = tmp_path / "data", tmp_path / "run"
    assert main(["simulate", "two_state", "--out", str(d), "-q"]) == 0
    assert main(["fit", str(d), "--out", str(r), "-q"]) == 0
    assert main(["evaluate", str(r), "--simulator", "two_state", "--episodes", "20", "--bootstrap", "20",
                 "--fqe-bootstrap", "20", "-q"]) == 0
    m = json.loads((r / "evaluation" / "metrics.json").read_text())
    assert m["rollout"]["policy"]["mean_discounted_cost"] == 0.0
    assert abs(m["ope"]["fqe"]["estimate"]) < 1e-9
    assert m["behaviour"]["support_violations"]["fraction"] == 0.0
