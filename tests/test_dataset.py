"""TransitionDataset and dataset directories."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from offline_adp.data import io as dio
from offline_adp.data import schema as S
from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import (
    DatasetNotFoundError,
    FormatVersionWarning,
    OfflineADPError,
    SchemaError,
)
from offline_adp.simulate import simulate


def test_save_load_round_trip(tmp_path, small_pt):
    small_pt.save(tmp_path / "ds")
    back = TransitionDataset.load(tmp_path / "ds")
    a, b = small_pt.arrays(), back.arrays()
    for f in ("obs", "action", "cost", "next_obs", "terminated", "truncated", "step", "episode", "behavior_prob"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert back.info == small_pt.info
    assert back.fingerprint() == small_pt.fingerprint()
    info = json.loads((tmp_path / "ds" / S.INFO_FILE).read_text())
    assert info["format_version"] == S.FORMAT_VERSION and info["n_transitions"] == len(small_pt)
    ep = pq.read_table(tmp_path / "ds" / S.EPISODES_FILE).to_pandas()
    assert ep["length"].sum() == len(small_pt) and len(ep) == small_pt.n_episodes
    stats = json.loads((tmp_path / "ds" / S.STATS_FILE).read_text())
    assert sum(stats["action_counts"].values()) == len(small_pt)
    meta = pq.ParquetFile(next((tmp_path / "ds" / "data").glob("part-*.parquet"))).metadata
    assert meta.row_group(0).column(0).compression == "LZ4"  # LZ4_RAW
    # columns without nulls are stored required (no definition levels); the dataset read
    # back declares its columns nullable, as any dataset's
    assert not pq.read_schema(next((tmp_path / "ds" / "data").glob("part-*.parquet"))).field(S.COST).nullable
    assert back.table.schema.field(S.COST).nullable


def test_parts_hold_whole_episodes(tmp_path, small_pt):
    small_pt.save(tmp_path / "ds", rows_per_part=100)
    parts = dio.part_files(tmp_path / "ds")
    assert len(parts) > 3
    seen: set[str] = set()
    for p in parts:
        ids = set(pq.read_table(p, columns=[S.EPISODE_ID]).column(0).to_pylist())
        assert not ids & seen  # no episode split across parts
        seen |= ids
    back = TransitionDataset.load(tmp_path / "ds")
    assert back.fingerprint() == small_pt.fingerprint()  # independent of chunking


def test_arrays_shapes_and_types(small_pt):
    a = small_pt.arrays(dtype=np.float32)
    n, d = len(small_pt), len(small_pt.feature_names)
    assert a.obs.shape == (n, d) and a.obs.dtype == np.float32 and a.next_obs.shape == (n, d)
    assert a.action.dtype == np.int32 and a.terminated.dtype == bool
    assert len(a.episode_starts) == small_pt.n_episodes
    # continuity inside episodes: next_obs(t) == obs(t+1)
    inner = np.r_[a.episode[1:] == a.episode[:-1], False]
    np.testing.assert_allclose(a.next_obs[inner], a.obs[np.flatnonzero(inner) + 1])


def test_unsorted_input_is_sorted(small_pt):
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(small_pt))
    shuffled = TransitionDataset(small_pt.table.take(pa.array(perm)), small_pt.info)
    assert shuffled.fingerprint() == small_pt.fingerprint()


def test_split_filter_states_at(small_pt):
    tr, va = small_pt.split(0.25, seed=3)
    assert set(tr.episode_ids) | set(va.episode_ids) == set(small_pt.episode_ids)
    assert not set(tr.episode_ids) & set(va.episode_ids)
    assert len(tr) + len(va) == len(small_pt)
    tr2, _ = small_pt.split(0.25, seed=3)
    assert list(tr2.episode_ids) == list(tr.episode_ids)
    demo = small_pt.filter_source("demonstration")
    assert set(demo.column(S.SOURCE)) == {"demonstration"}
    assert len(demo) == small_pt.source_counts()["demonstration"]
    x3 = small_pt.states_at(3)
    assert x3.shape == ((small_pt.episode_table()["length"] > 3).sum(), len(small_pt.feature_names))
    eps = list(small_pt.episodes())
    assert [e for e, _ in eps] == list(small_pt.episode_ids)
    assert sum(len(d) for _, d in eps) == len(small_pt)


def test_concat(small_pt):
    a = small_pt.select_episodes(small_pt.episode_ids[:5])
    b = small_pt.select_episodes(small_pt.episode_ids[5:])
    c = TransitionDataset.concat([b, a])
    assert c.fingerprint() == small_pt.fingerprint()
    with pytest.raises(SchemaError, match="episode ids occur in more than one"):
        TransitionDataset.concat([a, a])
    other = simulate("car_on_hill", 1, 1, seed=0)
    with pytest.raises(SchemaError, match="features"):
        TransitionDataset.concat([a, other])


def test_missing_column_names_it(small_pt):
    with pytest.raises(SchemaError, match="cost"):
        TransitionDataset(small_pt.table.drop_columns([S.COST]), small_pt.info)


def test_atomic_write_leaves_nothing_on_crash(tmp_path, small_pt, monkeypatch):
    calls = {"n": 0}
    real = pq.write_table

    def failing(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError("disk full")
        return real(*args, **kwargs)

    monkeypatch.setattr(dio.pq, "write_table", failing)
    with pytest.raises(OSError):
        small_pt.save(tmp_path / "ds", rows_per_part=100)
    # no half-written dataset, no temp dir left, no lock file (removed on release, see data.io.locked_directory)
    assert [p.name for p in tmp_path.iterdir()] == []


def test_overwrite_is_atomic_and_explicit(tmp_path, small_pt):
    small_pt.save(tmp_path / "ds")
    with pytest.raises(OfflineADPError, match="already exists"):
        small_pt.save(tmp_path / "ds")
    half = small_pt.select_episodes(small_pt.episode_ids[:3])
    half.save(tmp_path / "ds", overwrite=True)
    assert len(TransitionDataset.load(tmp_path / "ds")) == len(half)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


def test_load_errors(tmp_path, small_pt):
    with pytest.raises(DatasetNotFoundError, match="not a dataset directory"):
        TransitionDataset.load(tmp_path)
    small_pt.save(tmp_path / "ds")
    info = json.loads((tmp_path / "ds" / S.INFO_FILE).read_text())
    info["format_version"] = "0.9"
    (tmp_path / "ds" / S.INFO_FILE).write_text(json.dumps(info))
    with pytest.warns(FormatVersionWarning, match="0.9"):
        TransitionDataset.load(tmp_path / "ds")
    del info["action_table"]
    (tmp_path / "ds" / S.INFO_FILE).write_text(json.dumps(info))
    with pytest.raises(SchemaError, match="action_table"):
        TransitionDataset.load(tmp_path / "ds")


def test_simulate_logs_propensities_and_keeps_truncated_last_transition():
    from offline_adp.envs import make_problem

    ds = simulate("gridworld", 20, 20, seed=4, horizon=15)
    a = ds.arrays()
    prob = make_problem("gridworld")
    demo = ds.column(S.SOURCE) == "demonstration"
    p_demo = prob.demonstrator().probabilities(a.obs[demo], 0)[np.arange(demo.sum()), a.action[demo]]
    np.testing.assert_allclose(a.behavior_prob[demo], p_demo)
    np.testing.assert_allclose(a.behavior_prob[~demo], 0.25)
    ep = ds.episode_table()
    # every episode ends flagged; an episode cut by the time limit keeps all 15 transitions
    assert (ep.terminated ^ ep.truncated).all()
    assert (ep.loc[ep.truncated, "length"] == 15).all()
    assert simulate("gridworld", 20, 20, seed=4, horizon=15).fingerprint() == ds.fingerprint()


def test_episode_index_is_consistent_across_chunks(small_pt):
    ids = small_pt.episode_ids
    a = small_pt.select_episodes(ids[:4]).table
    b = small_pt.select_episodes(ids[4:]).table
    chunked = TransitionDataset(pa.concat_tables([a, b]), small_pt.info)
    assert chunked.table.column(S.EPISODE_ID).num_chunks >= 2
    expected = np.unique(chunked.column(S.EPISODE_ID), return_inverse=True)[1]
    np.testing.assert_array_equal(chunked.episode_index, expected)
    assert chunked.fingerprint() == small_pt.fingerprint()


def test_null_episode_id_in_a_part_is_a_schema_error(tmp_path, small_pt):
    """A hand-edited part with missing episode ids: our error naming the directory, not an IndexError."""
    small_pt.save(tmp_path / "ds")
    p = tmp_path / "ds" / "data" / "part-00000.parquet"
    t = pq.read_table(p)
    ids = t.column(S.EPISODE_ID).to_pylist()
    ids[3] = None
    pq.write_table(t.set_column(t.schema.get_field_index(S.EPISODE_ID), S.EPISODE_ID, pa.array(ids, pa.string())), p)
    with pytest.raises(SchemaError, match=r"ds: row 3: episode_id is missing"):
        TransitionDataset.load(tmp_path / "ds")
