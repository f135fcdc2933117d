"""D4RL arrays, Minari datasets and the LeRobot layout: round trips keep every transition."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from offline_adp.data.info import ActionTable
from offline_adp.errors import IngestError, OfflineADPError
from offline_adp.formats import (
    from_d4rl,
    from_minari,
    save_d4rl,
    to_d4rl,
    to_lerobot,
    to_minari,
)
from offline_adp.simulate import simulate


@pytest.fixture(scope="module")
def ds():
    """Path tracking: 7 features with units, 7 steering commands, propensities, two sources."""
    return simulate("path_tracking", 3, 3, seed=5, horizon=40)


@pytest.fixture(autouse=True)
def _local_minari(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))


def _same(a, b):
    """Every transition equal (values exactly, same order) and the same metadata."""
    assert a.info.to_dict() == b.info.to_dict()
    fa, fb = a.to_pandas(), b.to_pandas()
    cols = sorted(set(fa.columns) - {"src_file"})
    assert sorted(set(fb.columns) - {"src_file"}) == cols
    for c in cols:
        x, y = fa[c], fb[c]
        if isinstance(x.dtype, pd.CategoricalDtype) or isinstance(y.dtype, pd.CategoricalDtype):
            x, y = x.astype(str), y.astype(str)
        np.testing.assert_array_equal(x.to_numpy(), y.to_numpy(), err_msg=c)


def test_d4rl_round_trip_is_exact(ds, tmp_path):
    arrays = to_d4rl(ds)
    a = ds.arrays()
    np.testing.assert_array_equal(arrays["actions"], ds.info.action_table.values[a.action])
    np.testing.assert_array_equal(arrays["rewards"], -a.cost)
    np.testing.assert_array_equal(arrays["timeouts"], a.truncated)
    _same(from_d4rl(arrays), ds)
    path = save_d4rl(ds, tmp_path / "pt.npz")
    _same(from_d4rl(path), ds)


def test_d4rl_plain_arrays_without_our_extras(ds):
    """Only the D4RL core keys: actions matched to the table, episodes from terminals|timeouts,
    next states from the next row (an episode's last row is dropped unless terminal)."""
    full = to_d4rl(ds)
    core = {k: full[k] for k in ("observations", "actions", "rewards", "terminals", "timeouts")}
    got = from_d4rl(core, feature_names=ds.feature_names, action_table=ds.info.action_table)
    a = ds.arrays()
    last = np.r_[a.episode[1:] != a.episode[:-1], True]
    keep = ~last | a.terminated
    assert len(got) == int(keep.sum())
    g = got.arrays()
    np.testing.assert_array_equal(g.obs, a.obs[keep])
    np.testing.assert_array_equal(g.action, a.action[keep])
    np.testing.assert_array_equal(g.cost, a.cost[keep])
    inner = (~last)[keep]
    np.testing.assert_array_equal(g.next_obs[inner], a.next_obs[keep][inner])  # contiguous simulated episodes
    assert got.n_episodes == ds.n_episodes
    with pytest.raises(IngestError, match=r"row 0: action \[9\.0\] is not in the action table"):
        from_d4rl({**core, "actions": np.full((len(ds), 1), 9.0)}, action_table=ds.info.action_table)
    with pytest.raises(IngestError, match="missing D4RL arrays"):
        from_d4rl({"observations": core["observations"]})


def test_minari_round_trip_is_exact(ds, tmp_path):
    import minari

    path = to_minari(ds, "offline_adp/pt-v0")
    assert path.is_relative_to(tmp_path / "minari")  # local only: under MINARI_DATASETS_PATH
    mds = minari.load_dataset("offline_adp/pt-v0", download=False)
    assert mds.total_episodes == ds.n_episodes and mds.total_steps == len(ds)
    ep = next(mds.iterate_episodes())
    a = ds.arrays()
    T = int((a.episode == 0).sum())
    np.testing.assert_array_equal(ep.observations, np.vstack([a.obs[:T], a.next_obs[T - 1:T]]))
    np.testing.assert_array_equal(ep.actions, a.action[:T])
    _same(from_minari("offline_adp/pt-v0"), ds)
    _same(from_minari(mds), ds)
    _same(from_minari(path), ds)
    with pytest.raises(OfflineADPError, match="already exists"):
        to_minari(ds, "offline_adp/pt-v0")


def test_minari_without_our_metadata_and_missing_datasets(ds, tmp_path):
    import gymnasium as gym
    import minari
    from minari.data_collector import EpisodeBuffer

    rng = np.random.default_rng(0)
    obs = rng.normal(size=(6, 2))
    buf = [EpisodeBuffer(id=0, observations=obs, actions=np.array([0, 2, 1, 1, 0]), rewards=-rng.random(5),
                         terminations=np.array([0, 0, 0, 0, 1], bool), truncations=np.zeros(5, bool))]
    minari.create_dataset_from_buffers("plain-v0", buf,
                                       observation_space=gym.spaces.Box(-np.inf, np.inf, (2,), np.float64),
                                       action_space=gym.spaces.Discrete(3), data_format="arrow")
    got = from_minari("plain-v0", feature_names=["a", "b"])
    assert got.feature_names == ["a", "b"] and got.n_actions == 3
    np.testing.assert_array_equal(got.arrays().obs, obs[:-1])
    np.testing.assert_array_equal(got.arrays().next_obs, obs[1:])
    np.testing.assert_array_equal(got.arrays().cost, -np.asarray(buf[0].rewards))
    with pytest.raises(IngestError, match="nothing is downloaded"):
        from_minari("D4RL/door/human-v2")


def test_minari_refuses_non_contiguous_episodes(ds):
    a = ds.arrays()
    broken = ds.from_arrays(ds.info, episode_id=ds.column("episode_id"), step=a.step, obs=a.obs, action=a.action,
                            cost=a.cost,
                            next_obs=a.next_obs + (np.arange(len(ds)) == 3)[:, None], terminated=a.terminated,
                            truncated=a.truncated)
    with pytest.raises(OfflineADPError, match="contiguous"):
        to_minari(broken, "broken-v0")


def test_lerobot_layout_frames_are_the_transitions(ds, tmp_path):
    root = to_lerobot(ds, tmp_path / "lr", fps=10.0)
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["total_episodes"] == ds.n_episodes and info["total_frames"] == len(ds)
    assert info["features"]["observation.state"]["names"] == ds.feature_names
    files = sorted((root / "data").rglob("episode_*.parquet"))
    assert len(files) == ds.n_episodes
    frames = pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)
    a = ds.arrays()
    np.testing.assert_array_equal(np.stack(frames["observation.state"]), a.obs)
    np.testing.assert_array_equal(np.stack(frames["next.observation.state"]), a.next_obs)
    np.testing.assert_array_equal(np.stack(frames["action"]), ds.info.action_table.values[a.action])
    np.testing.assert_array_equal(frames["next.reward"], -a.cost)
    np.testing.assert_array_equal(frames["next.done"], a.terminated)
    np.testing.assert_array_equal(frames["index"], np.arange(len(ds)))
    eps = [json.loads(x) for x in (root / "meta" / "episodes.jsonl").read_text().splitlines()]
    assert [e["length"] for e in eps] == np.bincount(a.episode).tolist()


def test_convert_cli(ds, tmp_path):
    from offline_adp.cli import main

    ds.save(tmp_path / "data")
    assert main(["convert", str(tmp_path / "data"), "--to", "d4rl", "--out", str(tmp_path / "x.npz")]) == 0
    assert main(["convert", str(tmp_path / "x.npz"), "--from", "d4rl", "--to", "minari", "--out", "cli/pt-v0"]) == 0
    assert main(["convert", "cli/pt-v0", "--from", "minari", "--out", str(tmp_path / "back")]) == 0
    from offline_adp.data.dataset import read_dataset

    _same(read_dataset(tmp_path / "back"), ds)
    assert main(["convert", str(tmp_path / "data"), "--to", "lerobot", "--out", str(tmp_path / "lr")]) == 0
    assert main(["convert", str(tmp_path / "data"), "--to", "d4rl", "--out", str(tmp_path / "x.npz")]) == 2  # exists


def test_action_table_mismatch_is_named():
    t = ActionTable.from_values([[0.0, 1.0]], dims=("a", "b"))
    from offline_adp.formats import _action_indices

    with pytest.raises(IngestError, match="1 components, the action table 2"):
        _action_indices(np.zeros((3, 1)), t, "x")


def test_continuous_commands_are_exported_exactly_or_refused(tmp_path):
    """LeRobot wrote each command's coarse bin value (16 values for 2454 logged commands, off by
    up to 0.33); Minari wrote a Discrete space and dropped the commands (its import then failed
    the doctor). LeRobot now writes the commands as logged; Minari refuses, naming the formats that keep them."""
    from offline_adp.errors import ExportError
    from tests.test_continuous_deploy import command_dataset

    rng = np.random.default_rng(0)
    n = 60
    u = rng.uniform(-1, 1, (n, 2))
    x = rng.normal(size=(n, 2))
    ds = command_dataset(x, u, rng.random(n), x + 0.1, np.repeat(np.arange(6), 10), np.tile(np.arange(10), 6),
                         [-1.0, -1.0], [1.0, 1.0], ["steer", "throttle"])
    root = to_lerobot(ds, tmp_path / "lr", fps=10.0)
    frames = pd.concat([pd.read_parquet(f) for f in sorted((root / "data").rglob("episode_*.parquet"))],
                       ignore_index=True)
    np.testing.assert_array_equal(np.stack(frames["action"]), ds.commands())
    with pytest.raises(ExportError, match="continuous commands .* --to d4rl or --to lerobot"):
        to_minari(ds, "test/cont-v0", datasets_path=tmp_path / "minari")
