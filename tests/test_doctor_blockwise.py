"""The doctor's row masks made block by block (``validate._flagged``) and the ingestion's
end-of-episode flags set in place: the same findings and flags as the column-sized masks
they replace, on random tables with random defects and blocks of a few rows."""

from __future__ import annotations

import tomllib

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from offline_adp.data import schema as S
from offline_adp.data import validate as V
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.ingest.parquet import _map, ingest_tables
from offline_adp.ingest.spec import parse_parquet_spec

INFO = DatasetInfo(features=(Feature("x"),), action_table=ActionTable.from_values([0.0, 1.0, 2.0]))


def _table(seed: int, n_eps: int, max_len: int, p_defect: float) -> pa.Table:
    """Episodes of random lengths, each value wrong with probability ``p_defect``."""
    rng = np.random.default_rng(seed)
    lens = rng.integers(1, max_len + 1, n_eps)
    n = int(lens.sum())
    ep = np.repeat(np.arange(n_eps), lens)
    step = np.concatenate([np.arange(k) for k in lens])
    last = np.r_[ep[1:] != ep[:-1], True]
    bad = rng.random((7, n)) < p_defect
    step = np.where(bad[0], step + 1, step)
    obs = rng.normal(size=n)
    nxt = np.r_[obs[1:], 0.0]
    term = np.where(bad[1], ~last, last & (rng.random(n) < 0.5))
    trunc = np.where(bad[2], False, last & ~term)
    action = np.where(bad[3], rng.choice([-1, 3, 9], n), rng.integers(0, 3, n))
    prob = np.where(bad[4], rng.choice([0.0, -0.5, 1.5, np.nan], n), rng.uniform(0.01, 1.0, n))
    t_ns = np.where(bad[5], 0, 1_000 * step + 10**9 * ep)
    return pa.table({
        S.EPISODE_ID: pa.array([f"e{e:03d}" for e in ep]),
        S.STEP: step.astype(np.int32),
        S.T_NS: t_ns.astype(np.int64),
        "obs.x": obs,
        S.ACTION: action.astype(np.int32),
        S.COST: rng.normal(size=n),
        "next_obs.x": nxt,
        S.TERMINATED: term,
        S.TRUNCATED: trunc,
        S.SOURCE: pa.array(["exploration"] * n).dictionary_encode(),
        S.BEHAVIOR_PROB: prob,
    })


def _reference(ds: TransitionDataset) -> tuple[set[tuple[str, int]], int]:
    """The findings of the checks made block by block, and the count of rows both
    terminated and truncated, from column-sized masks (the doctor before the blocks)."""
    t = ds.table
    codes = ds.episode_codes
    n = t.num_rows
    last = np.r_[codes[1:] != codes[:-1], True]
    first = np.r_[True, codes[1:] != codes[:-1]]
    starts = np.flatnonzero(first)
    step = t.column(S.STEP).to_numpy()
    term = t.column(S.TERMINATED).to_numpy(zero_copy_only=False)
    trunc = t.column(S.TRUNCATED).to_numpy(zero_copy_only=False)
    a = t.column(S.ACTION).to_numpy()
    p = t.column(S.BEHAVIOR_PROB).to_numpy()
    ts = t.column(S.T_NS).to_numpy()
    dec = np.zeros(n, bool)
    dec[1:] = (ts[1:] < ts[:-1]) & ~last[:-1]
    masks = {
        "step_not_contiguous": step != np.arange(n) - starts[codes],
        "flag_not_last": (term | trunc) & ~last,
        "end_unflagged": last & ~(term | trunc),
        "action_out_of_range": (a < 0) | (a >= ds.n_actions),
        "propensity_out_of_range": (p <= 0) | (p > 1),
        "time_decreasing": dec,
    }
    found = {(check, int(i)) for check, m in masks.items() for i in np.flatnonzero(m)}
    return found, int(np.count_nonzero(term & trunc))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), n_eps=st.integers(1, 12), max_len=st.integers(1, 9),
       p_defect=st.sampled_from([0.0, 0.02, 0.2]), block=st.sampled_from([1, 2, 3, 8, 1 << 16]))
def test_blockwise_doctor_finds_what_column_masks_find(monkeypatch, seed, n_eps, max_len, p_defect, block):
    monkeypatch.setattr(V, "_BLOCK", block)
    ds = TransitionDataset(_table(seed, n_eps, max_len, p_defect), INFO)
    rep = V.validate(ds)
    want, both = _reference(ds)
    f = rep.findings
    checks = {c for c, _ in want} | {"step_not_contiguous", "flag_not_last", "end_unflagged",
                                      "action_out_of_range", "propensity_out_of_range", "time_decreasing"}
    got = {(c, int(r)) for c, r in zip(f["check"], f["row"], strict=True) if c in checks} if len(f) else set()
    assert got == want
    assert rep.n_terminated_and_truncated == both


def test_flagged_is_none_without_a_flag_and_the_mask_otherwise():
    x = np.arange(10)
    assert V._flagged(10, lambda lo, hi: x[lo:hi] > 99) is None
    for block in (1, 3, 4, 16):
        V_block = V._BLOCK
        try:
            V._BLOCK = block
            np.testing.assert_array_equal(V._flagged(10, lambda lo, hi: x[lo:hi] % 4 == 1), x % 4 == 1)
            m = V._flagged(10, lambda lo, hi: x[lo:hi] > x[lo - 1:hi - 1], start=1)
            np.testing.assert_array_equal(m, np.r_[False, np.ones(9, bool)])
        finally:
            V._BLOCK = V_block
    assert V._flagged(0, lambda lo, hi: x[lo:hi] > 0) is None


SPEC = """
kind = "transitions"
on_error = "quarantine"
[episode]
id = "ep"
step = "step"
[observations]
columns = ["x"]
next_columns = ["nx"]
[action]
column = "a"
values = [0, 1]
[cost]
column = "c"
[end]
terminated = "term"
truncated = "trunc"
"""


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), n_eps=st.integers(1, 8), max_len=st.integers(1, 6),
       nulls=st.booleans(), with_trunc=st.booleans())
def test_ingested_end_flags_follow_the_rule(tmp_path, seed, n_eps, max_len, nulls, with_trunc):
    """An episode's last row is truncated unless terminated, null flags stay null, and no
    other row changes: ``truncated | (last & ~terminated)`` over whole columns."""
    rng = np.random.default_rng(seed)
    lens = rng.integers(1, max_len + 1, n_eps)
    n = int(lens.sum())
    ep = np.repeat(np.arange(n_eps), lens)
    order = rng.permutation(n)  # shuffled rows: the ingestion sorts them
    term = rng.random(n) < 0.3
    trunc = rng.random(n) < 0.3
    tmask = (rng.random(n) < 0.2) if nulls else None
    cols = {"ep": pa.array([f"e{e}" for e in ep]), "step": np.concatenate([np.arange(k) for k in lens]),
            "x": rng.normal(size=n), "nx": rng.normal(size=n), "a": rng.integers(0, 2, n).astype(float),
            "c": rng.normal(size=n), "term": pa.array(term, mask=tmask)}
    spec_text = SPEC
    if with_trunc:
        cols["trunc"] = pa.array(trunc)
    else:
        spec_text = SPEC.replace('truncated = "trunc"\n', "")
    src = tmp_path / f"in{seed}_{n_eps}_{max_len}_{nulls}_{with_trunc}.parquet"
    pq.write_table(pa.table(cols).take(pa.array(order)), src)
    out = _map([src], parse_parquet_spec(tomllib.loads(spec_text)), None)[0]  # every row, sorted, before the doctor
    rows = out.column("src_row").to_numpy()  # row in the file
    e = out.column(S.EPISODE_ID).to_numpy(zero_copy_only=False)
    last = np.r_[e[1:] != e[:-1], True]
    f_term, f_null = term[order][rows], (tmask[order][rows] if tmask is not None else np.zeros(n, bool))
    f_trunc = trunc[order][rows] if with_trunc else np.zeros(n, bool)
    want = f_trunc | (last & ~(f_term & ~f_null))
    assert out.column(S.TRUNCATED).null_count == 0
    np.testing.assert_array_equal(out.column(S.TRUNCATED).to_numpy(zero_copy_only=False), want)
    got_term = out.column(S.TERMINATED)
    np.testing.assert_array_equal(np.asarray(got_term.is_null()), f_null)
    np.testing.assert_array_equal(got_term.fill_null(False).to_numpy(zero_copy_only=False), f_term & ~f_null)


@pytest.mark.parametrize("n", [1, 2, 5])
def test_tiny_tables_ingest(tmp_path, n):
    cols = {"ep": pa.array(["e"] * n), "step": np.arange(n), "x": np.zeros(n), "nx": np.zeros(n),
            "a": np.zeros(n), "c": np.zeros(n), "term": np.r_[np.zeros(n - 1, bool), True],
            "trunc": np.zeros(n, bool)}
    pq.write_table(pa.table(cols), tmp_path / "t.parquet")
    res = ingest_tables([tmp_path / "t.parquet"], parse_parquet_spec(tomllib.loads(SPEC)))
    assert res.report.ok, res.report.to_text()
    assert res.dataset.table.column(S.TRUNCATED).to_pylist() == [False] * n
