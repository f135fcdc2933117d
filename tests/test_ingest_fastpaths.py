"""The ingestion's fast paths give what their plain definitions give.

Discrete action matching, the doctor's continuity and range checks, the statistics' mean
and std, and the sortedness check each take a shortcut on the common case (values equal,
clean columns, sorted ids); these tests hold them to the rule they shortcut.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from offline_adp.data.columns import sorted_encoding
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import Action, ActionTable, DatasetInfo, Feature
from offline_adp.data.io import _mean_std
from offline_adp.data.validate import MAX_ABS_INPUT, MAX_ABS_VALUE, validate
from offline_adp.ingest.actions import _match_each


def _last_match(x: np.ndarray, tv: np.ndarray, tol: np.ndarray) -> np.ndarray:
    idx = np.full(len(x), -1, np.int64)
    for k in range(len(tv)):
        idx[np.abs(x - tv[k]) <= tol[k]] = k
    return idx


@pytest.mark.parametrize("n", [0, 1, 5, (1 << 14) + 3, 100_000])
@pytest.mark.parametrize(("tv", "far"), [
    ([-1.0, 0.0, 1.0, 1.0 + 5e-10, 3e9], False),  # two values within each other's tolerance: the rule
    ([1.0, -1.0, 0.0, 3e9, -5e-9], True),  # far apart: matched by equality first, the rest by the rule
    ([1.0, 0.0, -2.5e-9], False),  # tolerances 1e-9 each, 2.5e-9 apart: not far enough
    ([0.5], True),
    ([-1.0, 0.0, np.inf], False),  # not finite: the rule
])
def test_match_each_is_the_last_match_within_tolerance(n: int, tv: list[float], far: bool) -> None:
    from offline_adp.ingest.actions import _far_apart

    rng = np.random.default_rng(n)
    tv = np.array(tv)
    tol = 1e-9 * np.maximum(1.0, np.abs(tv))
    assert _far_apart(tv, tol) == far
    x = rng.choice(tv, n) + rng.choice([0.0, 0.0, 0.0, -0.0, 2e-10, -8e-10, 1e-9, 2e-9, 0.5], n)
    if n > 3:
        x[:3] = [np.nan, np.inf, -np.inf]
    with np.errstate(invalid="ignore"):
        got = _match_each(x, tv, tol)
        want = _last_match(x, tv, tol)
    assert got.dtype == np.int32
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("n", [1, 2, 3, 127, 1000, 65_536, 65_537, 131_079, 300_007, 1_000_003])
def test_mean_std_are_numpys_bit_for_bit(n: int) -> None:
    rng = np.random.default_rng(n)
    # the last: Cauchy values over ten orders of magnitude, where the order of the sums shows
    for x in (rng.normal(size=n) * 1e6 + 3, rng.random(n), np.cumsum(rng.normal(size=n)), np.full(n, 0.1),
              rng.standard_cauchy(n) * 10.0 ** rng.integers(-5, 5, n)):
        mean, std = _mean_std(x, np.empty(min(n, 1 << 16)))
        assert mean == float(x.mean()) and std == float(x.std())



@pytest.mark.parametrize("block", [0, 8, 15, 16, 24, 100, 128, 200])
def test_squared_deviations_with_a_small_block_end_and_are_numpys(monkeypatch, block: int) -> None:
    """``_STATS_BLOCK`` below 16 made the split's half (rounded down to a multiple of 8) 0,
    recursing with no end; below numpy's own block (128) the split was not numpy's. Any
    block now gives ``np.add.reduce((x - mean) ** 2)`` bit for bit, and the statistics too,
    with the buffer ``dataset_stats`` makes for it."""
    import offline_adp.data.io as io

    monkeypatch.setattr(io, "_STATS_BLOCK", block)
    rng = np.random.default_rng(block)
    for n in (0, 1, 7, 8, 9, 12, 15, 16, 17, 33, 100, 127, 128, 129, 257, 1000, 4099):
        x = rng.standard_cauchy(n) * 10.0 ** rng.integers(-5, 5, n)  # where the order of the sums shows
        mean = x.mean() if n else 0.0
        buf = np.empty(min(n, io._stats_block()))
        got, want = io._sq_dev_sum(x, mean, buf), np.add.reduce((x - mean) ** 2)
        assert np.float64(got).view(np.int64) == np.float64(want).view(np.int64), (block, n)
        if n:
            m, s = io._mean_std(x, buf)
            assert m == float(x.mean()) and s == float(x.std()), (block, n)


def _dataset(obs: np.ndarray, nxt: np.ndarray, ep_len: int) -> TransitionDataset:
    n = len(obs)
    info = DatasetInfo(features=(Feature("x"),), action_table=ActionTable((Action("a", (0.0,)),)))
    ep = np.arange(n) // ep_len
    return TransitionDataset.from_arrays(
        info, episode_id=np.char.add("e", np.char.zfill(ep.astype(str), 6)), step=np.arange(n) % ep_len,  # in row order
        obs=obs, action=np.zeros(n, np.int32), cost=np.zeros(n), next_obs=nxt,
        terminated=np.zeros(n, bool), truncated=(np.arange(n) % ep_len) == ep_len - 1)


def test_doctor_continuity_and_range_checks_follow_their_rules() -> None:
    rng = np.random.default_rng(0)
    ep_len, n_ep = 50, 3000  # 150k rows: several blocks, dense and sparse blocks of differences
    n = ep_len * n_ep
    walk = rng.normal(size=n + 1).cumsum()
    obs, nxt = walk[:-1].copy(), walk[1:].copy()
    k = rng.choice(n - 1, 400, replace=False)
    nxt[k[:100]] += 1e-3  # beyond tolerance
    nxt[k[100:200]] *= 1 + 1e-9  # within rtol
    obs[k[200:220]] = np.nan
    nxt[k[220:240]] = np.inf
    obs[k[240:250]] = MAX_ABS_VALUE * 10
    obs[k[250:255]] = 1e50  # within the cost's bound, beyond a model input's (float32 trees)
    nxt[k[255:260]] = -MAX_ABS_INPUT * 1.01
    obs[k[260:265]] = MAX_ABS_INPUT  # at the bound: accepted
    nxt[70_000:80_000] += 1e-12 * (1 + np.abs(nxt[70_000:80_000]))  # a block where many rows differ (within tolerance)
    nxt[90_000:100_000] += 1.0  # ... and many beyond it
    ds = _dataset(obs, nxt, ep_len)
    f = validate(ds).findings
    last = (np.arange(n) % ep_len) == ep_len - 1
    x, y = nxt[:-1], obs[1:]
    with np.errstate(invalid="ignore", over="ignore"):
        close = np.abs(x - y) <= 1e-9 + 1e-7 * np.abs(y)
    mismatch = np.r_[~close & np.isfinite(x) & np.isfinite(y) & ~last[:-1], False]
    got = np.sort(f.loc[f["check"] == "next_obs_mismatch", "row"].to_numpy())
    np.testing.assert_array_equal(got, np.flatnonzero(mismatch))
    for col, v in (("obs.x", obs), ("next_obs.x", nxt)):
        sel = f["column"] == col
        np.testing.assert_array_equal(np.sort(f.loc[sel & (f["check"] == "non_finite"), "row"].to_numpy()),
                                      np.flatnonzero(~np.isfinite(v)))
        with np.errstate(invalid="ignore"):
            big = np.isfinite(v) & (np.abs(v) > MAX_ABS_INPUT)
        assert big.sum() == {"obs.x": 15, "next_obs.x": 5}[col]
        np.testing.assert_array_equal(np.sort(f.loc[sel & (f["check"] == "value_out_of_range"), "row"].to_numpy()),
                                      np.flatnonzero(big))


def test_clean_dataset_has_no_findings() -> None:
    walk = np.random.default_rng(1).normal(size=10_001).cumsum()
    assert validate(_dataset(walk[:-1], walk[1:], 100)).ok


def _expected_encoding(ids: list[str], order: np.ndarray) -> tuple[list[int], list[str]] | None:
    key = [(s.encode(), o) for s, o in zip(ids, order, strict=True)]
    if any(b < a for a, b in zip(key, key[1:], strict=False)):
        return None
    words = list(dict.fromkeys(ids))
    return [words.index(s) for s in ids], words


@pytest.mark.parametrize("seed", range(12))
def test_sorted_encoding_is_none_unless_rows_are_in_id_then_order(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 60))
    ids = sorted(rng.choice(["a", "b", "ba", "c", "é", "z"], n).tolist(), key=str.encode)
    order = np.concatenate([np.arange(c) for c in np.unique(ids, return_counts=True)[1][np.argsort(
        [s.encode() for s in np.unique(ids)])]]).astype(np.int64)
    if seed % 3 == 1 and n > 1:  # ids out of order
        i = int(rng.integers(0, n - 1))
        ids[i], ids[i + 1] = ids[i + 1], ids[i]
    if seed % 3 == 2 and n > 1:  # order decreasing somewhere
        order = order[::-1].copy()
    split = int(rng.integers(0, n + 1))
    col = pa.chunked_array([pa.array(ids[:split], pa.string()), pa.array(ids[split:], pa.string())])
    enc = sorted_encoding(col, order)
    want = _expected_encoding(ids, order)
    if want is None:
        assert enc is None
    else:
        assert enc is not None
        assert enc.indices.to_pylist() == want[0] and enc.dictionary.to_pylist() == want[1]


def test_dataset_stats_are_the_plain_statistics_of_the_finite_values() -> None:
    """``stats.json``'s shortcut (no finiteness pass when a column's sum is finite, actions
    counted by comparison) against numpy over each column's finite values."""
    from offline_adp.data.io import dataset_stats

    rng = np.random.default_rng(3)
    n, ep_len = 4000, 40
    obs = rng.normal(size=(n, 1)) * 1e3
    nxt = rng.normal(size=(n, 1))
    obs[7, 0], obs[100, 0] = np.nan, np.inf  # not finite: left out, counted
    nxt[:, 0] = 1e308  # finite values whose sum overflows
    ds = _dataset(obs, nxt, ep_len)
    action = rng.integers(0, 3, n).astype(np.int32)
    info = ds.info.replace(action_table=ActionTable(tuple(Action(f"a{k}", (float(k),)) for k in range(3))))
    ds = TransitionDataset(ds.table.set_column(ds.table.column_names.index("action"), "action", pa.array(action)), info)
    stats = dataset_stats(ds)
    for name, x in (("obs.x", obs[:, 0]), ("next_obs.x", nxt[:, 0]), ("cost", np.zeros(n))):
        f = x[np.isfinite(x)]
        with np.errstate(over="ignore", invalid="ignore"):
            want = {"mean": float(f.mean()), "std": float(f.std()), "min": float(f.min()), "max": float(f.max()),
                    "non_finite": int(n - len(f))}
        got = stats["columns"][name]
        assert got.keys() == want.keys()
        for k, v in want.items():
            assert got[k] == v or (np.isnan(got[k]) and np.isnan(v)), (name, k)
    assert stats["action_counts"] == {f"a{k}": int((action == k).sum()) for k in range(3)}


@pytest.mark.parametrize("cuts", [(), (0,), (3,), (0, 0, 7), (5, 5, 19), (20,)])
def test_take_chunkwise_is_the_take_of_the_combined_column(cuts: tuple[int, ...]) -> None:
    """The episode ids' dictionary is taken chunk by chunk (no concatenation of the column):
    the same strings as Arrow's take on the chunked column, empty chunks included."""
    from offline_adp.data.columns import _take_chunkwise

    words = [f"id-{i:03d}" for i in range(20)]
    edges = [0, *cuts, 20]
    for large in (False, True):
        typ = pa.large_string() if large else pa.string()
        col = pa.chunked_array([pa.array(words[a:b], typ) for a, b in zip(edges[:-1], edges[1:], strict=True)], typ)
        for idx in (np.arange(20), np.array([0, 4, 5, 6, 19]), np.array([], np.int64), np.array([7])):
            got = _take_chunkwise(col, idx)
            assert got.type == typ
            assert got.to_pylist() == col.take(pa.array(idx, pa.int64())).combine_chunks().to_pylist()


@pytest.mark.parametrize("seed", range(6))
def test_bool_values_is_arrows_conversion(seed: int) -> None:
    """Booleans unpacked from the bitmaps equal Arrow's value-by-value conversion: slices at
    any bit offset, several chunks, nulls as False or True."""
    from offline_adp.data.columns import bool_values

    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 3000))
    vals = rng.random(n) < 0.5
    mask = rng.random(n) < (0.2 if seed % 2 else 0.0)
    arr = pa.array(vals, mask=mask)
    cuts = np.sort(rng.integers(0, n + 1, 3))
    chunks = [arr.slice(int(a), int(b - a)) for a, b in zip([0, *cuts], [*cuts, n], strict=True)]
    for col in (arr, pa.chunked_array(chunks, pa.bool_()), arr.slice(min(n, 13))):
        for null in (False, True):
            want = np.asarray(col.fill_null(null).to_numpy(zero_copy_only=False), dtype=bool)
            got = bool_values(col, null)
            assert got.dtype == bool
            np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("seed", range(8))
def test_episode_sums_are_bincount_bit_for_bit(seed: int) -> None:
    """Per-episode sums over whole episodes a block at a time (from a read-only column, as
    Arrow's) equal ``np.bincount`` with weights bit for bit: short and long episodes, NaN,
    signed zeros, values over many orders of magnitude."""
    from offline_adp.data.columns import episode_sums

    rng = np.random.default_rng(seed)
    lengths = rng.integers(1, 400, int(rng.integers(1, 60)))
    if seed % 3 == 0:
        lengths[len(lengths) // 2] = 5000  # an episode longer than the block
    n = int(lengths.sum())
    codes = np.repeat(np.arange(len(lengths)), lengths)
    starts = np.r_[0, np.cumsum(lengths)[:-1]]
    x = rng.standard_cauchy(n) * 10.0 ** rng.integers(-8, 8, n)
    x[rng.integers(0, n, 3)] = [np.nan, -0.0, 0.0]
    x.flags.writeable = False
    want = np.bincount(codes, weights=x, minlength=len(lengths))
    got = episode_sums(codes, starts, x, len(lengths), block=int(rng.integers(1, 700)))
    assert got.tobytes() == want.tobytes()
    shuffled = codes[::-1].copy()  # not in episode order: bincount itself
    assert episode_sums(shuffled, starts, x, len(lengths)).tobytes() == np.bincount(
        shuffled, weights=x, minlength=len(lengths)).tobytes()


def test_episode_codes_are_episode_index_without_the_copy() -> None:
    """``episode_codes`` (the encoding's int32, read by the doctor, the episode table and the
    fingerprint) holds the values of ``episode_index`` (int64, widened once when read)."""
    n = 7
    table = pa.table({"episode_id": ["b", "b", "a", "c", "c", "c", "a"], "step": [0, 1, 0, 0, 1, 2, 1],
                      "obs.x": np.arange(n, dtype=float), "action": np.zeros(n, np.int32), "cost": np.ones(n),
                      "next_obs.x": np.arange(n, dtype=float) + 1, "terminated": [False] * n,
                      "truncated": [False, True, False, False, False, True, True], "source": ["s"] * n})
    info = DatasetInfo(features=(Feature("x"),), action_table=ActionTable((Action("a0", (0.0,)),), ("u",)))
    ds = TransitionDataset(table, info)
    assert ds.episode_codes.dtype == np.int32
    assert ds.episode_index.dtype == np.int64
    np.testing.assert_array_equal(ds.episode_codes, ds.episode_index)
    assert ds.episode_ids[ds.episode_index].tolist() == ds.table.column("episode_id").to_pylist()
    assert ds.episode_table()["length"].tolist() == [2, 2, 3]


def test_doctor_mask_checks_follow_their_rules() -> None:
    """Flags, actions, propensities and times against their plain definitions (each check
    computes its mask with as few column-sized temporaries as it can)."""
    rng = np.random.default_rng(3)
    ep_len, n_ep = 40, 2000
    n = ep_len * n_ep
    walk = rng.normal(size=n + 1).cumsum()
    last = (np.arange(n) % ep_len) == ep_len - 1
    term = rng.random(n) < 0.01
    trunc = last & (rng.random(n) < 0.8)
    action = rng.integers(-3, 5, n).astype(np.int32)
    prob = rng.choice([0.5, 1.0, 0.0, -0.1, 1.5, np.nan, np.inf, -np.inf, 1e-300], n)
    t_ns = np.arange(n, dtype=np.int64) * 10 - rng.choice([0, 0, 0, 25], n)
    info = DatasetInfo(features=(Feature("x"),), action_table=ActionTable(tuple(Action(f"a{k}", (float(k),))
                                                                                for k in range(3))))
    ep = np.arange(n) // ep_len
    ds = TransitionDataset.from_arrays(
        info, episode_id=np.char.add("e", np.char.zfill(ep.astype(str), 6)), step=np.arange(n) % ep_len,
        obs=walk[:-1], action=action, cost=np.zeros(n), next_obs=walk[1:], terminated=term, truncated=trunc,
        behavior_prob=prob, t_ns=t_ns)
    f = validate(ds).findings

    def rows(check: str) -> np.ndarray:
        return np.sort(f.loc[f["check"] == check, "row"].to_numpy())

    first = np.r_[True, last[:-1]]
    np.testing.assert_array_equal(rows("flag_not_last"), np.flatnonzero((term | trunc) & ~last))
    np.testing.assert_array_equal(rows("end_unflagged"), np.flatnonzero(last & ~term & ~trunc))
    np.testing.assert_array_equal(rows("action_out_of_range"), np.flatnonzero((action < 0) | (action >= 3)))
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(rows("propensity_out_of_range"),
                                      np.flatnonzero(~np.isnan(prob) & ~((prob > 0) & (prob <= 1))))
    np.testing.assert_array_equal(rows("time_decreasing"),
                                  np.flatnonzero(np.r_[False, (t_ns[1:] < t_ns[:-1]) & ~first[1:]]))


@pytest.mark.parametrize("seed", range(6))
def test_code_counts_are_arrows_value_counts(seed: int) -> None:
    """Source labels counted by one comparison per code: Arrow's value_counts (codes used, in
    order of first appearance), over chunks, unused codes left out."""
    from offline_adp.data.dataset import _code_counts

    rng = np.random.default_rng(seed)
    n_codes = int(rng.integers(1, 9))
    used = rng.choice(n_codes, int(rng.integers(1, n_codes + 1)), replace=False)
    x = rng.choice(used, int(rng.integers(1, 5000))).astype(np.int32)
    cuts = np.sort(rng.integers(0, len(x) + 1, 2))
    chunks = [pa.array(x[a:b]) for a, b in zip([0, *cuts], [*cuts, len(x)], strict=True)]
    vc = pc.value_counts(pa.chunked_array(chunks, pa.int32()))
    want = list(zip(vc.field("values").to_pylist(), vc.field("counts").to_pylist(), strict=True))
    assert _code_counts(chunks, n_codes) == want
