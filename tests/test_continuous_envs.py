"""Simulators and rollouts over continuous commands (issue #41 items 5-6): gymnasium Box
environments and path_tracking's command modes step commands (n, m), rollouts of a
continuous policy pass its commands (never its binned view), and ``collect`` logs a
continuous behaviour's exact commands."""

from __future__ import annotations

import json

import gymnasium
import numpy as np
import pytest

from offline_adp.cli import main
from offline_adp.data.dataset import read_dataset
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.data.validate import validate
from offline_adp.envs import make_problem, problem_for_dataset
from offline_adp.envs.gym import GymResetModel
from offline_adp.envs.path_tracking import (
    SPEED_WEIGHT,
    STEERING_COMMANDS,
    V_MAX,
    V_TARGET,
    PathTracking,
)
from offline_adp.errors import IncompatibleError, InvalidArgumentError
from offline_adp.policies import CommandPolicy, GaussianCommandPolicy, nearest_entry
from offline_adp.rollout import collect, rollout, state_samples

PENDULUM = DatasetInfo(features=tuple(Feature(n) for n in ("cos_th", "sin_th", "omega")),
                       action_table=ActionTable.from_values([-1.5, 0.25, 2.0]), gamma=0.9)
CARTPOLE = DatasetInfo(features=tuple(Feature(n) for n in ("x", "v", "th", "w")),
                       action_table=ActionTable.from_values([0.0, 1.0]), gamma=0.99)


class Torque(CommandPolicy):
    """A continuous policy whose commands leave the box (|u| up to ~5), so clipping matters."""

    def commands(self, obs, t=0):
        return (-3.0 * obs[:, 1:2] - 0.5 * obs[:, 2:3]) * (1.0 + 0.01 * np.asarray(t))


class Stanley(CommandPolicy):
    def commands(self, obs, t=0):
        return np.clip(-(obs[:, 2] + np.arctan(1.5 * obs[:, 1] / obs[:, 4])), -0.3, 0.3)[:, None]


def test_continuous_rollout_in_gymnasium_equals_a_plain_loop():
    model = GymResetModel("Pendulum-v1", PENDULUM)
    assert model.accepts_commands
    n, H = 3, 30
    seen: list[tuple[int, np.ndarray, np.ndarray]] = []
    res = rollout(model, Torque(), n, np.random.default_rng(9), horizon=H, gamma=0.9,
                  on_step=lambda t, idx, xs, a, r: seen.append((t, a.copy(), r.next_states.copy())))
    seeds = np.random.default_rng(9).integers(0, 2**31 - 1, size=n)  # how initial_states draws its seeds
    envs = [gymnasium.make("Pendulum-v1").unwrapped for _ in seeds]
    obs = np.array([e.reset(seed=int(s))[0] for e, s in zip(envs, seeds, strict=True)], dtype=np.float64)
    disc = np.zeros(n)
    assert any(np.abs(a).max() > 2.0 for _, a, _ in seen)  # commands outside the box were sent (and clipped)
    for t in range(H):
        u = Torque().commands(obs, t)
        assert seen[t][0] == t
        np.testing.assert_array_equal(seen[t][1], u)
        for i in range(n):
            o, rew, *_ = envs[i].step(np.clip(u[i], -2.0, 2.0).astype(np.float32))
            obs[i], disc[i] = o, disc[i] - 0.9**t * rew
        np.testing.assert_array_equal(seen[t][2], obs)
    np.testing.assert_allclose(res.discounted_cost, disc, rtol=1e-12)


def test_gym_commands_are_checked():
    model = GymResetModel("Pendulum-v1", PENDULUM)
    x = model.initial_states(2, np.random.default_rng(0))
    with pytest.raises(InvalidArgumentError, match="not finite"):
        model.step(x, np.array([[0.5], [np.nan]]), np.random.default_rng(0))
    with pytest.raises(IncompatibleError, match=r"shape \(2, 1\)"):
        model.step(x, np.zeros((2, 2)), np.random.default_rng(0))
    cart = GymResetModel("CartPole-v1", CARTPOLE)
    assert not cart.accepts_commands
    xc = cart.initial_states(1, np.random.default_rng(0))
    with pytest.raises(IncompatibleError, match="indices"):
        cart.step(xc, np.zeros((1, 1)), np.random.default_rng(0))


def test_a_continuous_policy_is_never_rolled_out_binned():
    for model in (PathTracking(), GymResetModel("CartPole-v1", CARTPOLE)):
        with pytest.raises(IncompatibleError, match=f"simulator '{model.name}'.*does not accept continuous commands"):
            rollout(model, Stanley(), 2, np.random.default_rng(0), horizon=5)
        with pytest.raises(IncompatibleError, match="does not accept continuous commands"):
            state_samples(model, Stanley(), 2, 3, np.random.default_rng(0))
    with pytest.raises(IncompatibleError, match="does not accept continuous commands"):
        collect(PathTracking(), PathTracking(commands="continuous").demonstrator(), 2, np.random.default_rng(0),
                horizon=5)


@pytest.mark.parametrize("mode", ["continuous", "steer_accel"])
def test_path_tracking_commands_step_like_the_discrete_problem(mode):
    """Oracle: the same integrator; a command equal to a discrete command steps as its index."""
    disc, cont = PathTracking(), PathTracking(commands=mode)
    assert cont.accepts_commands and not disc.accepts_commands
    rng = np.random.default_rng(1)
    x = disc.initial_states(64, rng)
    a = rng.integers(0, len(STEERING_COMMANDS), 64)
    u = STEERING_COMMANDS[a][:, None]
    if mode == "steer_accel":
        u = np.column_stack([u, np.zeros(64)])
    ref = disc.step_seeded(x, a, 5)
    got = cont.step_seeded(x, u, 5)
    np.testing.assert_array_equal(got.next_states, ref.next_states)
    np.testing.assert_array_equal(got.terminated, ref.terminated)
    extra = 0.0 if mode == "continuous" else np.where(ref.terminated, 0.0, SPEED_WEIGHT * (x[:, 4] - V_TARGET) ** 2)
    np.testing.assert_allclose(got.costs, ref.costs + extra, rtol=0, atol=1e-12)
    # indices step the table's entries (the coarse bins: the discrete commands, accel 0 in the middle)
    idx = nearest_entry(cont.action_table, u)
    np.testing.assert_array_equal(cont.step_seeded(x, idx, 5).next_states, ref.next_states)


def test_path_tracking_command_bounds():
    p = PathTracking(commands="steer_accel", heading_noise=0.0)
    lo, hi = p.action_table.bounds()
    np.testing.assert_array_equal(lo, [-0.3, -2.0])
    np.testing.assert_array_equal(hi, [0.3, 2.0])
    x = p.initial_states(4, np.random.default_rng(2))
    x[:, 4] = [11.95, 11.95, 4.02, 8.0]
    beyond = np.array([[0.9, 10.0], [-0.3, 2.0], [-7.0, -50.0], [0.1, 0.0]])
    inside = np.clip(beyond, lo, hi)
    np.testing.assert_array_equal(p.step_seeded(x, beyond, 0).next_states, p.step_seeded(x, inside, 0).next_states)
    v = p.step_seeded(x, beyond, 0).next_states[:, 4]
    assert v[0] == V_MAX and v[1] == V_MAX and v[2] == 4.0 and v[3] == 8.0
    with pytest.raises(InvalidArgumentError, match="not finite"):
        p.step_seeded(x, np.full((4, 2), np.inf), 0)
    with pytest.raises(IncompatibleError, match=r"shape \(4, 2\)"):
        p.step_seeded(x, np.zeros((4, 1)), 0)
    with pytest.raises(InvalidArgumentError, match="commands must be one of"):
        make_problem("path_tracking", commands="torque")


def test_default_path_tracking_is_unchanged():
    p = PathTracking()
    assert p.problem_options == {} and p.action_table.kind == "discrete" and not p.accepts_commands
    assert type(p.demonstrator()).__name__ == "EpsilonPolicy"
    assert type(p).action_table is p.action_table


def test_default_path_tracking_logs_are_bit_identical():
    """The default problem's simulated logs, pinned to their fingerprint before the command
    modes were added (the README demo and many tests read these logs)."""
    from offline_adp.simulate import simulate

    ds = simulate("path_tracking", 20, 20, seed=3)
    assert ds.fingerprint() == "970ba558853fe1b61f36091e7712b60d1ca7c1f1eddcdd8b2bba0fd65d523874"


@pytest.mark.parametrize("mode", ["continuous", "steer_accel"])
def test_collect_logs_exact_commands_that_pass_the_doctor(mode):
    p = PathTracking(commands=mode, heading_noise=0.0, horizon=40)
    ds = collect(p, p.demonstrator(), 4, np.random.default_rng(3), source="demonstration")
    table = ds.info.action_table
    m = len(table.dims)
    u = ds.commands()
    assert table.kind == "continuous" and u.shape == (len(ds), m) and not ds.has_propensities
    assert validate(ds).ok
    lo, hi = table.bounds()
    assert (u >= lo).all() and (u <= hi).all()
    assert np.mean(np.isin(u[:, 0], STEERING_COMMANDS)) < 0.2  # not quantised (only the clipped ones at +-0.3)
    np.testing.assert_array_equal(ds.table.column("action").to_numpy(), nearest_entry(table, u))
    # the logged command is the one that was stepped (no heading noise: the step is deterministic)
    arr = ds.arrays()
    np.testing.assert_array_equal(p.step_seeded(arr.obs, u, 0).next_states, arr.next_obs)
    explore = collect(p, p.exploration(), 3, np.random.default_rng(4), source="exploration")
    ue = explore.commands()
    assert validate(explore).ok and ue[:, 0].std() > 0.12  # uniform in [-0.3, 0.3]: std 0.17


def test_gaussian_behaviour_discrete_view_matches_its_samples():
    for mode in ("continuous", "steer_accel"):
        p = PathTracking(commands=mode)
        pol = p.demonstrator()
        assert isinstance(pol, GaussianCommandPolicy)
        x = np.repeat(p.initial_states(3, np.random.default_rng(5)), 20000, axis=0)
        x[20000:40000, 1] += 0.3  # a state whose target is between bins
        probs = pol.probabilities(x[::20000])
        np.testing.assert_allclose(probs.sum(axis=1), 1.0)
        bins = nearest_entry(p.action_table, pol.sample_commands(x, 0, np.random.default_rng(6))).reshape(3, 20000)
        freq = np.stack([np.bincount(b, minlength=len(p.action_table)) / 20000 for b in bins])
        np.testing.assert_allclose(freq, probs, atol=0.015)


def test_simulate_cli_logs_exact_commands(tmp_path, capsys):
    out = tmp_path / "pt"
    assert main(["simulate", "path_tracking", "--problem-options", json.dumps({"commands": "continuous"}),
                 "--demonstrations", "2", "--exploration", "2", "--horizon", "20", "--out", str(out), "-q"]) == 0
    ds = read_dataset(out)
    assert ds.info.action_table.kind == "continuous" and ds.info.action_table.dims == ("delta_cmd",)
    assert ds.info.action_table.units == ("rad",)
    u = ds.commands()
    assert u is not None and len(np.unique(u)) > len(ds) // 2
    assert not ds.has_propensities and validate(ds).ok
    sim = problem_for_dataset("path_tracking", ds.info)
    assert sim.commands == "continuous" and sim.accepts_commands
    assert main(["simulate", "path_tracking", "--problem-options", json.dumps({"commands": "continuous"}),
                 "--demonstrations", "1", "--exploration", "0", "--format", "mcap-json", "--out",
                 str(tmp_path / "mcap"), "-q"]) == 2  # MCAP writers log table entries: refused, not dropped
    assert "exact continuous commands" in capsys.readouterr().err


def test_fitted_command_policy_rolls_out_in_path_tracking():
    from offline_adp.algorithms.fqi import FittedQIteration
    from offline_adp.simulate import simulate

    ds = simulate("path_tracking", 3, 6, seed=0, horizon=30, problem_options={"commands": "continuous"})
    model = problem_for_dataset("path_tracking", ds.info)
    est = FittedQIteration(gamma=0.95, n_iterations=3, regressor_params={"n_estimators": 5},
                           commands="continuous").fit(ds)
    sent: list[np.ndarray] = []
    res = rollout(model, est.policy_, 4, np.random.default_rng(0), horizon=10, on_step=lambda t, i, x, a,
                  r: sent.append(a))
    assert all(a.ndim == 2 and a.shape[1] == 1 for a in sent) and np.isfinite(res.discounted_cost).all()
    from offline_adp.algorithms.fqi_data import command_representatives

    # greedy over logged commands and the log's representative commands, sent as they are
    allowed = np.r_[ds.commands()[:, 0], command_representatives(ds.commands(), est.n_representatives)[:, 0]]
    assert all(np.isin(a[:, 0], allowed).all() for a in sent)


def test_make_env_of_a_command_mode_has_a_box_action_space():
    env = PathTracking(commands="steer_accel", heading_noise=0.0).make_env()
    assert isinstance(env.action_space, gymnasium.spaces.Box) and env.action_space.shape == (2,)
    obs, _ = env.reset(seed=0)
    nxt, reward, *_ = env.step(np.array([0.1, 0.5]))
    ref = env.problem.step_seeded(obs[None], np.array([[0.1, 0.5]]), 0)
    np.testing.assert_array_equal(nxt, ref.next_states[0])
    assert reward == -ref.costs[0]
    assert isinstance(PathTracking().make_env().action_space, gymnasium.spaces.Discrete)


def test_simulated_continuous_commands_round_trip_through_a_raw_table(tmp_path):
    """`simulate --format parquet` of a command mode writes one column per component and a
    spec with `columns = [...]`; ingesting it gives the simulated commands exactly."""
    from offline_adp.cli import main
    from offline_adp.data.dataset import TransitionDataset

    args = ["simulate", "path_tracking", "--problem-options", '{"commands": "steer_accel"}', "--demonstrations", "3",
            "--exploration", "3", "--horizon", "15", "--seed", "4"]
    assert main([*args, "--out", str(tmp_path / "ds"), "-q"]) == 0
    assert main([*args, "--format", "parquet", "--out", str(tmp_path / "t.parquet"), "-q"]) == 0
    assert main(["ingest", "parquet", str(tmp_path / "t.parquet"), "--spec", str(tmp_path / "t.spec.toml"),
                 "--out", str(tmp_path / "back"), "-q"]) == 0
    ref, back = TransitionDataset.load(tmp_path / "ds"), TransitionDataset.load(tmp_path / "back")
    assert back.info.action_table.continuous and back.info.action_table.low == ref.info.action_table.low
    np.testing.assert_array_equal(back.commands(), ref.commands())
    np.testing.assert_array_equal(back.arrays().obs, ref.arrays().obs)
