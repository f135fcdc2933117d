"""Hostile inputs to ``convert --from d4rl`` / ``--from minari``: everything that cannot be
represented is refused with one line naming the file, array and row; memory stays
bounded whatever sizes a file declares; plain and continuous-action datasets import and
equal their source arrays (the ground truth) exactly.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from offline_adp.data.info import Action, ActionTable
from offline_adp.data.validate import validate
from offline_adp.errors import IngestError, OfflineADPError, SchemaError
from offline_adp.formats import ACTION_VALUE, from_d4rl, from_minari, save_d4rl, to_d4rl
from tests.fuzz_util import peak_cli

ROOT = Path(__file__).resolve().parents[1]
PEAK_LIMIT_MB = 500


@pytest.fixture(autouse=True)
def _local_minari(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))


def _cli(*args: str, timeout: int = 300, env_extra: dict | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT), **(env_extra or {})}
    return subprocess.run([sys.executable, "-m", "offline_adp", *args], capture_output=True, text=True, env=env,
                          timeout=timeout)


_peak_cli = peak_cli


def _one_line_error(r: subprocess.CompletedProcess, *needles: str) -> str:
    err = "\n".join(ln for ln in r.stderr.splitlines() if ln.strip() and not ln.startswith("PEAK_KB="))
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert len(err) < 1500, len(err)
    for n in needles:
        assert n in err, (n, err)
    return err


def _episodes(n_ep=10, length=12, d=3, seed=0, end="mixed"):
    """Plain D4RL core arrays (no infos): episodes of ``length`` steps, contiguous observations,
    the last row terminal (even episodes) or a timeout (odd ones)."""
    rng = np.random.default_rng(seed)
    obs, nxt, act, rew, term, tout = [], [], [], [], [], []
    for e in range(n_ep):
        o = rng.normal(size=(length + 1, d))
        obs.append(o[:-1])
        nxt.append(o[1:])
        act.append(rng.integers(0, 3, length).astype(np.float64).reshape(-1, 1))
        rew.append(rng.normal(size=length))
        t = np.zeros(length, bool)
        u = np.zeros(length, bool)
        if end == "mixed":
            (t if e % 2 == 0 else u)[-1] = True
        else:
            u[-1] = True
        term.append(t)
        tout.append(u)
    return {"observations": np.vstack(obs), "next_observations": np.vstack(nxt), "actions": np.vstack(act),
            "rewards": np.concatenate(rew), "terminals": np.concatenate(term), "timeouts": np.concatenate(tout)}


def _save(path: Path, arrays: dict) -> Path:
    np.savez(path, **arrays)
    return path


# ----------------------------------------------------------------------------- what cannot be represented
def test_step_beyond_int32_is_refused_not_wrapped(tmp_path):
    a = _episodes()
    step = np.concatenate([np.arange(12)] * 10).astype(np.int64)
    step[17] = 2**40  # int32 would store it as 0
    f = _save(tmp_path / "x.npz", {**a, "infos/step": step})
    with pytest.raises(IngestError, match=r"x\.npz: infos/step: row 17: value 1099511627776 is not a whole number"):
        from_d4rl(f)
    r = _cli("convert", str(f), "--from", "d4rl", "--out", str(tmp_path / "out"))
    _one_line_error(r, "x.npz", "infos/step", "row 17")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("value", [np.nan, 0.5, 2.0, -1.0])
@pytest.mark.parametrize("field", ["terminals", "timeouts"])
def test_non_boolean_flags_are_refused(tmp_path, field, value):
    a = _episodes()
    flags = a[field].astype(np.float64)
    flags[30] = value
    f = _save(tmp_path / "x.npz", {**a, field: flags})
    with pytest.raises(IngestError, match=rf"x\.npz: {field}: row 30: value .* is not a boolean flag"):
        from_d4rl(f)
    # 0/1 as floats are flags: the same arrays with the row restored convert
    flags[30] = a[field][30]
    ds = from_d4rl({**a, field: flags})
    np.testing.assert_array_equal(ds.arrays().terminated if field == "terminals" else ds.arrays().truncated, a[field])


@pytest.mark.parametrize("field", ["observations", "next_observations", "rewards", "actions"])
def test_nan_is_refused_naming_the_array_and_row(tmp_path, field):
    a = _episodes()
    x = a[field].copy()
    x.reshape(len(x), -1)[41, 0] = np.nan
    f = _save(tmp_path / "x.npz", {**a, field: x})
    r = _cli("convert", str(f), "--from", "d4rl", "--out", str(tmp_path / "out"))
    _one_line_error(r, "x.npz", f"{field}: row 41", "NaN")


@settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(row=st.integers(0, 119), value=st.one_of(st.integers(2**31, 2**62), st.integers(-(2**62), -1)),
       field=st.sampled_from(["infos/step", "infos/action_index"]))
def test_out_of_range_integers_are_refused_at_their_row(row, value, field):
    a = _episodes()
    step = np.concatenate([np.arange(12)] * 10).astype(np.int64)
    idx = (a["actions"][:, 0]).astype(np.int64)
    arrays = {**a, "infos/step": step, "infos/action_index": idx}
    arrays[field] = arrays[field].copy()
    arrays[field][row] = value
    with pytest.raises(IngestError, match=rf"{field}: row {row}: value {value} is not a whole number"):
        from_d4rl(arrays, feature_names=["p", "q", "r"],
                  action_table=ActionTable.from_values(np.array([0.0, 1.0, 2.0])))


def test_inconsistent_rows_go_through_the_doctor_naming_file_and_row(tmp_path):
    """A terminal flag in the middle of an episode named by infos/episode_id: the doctor's
    finding names the npz file and the row in it."""
    a = _episodes()
    ep = np.repeat([f"e{k}" for k in range(10)], 12)
    term = a["terminals"].copy()
    term[53] = True  # episode e4, step 5 of 12
    f = _save(tmp_path / "x.npz", {**a, "terminals": term, "infos/episode_id": ep})
    with pytest.raises(OfflineADPError, match=r"fails the doctor.*x\.npz: row 53 \(episode e4, step 5\)"):
        from_d4rl(f)


# ----------------------------------------------------------------------------- plain D4RL, no infos
@pytest.mark.parametrize("with_next", [True, False])
@pytest.mark.parametrize("end", ["mixed", "timeouts"])
def test_plain_d4rl_without_infos_converts_and_passes_the_doctor(tmp_path, with_next, end):
    a = _episodes(end=end)
    if not with_next:
        a.pop("next_observations")
    f = _save(tmp_path / "plain.npz", a)
    out = tmp_path / "ds"
    r = _cli("convert", str(f), "--from", "d4rl", "--out", str(out))
    assert r.returncode == 0, r.stderr
    from offline_adp.data.dataset import read_dataset

    ds = read_dataset(out)
    assert validate(ds).ok
    ends = a["terminals"] | a["timeouts"]
    n_ep = int(ends.sum())
    assert ds.n_episodes == n_ep == 10
    # ground truth: without next observations, a timed-out episode's last row has no successor
    keep = np.ones(len(ends), bool) if with_next else ~(a["timeouts"] & ~a["terminals"])
    x = ds.arrays()
    np.testing.assert_array_equal(x.obs, a["observations"][keep])
    np.testing.assert_array_equal(x.cost, -a["rewards"][keep])
    np.testing.assert_array_equal(x.terminated, a["terminals"][keep])
    np.testing.assert_array_equal(ds.info.action_table.values[x.action], a["actions"][keep])
    if with_next:
        np.testing.assert_array_equal(x.next_obs, a["next_observations"])
        np.testing.assert_array_equal(x.truncated, a["timeouts"])
    else:
        inner = ~x.terminated
        np.testing.assert_array_equal(x.next_obs[inner], np.vstack([a["observations"][1:],
                                                                    a["observations"][:1]])[keep][inner])
        # every episode ends flagged: terminal, or truncated where its dropped last row was
        ep_end = np.r_[ds.episode_index[1:] != ds.episode_index[:-1], True]
        np.testing.assert_array_equal(x.terminated | x.truncated, ep_end)


def test_final_unflagged_episode_is_truncated():
    """The last episode of a file often ends without a flag (a cut log): truncated, not refused."""
    a = _episodes()
    a["timeouts"][-1] = False
    ds = from_d4rl(a)
    assert ds.n_episodes == 10 and bool(ds.arrays().truncated[-1]) and validate(ds).ok


# ----------------------------------------------------------------------------- memory bombs
def _deflate_bomb(path: Path, declared_rows: int, d: int = 17) -> Path:
    """An .npz whose `observations` member declares (declared_rows, d) float64 of zeros,
    deflated to about a thousandth of that, plus small valid core arrays."""
    header = {"descr": "<f8", "fortran_order": False, "shape": (declared_rows, d)}
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        with zf.open("observations.npy", "w", force_zip64=True) as w:
            np.lib.format.write_array_header_1_0(w, header)
            chunk = bytes(1 << 22)
            left = declared_rows * d * 8
            while left > 0:
                w.write(chunk[:min(left, len(chunk))])
                left -= len(chunk)
        for k, v in (("actions", np.zeros((declared_rows, 1))), ("rewards", np.zeros(declared_rows)),
                     ("terminals", np.zeros(declared_rows, bool))):
            with zf.open(f"{k}.npy", "w", force_zip64=True) as w:
                np.lib.format.write_array(w, v)
    return path


def test_deflate_bomb_is_refused_before_reading_with_bounded_memory(tmp_path):
    f = _deflate_bomb(tmp_path / "bomb.npz", 6_000_000)  # declares ~1.1 GB (as float64: more)
    assert f.stat().st_size < 3_000_000
    r, peak = _peak_cli("convert", str(f), "--from", "d4rl", "--out", str(tmp_path / "out"))
    _one_line_error(r, "bomb.npz", "observations", "declare", "refusing to read")
    assert peak < PEAK_LIMIT_MB, peak


def test_compressed_real_sized_file_with_sparse_flags_converts(tmp_path):
    """savez_compressed of 200,000 rows: the flag arrays compress far beyond 64x (runs of
    false), the file as a whole does not; it converts and equals its arrays."""
    rng = np.random.default_rng(3)
    n, length = 200_000, 1000
    o = rng.normal(size=(n, 4)).astype(np.float32)
    a = {"observations": o, "actions": rng.integers(0, 3, (n, 1)).astype(np.float32),
         "rewards": rng.normal(size=n).astype(np.float32), "terminals": np.zeros(n, bool),
         "timeouts": (np.arange(n) % length) == length - 1}
    f = tmp_path / "c.npz"
    np.savez_compressed(f, **a)
    ds = from_d4rl(f)
    keep = ~a["timeouts"]
    assert ds.n_episodes == n // length and len(ds) == int(keep.sum())
    np.testing.assert_array_equal(ds.arrays().obs, o[keep].astype(np.float64))


def test_declared_bytes_are_capped_whatever_the_file_size(tmp_path):
    a = _episodes()
    f = _save(tmp_path / "x.npz", a)  # uncompressed: declared == stored
    assert len(from_d4rl(f)) == 120
    with pytest.raises(IngestError, match=r"x\.npz: .*arrays declare \d+ bytes .*refusing to read"):
        from_d4rl(f, max_bytes=4096)


def test_header_declaring_more_than_stored_is_refused(tmp_path):
    f = tmp_path / "lie.npz"
    with zipfile.ZipFile(f, "w") as zf:
        with zf.open("observations.npy", "w") as w:
            np.lib.format.write_array_header_1_0(w, {"descr": "<f8", "fortran_order": False, "shape": (10**9, 4)})
            w.write(bytes(64))
    r, peak = _peak_cli("convert", str(f), "--from", "d4rl", "--out", str(tmp_path / "out"))
    _one_line_error(r, "lie.npz", "observations")
    assert peak < PEAK_LIMIT_MB


# ----------------------------------------------------------------------------- continuous actions
@pytest.mark.parametrize("k", [1, 2, 6])
def test_continuous_d4rl_actions_import_exactly(tmp_path, k):
    rng = np.random.default_rng(k)
    a = _episodes(n_ep=40, length=100)
    a["actions"] = rng.uniform(-2, 2, size=(len(a["rewards"]), k))
    f = _save(tmp_path / "c.npz", a)
    out = tmp_path / "ds"
    r = _cli("convert", str(f), "--from", "d4rl", "--out", str(out))
    assert r.returncode == 0, r.stderr
    from offline_adp.data.dataset import read_dataset

    ds = read_dataset(out)
    table = ds.info.action_table
    assert table.kind == "continuous" and len(table) <= 4096  # exact commands; the bins a coarse view
    got = np.column_stack([ds.column(ACTION_VALUE + dname) for dname in table.dims])
    np.testing.assert_array_equal(got, a["actions"])  # the exact commands
    # each index is the bin cell of its command; cell values are the mean command in them
    x = ds.arrays()
    for cell in np.unique(x.action):
        np.testing.assert_allclose(table.values[cell], a["actions"][x.action == cell].mean(axis=0), rtol=1e-12)
    np.testing.assert_array_equal(x.obs, a["observations"])
    # and back out: to_d4rl gives the exact commands
    np.testing.assert_array_equal(to_d4rl(ds)["actions"], a["actions"])
    save_d4rl(ds, tmp_path / "back.npz")
    np.testing.assert_array_equal(from_d4rl(tmp_path / "back.npz").column(ACTION_VALUE + table.dims[0]),
                                  a["actions"][:, 0])


def test_error_messages_are_capped():
    with pytest.raises(SchemaError) as ei:
        ActionTable(actions=tuple(Action("same", (float(i),)) for i in range(4000)))
    assert len(str(ei.value)) < 300
    table = ActionTable.from_values(np.arange(4000, dtype=float))
    with pytest.raises(IngestError) as ei:
        from_d4rl({**_episodes(), "actions": np.full((120, 1), -7.5)}, action_table=table)
    assert len(str(ei.value)) < 600 and "4000 in all" in str(ei.value)


# ----------------------------------------------------------------------------- Minari
def _pendulum_minari(dataset_id="test/pendulum-v0", episodes=4, steps=100):
    """A Box-action Minari dataset from real Pendulum-v1 rollouts (minari's own writer)."""
    import gymnasium as gym
    import minari
    from minari.data_collector import EpisodeBuffer

    env = gym.make("Pendulum-v1", max_episode_steps=steps)
    bufs = []
    for s in range(episodes):
        o, _ = env.reset(seed=s)
        env.action_space.seed(s)
        obs, acts, rews, terms, truncs = [o], [], [], [], []
        while True:
            act = env.action_space.sample()
            o, r, te, tr, _ = env.step(act)
            obs.append(o)
            acts.append(act)
            rews.append(r)
            terms.append(te)
            truncs.append(tr)
            if te or tr:
                break
        bufs.append(EpisodeBuffer(id=s, observations=np.array(obs), actions=np.array(acts), rewards=np.array(rews),
                                  terminations=np.array(terms), truncations=np.array(truncs), infos={}))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return minari.create_dataset_from_buffers(dataset_id, bufs, env=env, algorithm_name="test", author="t",
                                                  author_email="t@example.org", code_permalink="https://example.org",
                                                  description="pendulum", data_format="arrow")


@pytest.mark.parametrize("steps", [100, 20])  # 400 distinct commands (binned) / 80 (exact table)
def test_continuous_minari_pendulum_imports_equal_to_the_source(tmp_path, steps):
    mds = _pendulum_minari(steps=steps)
    src = list(mds.iterate_episodes())
    out = tmp_path / "ds"
    r = _cli("convert", "test/pendulum-v0", "--from", "minari", "--out", str(out),
             env_extra={"MINARI_DATASETS_PATH": os.environ["MINARI_DATASETS_PATH"]})
    assert r.returncode == 0, r.stderr
    from offline_adp.data.dataset import read_dataset

    ds = read_dataset(out)
    x = ds.arrays()
    assert validate(ds).ok and ds.n_episodes == len(src)
    np.testing.assert_array_equal(x.obs, np.vstack([e.observations[:-1] for e in src]).astype(np.float64))
    np.testing.assert_array_equal(x.next_obs, np.vstack([e.observations[1:] for e in src]).astype(np.float64))
    np.testing.assert_array_equal(x.cost, -np.concatenate([e.rewards for e in src]))
    np.testing.assert_array_equal(x.terminated, np.concatenate([e.terminations for e in src]))
    np.testing.assert_array_equal(x.truncated, np.concatenate([e.truncations for e in src]))
    np.testing.assert_array_equal(x.step, np.concatenate([np.arange(len(e.rewards)) for e in src]))
    acts = np.vstack([e.actions for e in src]).astype(np.float64)
    table = ds.info.action_table
    if ACTION_VALUE + "a" in ds.table.column_names:
        assert steps == 100 and table.kind == "continuous" and table.low == (-2.0,) and table.high == (2.0,)
        np.testing.assert_array_equal(ds.column(ACTION_VALUE + "a").reshape(-1, 1), acts)
    else:
        assert steps == 20 and table.kind == "discrete" and len(table) == len(np.unique(acts))
        np.testing.assert_array_equal(table.values[x.action], acts)


def _minari_plain(tmp_path):
    mds = _pendulum_minari("test/p-v0", episodes=2, steps=10)
    return Path(mds.storage.data_path).parent


def _break_missing_metadata(root: Path) -> str:
    (root / "data" / "metadata.json").unlink()
    return "no local Minari dataset"


def _break_metadata_not_json(root: Path) -> str:
    (root / "data" / "metadata.json").write_text("{not json")
    return "metadata.json: not valid JSON"


def _break_metadata_not_object(root: Path) -> str:
    (root / "data" / "metadata.json").write_text("[1, 2]")
    return "a JSON object is required"


def _break_missing_episode(root: Path) -> str:
    (root / "data" / "1" / "part-0.arrow").unlink()
    return "total_episodes = 2 but 1 were read"


def _break_missing_episode_dir(root: Path) -> str:
    import shutil

    shutil.rmtree(root / "data" / "1")
    return "Minari"


def _break_truncated_episode(root: Path) -> str:
    p = root / "data" / "0" / "part-0.arrow"
    p.write_bytes(p.read_bytes()[:200])
    return "not a readable Minari dataset"


def _break_observation_shape(root: Path) -> str:
    m = json.loads((root / "data" / "metadata.json").read_text())
    space = json.loads(m["observation_space"])
    space.update(shape=[5], low=[-1.0] * 5, high=[1.0] * 5)
    m["observation_space"] = json.dumps(space)
    (root / "data" / "metadata.json").write_text(json.dumps(m))
    return "not a readable Minari dataset"


def _break_action_space(root: Path) -> str:
    m = json.loads((root / "data" / "metadata.json").read_text())
    m["action_space"] = json.dumps({"type": "Nonsense"})
    (root / "data" / "metadata.json").write_text(json.dumps(m))
    return "not a readable Minari dataset"


def _break_action_shape(root: Path) -> str:
    m = json.loads((root / "data" / "metadata.json").read_text())
    space = json.loads(m["action_space"])
    space.update(shape=[3], low=[-2.0] * 3, high=[2.0] * 3)
    m["action_space"] = json.dumps(space)
    (root / "data" / "metadata.json").write_text(json.dumps(m))
    return "not a readable Minari dataset"


def _break_float_terminations(root: Path) -> str:
    """Episode 0's terminations rewritten as floats (0.5, NaN) in its arrow file."""
    import pyarrow as pa
    import pyarrow.ipc as ipc

    p = root / "data" / "0" / "part-0.arrow"
    t = ipc.open_file(p).read_all()
    n = t.num_rows
    t = t.set_column(t.schema.get_field_index("terminations"), "terminations",
                     pa.array(np.r_[0.0, 0.5, np.zeros(n - 3), np.nan]))
    with ipc.new_file(p, t.schema) as w:
        w.write_table(t)
    return "not a readable Minari dataset"


BREAKS = {f.__name__[len("_break_"):]: f for f in (
    _break_missing_metadata, _break_metadata_not_json, _break_metadata_not_object, _break_missing_episode,
    _break_missing_episode_dir,
    _break_truncated_episode, _break_observation_shape, _break_action_space, _break_action_shape,
    _break_float_terminations)}


@pytest.mark.parametrize("kind", sorted(BREAKS))
def test_crafted_minari_directories_are_one_clear_error(tmp_path, kind):
    root = _minari_plain(tmp_path)
    assert len(from_minari(root)) == 20  # intact, it imports
    needle = BREAKS[kind](root)
    with pytest.raises(IngestError, match=needle) as ei:
        from_minari(root)
    assert "\n" not in str(ei.value) and len(str(ei.value)) < 1000
    r = _cli("convert", str(root), "--from", "minari", "--out", str(tmp_path / "out"))
    _one_line_error(r, needle)
    assert not (tmp_path / "out").exists()


def test_convert_from_a_dataset_directory_runs_the_doctor(tmp_path):
    """A hand-edited dataset directory (a NaN cost) is not exported: the finding names the
    part file and row."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    ds = from_d4rl(_episodes())
    ds.save(tmp_path / "ds")
    part = tmp_path / "ds" / "data" / "part-00000.parquet"
    t = pq.read_table(part)
    cost = t.column("cost").to_numpy().copy()
    cost[7] = np.nan
    pq.write_table(t.set_column(t.schema.get_field_index("cost"), "cost", pa.array(cost)), part)
    r = _cli("convert", str(tmp_path / "ds"), "--to", "d4rl", "--out", str(tmp_path / "x.npz"))
    _one_line_error(r, "part-00000.parquet", "row 7", "cost")
    assert not (tmp_path / "x.npz").exists()


def test_a_minari_datacollector_dataset_with_continuous_actions_imports_equal_to_the_source(tmp_path):
    """The issue's Done-when: a Box-action dataset made with minari's own DataCollector
    (Pendulum-v1, random torques) converts and equals the source arrays."""
    import gymnasium as gym
    from minari import DataCollector

    pytest.importorskip("jax")  # DataCollector's episode buffers need it (minari[create])
    env = DataCollector(gym.make("Pendulum-v1", max_episode_steps=30), record_infos=False, data_format="arrow")
    for s in range(3):
        env.reset(seed=s)
        env.action_space.seed(s)
        done = False
        while not done:
            _, _, te, tr, _ = env.step(env.action_space.sample())
            done = te or tr
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mds = env.create_dataset("test/collected-v0", algorithm_name="random", author="t",
                                 author_email="t@example.org", code_permalink="https://example.org",
                                 description="pendulum, random torques")
    src = list(mds.iterate_episodes())
    out = tmp_path / "ds"
    r = _cli("convert", "test/collected-v0", "--from", "minari", "--out", str(out),
             env_extra={"MINARI_DATASETS_PATH": os.environ["MINARI_DATASETS_PATH"]})
    assert r.returncode == 0, r.stderr
    from offline_adp.data.dataset import read_dataset

    ds = read_dataset(out)
    x = ds.arrays()
    assert validate(ds).ok and ds.n_episodes == 3 and len(ds) == 90
    np.testing.assert_array_equal(x.obs, np.vstack([e.observations[:-1] for e in src]).astype(np.float64))
    np.testing.assert_array_equal(x.next_obs, np.vstack([e.observations[1:] for e in src]).astype(np.float64))
    np.testing.assert_array_equal(x.cost, -np.concatenate([e.rewards for e in src]))
    acts = np.vstack([e.actions for e in src]).astype(np.float64)
    table = ds.info.action_table
    np.testing.assert_array_equal(table.values[x.action], acts)  # 90 distinct torques: an exact table


@pytest.mark.parametrize("kind", ["empty", "behavior_prob_2d"])
def test_empty_or_misshapen_d4rl_arrays_are_one_clear_error(tmp_path, kind):
    arrays = _episodes()
    n = len(arrays["observations"])
    if kind == "empty":
        arrays = {k: v[:0] for k, v in arrays.items()}
    else:
        arrays["infos/behavior_prob"] = np.full((n, 2), 0.5)
    f = tmp_path / "bad.npz"
    np.savez(f, **arrays)
    r = _cli("convert", str(f), "--from", "d4rl", "--out", str(tmp_path / "out"))
    _one_line_error(r, "bad.npz", "no transitions" if kind == "empty" else "infos/behavior_prob")
