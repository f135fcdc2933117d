"""gym:ENV_ID simulators: a registered gymnasium environment as a reset model for rollouts."""

from __future__ import annotations

import json

import gymnasium
import numpy as np
import pandas as pd
import pytest

from offline_adp.cli import main
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.envs.gym import GymResetModel, record_random_log, resolve_simulator
from offline_adp.errors import AccessModelError, OfflineADPError

CARTPOLE = DatasetInfo(features=tuple(Feature(n) for n in ("cart_x", "cart_v", "pole", "pole_rate")),
                       action_table=ActionTable.from_values([0.0, 1.0]), gamma=0.99)


def _log_table(log: dict, features: list[str], columns: tuple[str, ...]) -> pd.DataFrame:
    """A :func:`record_random_log` log as a user's table: ``columns`` names the episode, step,
    action, reward, terminated and truncated columns; next-state features get a "2"."""
    episode, step, action, reward, terminated, truncated = columns
    return pd.DataFrame({episode: log["episode"].astype(int), step: log["step"].astype(int), action: log["action"],
                         reward: log["reward"], terminated: log["terminated"],
                         truncated: log["truncated"] & ~log["terminated"],
                         **{n: log["obs"][:, j] for j, n in enumerate(features)},
                         **{n + "2": log["next_obs"][:, j] for j, n in enumerate(features)}})


def test_steps_match_a_plain_gymnasium_loop_with_the_same_seeds():
    model = GymResetModel("CartPole-v1", CARTPOLE)
    x = model.initial_states(3, np.random.default_rng(7))
    seeds = np.random.default_rng(7).integers(0, 2**31 - 1, size=3)  # how initial_states draws its seeds
    envs = [gymnasium.make("CartPole-v1") for _ in seeds]
    ref = np.array([e.reset(seed=int(s))[0] for e, s in zip(envs, seeds, strict=True)], dtype=np.float64)
    np.testing.assert_array_equal(x, ref)
    actions = np.random.default_rng(1).integers(0, 2, size=(30, 3))
    alive = np.arange(3)
    for t in range(30):
        r = model.step(x[alive], actions[t, alive], np.random.default_rng(0))
        for j, i in enumerate(alive):
            obs, rew, term, _, _ = envs[i].step(int(actions[t, i]))
            np.testing.assert_array_equal(r.next_states[j], obs)
            assert r.costs[j] == -rew and r.terminated[j] == term
        x[alive] = r.next_states
        alive = alive[~r.terminated]
        if not len(alive):
            break
    with pytest.raises(AccessModelError, match="reset model"):
        model.step(np.full((1, 4), 123.0), np.zeros(1, int), np.random.default_rng(0))


def test_widths_and_actions_are_checked():
    three = DatasetInfo(features=(Feature("a"), Feature("b"), Feature("c")),
                        action_table=ActionTable.from_values([0.0, 1.0]))
    with pytest.raises(OfflineADPError, match="4 entries, the dataset has 3 features"):
        resolve_simulator("gym:CartPole-v1", three)
    bad = DatasetInfo(features=CARTPOLE.features, action_table=ActionTable.from_values([-1.0, 1.0]))
    with pytest.raises(OfflineADPError, match=r"action values \[-1.0\]"):
        resolve_simulator("gym:CartPole-v1", bad)
    with pytest.raises(OfflineADPError, match="cannot make"):
        resolve_simulator("gym:NoSuchEnv-v0", CARTPOLE)
    assert resolve_simulator("none", CARTPOLE) is None


SPEC = """
kind = "transitions"
name = "cartpole log"
[episode]
id = "run"
step = "tick"
[observations]
columns = ["cart_x", "cart_v", "pole", "pole_rate"]
next_columns = ["cart_x2", "cart_v2", "pole2", "pole_rate2"]
[action]
column = "push"
type = "discrete"
values = [0, 1]
[cost]
reward = "r"
[end]
terminated = "fell"
truncated = "time_up"
[source]
value = "exploration"
[hints]
gamma = 0.99
"""


@pytest.mark.integration
def test_evaluate_a_cartpole_run_in_gymnasium(tmp_path, capsys):
    log = record_random_log("CartPole-v1", 1500, seed=3)
    names = ["cart_x", "cart_v", "pole", "pole_rate"]
    df = _log_table(log, names, ("run", "tick", "push", "r", "fell", "time_up"))
    df.to_parquet(tmp_path / "cartpole.parquet")
    (tmp_path / "spec.toml").write_text(SPEC)
    (tmp_path
     / "fqi.toml").write_text('[fqi]\nn_iterations = 8\nmode = "frozen"\n[fqi.regressor_params]\nn_estimators = '
                              '10\nn_jobs = 1\n')
    ds, run = tmp_path / "ds", tmp_path / "run"
    assert main(["ingest", "parquet", str(tmp_path / "cartpole.parquet"), "--spec", str(tmp_path / "spec.toml"),
                 "--out", str(ds), "-q"]) == 0
    assert main(["fit", str(ds), "--config", str(tmp_path / "fqi.toml"), "--out", str(run), "-q"]) == 0
    assert "verdict: " in capsys.readouterr().out
    assert main(["evaluate", str(run), "--simulator", "gym:CartPole-v1", "--episodes", "16", "--bootstrap", "5",
                 "--fqe-bootstrap", "0", "-q"]) == 0
    out = capsys.readouterr().out
    assert "no demonstrator" in out
    m = json.loads((run / "evaluation" / "metrics.json").read_text())
    r = m["rollout"]
    assert m["simulator"] == "gym:CartPole-v1" and "demonstrator" not in r and "comparison skipped" in r["note"]
    p = r["policy"]
    assert p["n_episodes"] == 16 and 1 <= p["mean_length"] <= r["horizon"]
    # every CartPole step pays reward 1: the discounted cost of an episode of length L is -(1 - g^L) / (1 - g)
    L = p["mean_length"]
    # Jensen: the cost is a convex function of L, so its mean is at least the cost at the mean length
    assert -(1 - 0.99**L) / (1 - 0.99) - 1e-9 <= p["mean_discounted_cost"] <= -1.0
    # 2 != 4 features
    assert main(["evaluate", str(run), "--simulator", "gym:MountainCar-v0", "--episodes", "4", "-q"]) == 2
    assert "4 features" in capsys.readouterr().err


PENDULUM_TABLE = ActionTable.from_values([-1.5, 0.25, 2.0])
PENDULUM = DatasetInfo(features=tuple(Feature(n) for n in ("cos_th", "sin_th", "omega")),
                       action_table=PENDULUM_TABLE, gamma=0.95)


def test_box_actions_step_like_a_plain_gymnasium_loop():
    """A continuous-action environment: action i is the box action [values[i]]."""
    model = GymResetModel("Pendulum-v1", PENDULUM)
    x = model.initial_states(2, np.random.default_rng(4))
    seeds = np.random.default_rng(4).integers(0, 2**31 - 1, size=2)
    envs = [gymnasium.make("Pendulum-v1") for _ in seeds]
    ref = np.array([e.reset(seed=int(s))[0] for e, s in zip(envs, seeds, strict=True)], dtype=np.float64)
    np.testing.assert_array_equal(x, ref)
    values = np.array([-1.5, 0.25, 2.0], dtype=np.float32)
    actions = np.random.default_rng(2).integers(0, 3, size=(25, 2))
    for t in range(25):
        r = model.step(x, actions[t], np.random.default_rng(0))
        for i in range(2):
            obs, rew, term, _, _ = envs[i].step(values[actions[t, i]:actions[t, i] + 1])
            np.testing.assert_array_equal(r.next_states[i], obs)
            assert r.costs[i] == -rew and r.terminated[i] == term
        x = r.next_states


def test_box_action_tables_are_checked():
    wide = DatasetInfo(features=PENDULUM.features, action_table=ActionTable.from_values([-3.0, 0.0, 2.0]))
    with pytest.raises(OfflineADPError, match=r"action\(s\) \[0\] with values \[\[-3.0\]\] are outside the action box"):
        resolve_simulator("gym:Pendulum-v1", wide)
    two = DatasetInfo(features=PENDULUM.features,
                      action_table=ActionTable.from_values([[0.0, 1.0], [1.0, 0.0]], dims=("u", "w")))
    with pytest.raises(OfflineADPError, match="vectors of 1 numbers.*shape \\(2, 2\\)"):
        resolve_simulator("gym:Pendulum-v1", two)
    with pytest.raises(OfflineADPError, match="unbounded"):
        record_random_log("offline_adp_test/Echo-v0", 10, action_space=gymnasium.spaces.Box(-np.inf, np.inf, (1,)))


class _Echo(gymnasium.Env):
    """Observes the last action it was given (two numbers); ends after 3 steps."""

    observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (2,))

    def __init__(self, action_space=None):
        self.action_space = action_space if action_space is not None else gymnasium.spaces.Discrete(3, start=1)
        self.received = []

    def reset(self, *, seed=None, options=None):
        self.t = 0
        return np.zeros(2, np.float32), {}

    def step(self, action):
        self.received.append(action)
        self.t += 1
        a = np.atleast_1d(np.asarray(action, np.float32))
        obs = np.array([a[0], a[-1]], np.float32) + np.float32(0.001 * self.t)
        if isinstance(action, np.ndarray):
            action[...] = 99  # an environment that scribbles on its action must not change the table
        return obs, 0.0, self.t >= 3, False, {}


@pytest.fixture(autouse=True)
def _echo_env():
    gymnasium.register("offline_adp_test/Echo-v0", entry_point=_Echo)
    yield
    del gymnasium.envs.registry["offline_adp_test/Echo-v0"]


def _echo(values, space, dims=("a",)):
    info = DatasetInfo(features=(Feature("p"), Feature("q")), action_table=ActionTable.from_values(values, dims=dims))
    return GymResetModel("offline_adp_test/Echo-v0", info, action_space=space)


def test_echo_environment_receives_the_table_values():
    """Discrete with a nonzero start, a two-entry box, a value within the slack (clipped)."""
    cases = [([[1.0], [3.0]], gymnasium.spaces.Discrete(3, start=1), ("a",), [[1.0, 1.0], [3.0, 3.0]]),
             ([[0.5, -1.0], [2.0 + 1e-7, 0.25]], gymnasium.spaces.Box(-1.0, 2.0, (2,)), ("u", "w"),
              [[0.5, -1.0], [2.0, 0.25]])]
    for values, space, dims, sent in cases:
        model = _echo(values, space, dims)
        for rep in range(2):  # the second pass sees the table unchanged by the environment's scribbling
            x = model.initial_states(2, np.random.default_rng(rep))
            r = model.step(x, np.array([0, 1]), np.random.default_rng(0))
            np.testing.assert_allclose(r.next_states - 0.001, np.array(sent), rtol=0, atol=1e-6)
    with pytest.raises(OfflineADPError, match=r"action values \[4.0\] are not actions"):
        _echo([[1.0], [4.0]], gymnasium.spaces.Discrete(3, start=1))
    with pytest.raises(OfflineADPError, match=r"action values \[nan\]"):
        _echo([[1.0], [np.nan]], gymnasium.spaces.Discrete(3, start=1))


def test_box_bounds_are_checked_side_by_side():
    half = gymnasium.spaces.Box(np.array([0.0, -np.inf], np.float32), np.array([np.inf, 1.0], np.float32))
    _echo([[0.0, 1.0], [1e6, -1e6]], half, ("u", "w"))  # within an open side: fine
    for values, bad in ([[-5.0, 0.0], [1.0, 0.0]], "[0]"), ([[1.0, 0.0], [1.0, 7.0]], "[1]"), ([[np.nan, 0.0]], "[0]"):
        with pytest.raises(OfflineADPError, match=f"action\\(s\\) \\{bad[0]}{bad[1:-1]}\\] with values"):
            _echo(values, half, ("u", "w"))
    ints = gymnasium.spaces.Box(0, 5, (1,), np.int64)
    with pytest.raises(OfflineADPError, match=r"holds integers.*\[\[2.5\]\]"):
        _echo([[1.0], [2.5]], ints)
    _echo([[1.0], [5.0]], ints)


def test_random_logs_draw_within_the_action_space():
    log = record_random_log("offline_adp_test/Echo-v0", 200, seed=0)
    assert set(np.unique(log["action"])) == {1, 2, 3}
    log = record_random_log("offline_adp_test/Echo-v0", 300, seed=0,
                            action_space=gymnasium.spaces.Box(0, 2, (1,), np.int64))
    assert set(np.unique(log["action"])) == {0, 1, 2}
    log = record_random_log("offline_adp_test/Echo-v0", 50, seed=0, action_space=gymnasium.spaces.Box(-1.0, 1.0, (2,)))
    assert log["action"].shape == (len(log["step"]), 2) and np.abs(log["action"]).max() <= 1.0


PENDULUM_SPEC = """
kind = "transitions"
name = "pendulum log"
[episode]
id = "ep"
step = "t"
[observations]
columns = ["c", "s", "w"]
next_columns = ["c2", "s2", "w2"]
[action]
column = "torque"
type = "continuous"
n_bins = 5
[cost]
reward = "r"
[end]
terminated = "term"
truncated = "trunc"
[source]
value = "exploration"
[hints]
gamma = 0.95
"""


@pytest.mark.integration
def test_evaluate_a_pendulum_run_with_binned_torques_in_gymnasium(tmp_path, capsys):
    """Continuous commands binned at ingestion, rolled out in a continuous-action environment."""
    log = record_random_log("Pendulum-v1", 1200, seed=5)
    assert log["action"].shape == (len(log["step"]),) and np.abs(log["action"]).max() <= 2.0
    names = ["c", "s", "w"]
    df = _log_table(log, names, ("ep", "t", "torque", "r", "term", "trunc"))
    df.to_csv(tmp_path / "pendulum.csv", index=False)
    (tmp_path / "spec.toml").write_text(PENDULUM_SPEC)
    (tmp_path
     / "fqi.toml").write_text('[fqi]\nn_iterations = 5\n[fqi.regressor_params]\nn_estimators = 10\nn_jobs = 1\n')
    ds, run = tmp_path / "ds", tmp_path / "run"
    assert main(["ingest", "parquet", str(tmp_path / "pendulum.csv"), "--spec", str(tmp_path / "spec.toml"), "--out",
                 str(ds), "-q"]) == 0
    assert main(["fit", str(ds), "--config", str(tmp_path / "fqi.toml"), "--out", str(run), "-q"]) == 0
    assert main(["evaluate", str(run), "--simulator", "gym:Pendulum-v1", "--episodes", "6", "--bootstrap", "5",
                 "--fqe-bootstrap", "0", "-q"]) == 0
    capsys.readouterr()
    m = json.loads((run / "evaluation" / "metrics.json").read_text())
    r = m["rollout"]
    p = r["policy"]
    assert m["simulator"] == "gym:Pendulum-v1" and p["n_episodes"] == 6
    # Pendulum never terminates: every episode runs the horizon; each step's cost is in [0, pi^2 + 0.1 * 8^2 + 0.001 *
    # 2^2]
    assert p["mean_length"] == r["horizon"]
    worst = (np.pi**2 + 0.1 * 64 + 0.001 * 4) * (1 - 0.95 ** r["horizon"]) / (1 - 0.95)
    assert 0.0 < p["mean_discounted_cost"] < worst
