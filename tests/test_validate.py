"""The dataset doctor on a crafted bad table, and quarantine."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from offline_adp.data import schema as S
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.data.validate import (
    CHECKS,
    RowOrigin,
    split_quarantine,
    validate,
    validate_directory,
)

INFO = DatasetInfo(features=(Feature("x"),), action_table=ActionTable.from_values([0.0, 1.0]))


def _good(n_eps=3, T=4):
    rows = []
    for e in range(n_eps):
        for t in range(T):
            rows.append(
                {
                    S.EPISODE_ID: f"e{e}",
                    S.STEP: t,
                    S.T_NS: 1000 * t,
                    "obs.x": float(10 * e + t),
                    S.ACTION: t % 2,
                    S.COST: 1.0,
                    "next_obs.x": float(10 * e + t + 1),
                    S.TERMINATED: False,
                    S.TRUNCATED: t == T - 1,
                    S.SOURCE: "exploration",
                    S.BEHAVIOR_PROB: 0.5,
                }
            )
    return rows


def test_good_table_passes():
    ds = TransitionDataset(pa.Table.from_pylist(_good()), INFO)
    rep = validate(ds)
    assert rep.ok, rep.to_text()


# (check code, mutation on row index, expected column) -- one defect per episode-sized block
DEFECTS = {
    "step_not_contiguous": (lambda r: r[1].update({S.STEP: 5}), S.STEP),
    "next_obs_mismatch": (lambda r: r[1].update({"next_obs.x": 99.0}), "next_obs.x"),
    "flag_not_last": (lambda r: r[1].update({S.TERMINATED: True}), S.TERMINATED),
    "end_unflagged": (lambda r: r[3].update({S.TRUNCATED: False}), "terminated,truncated"),
    "non_finite": (lambda r: r[2].update({S.COST: float("nan")}), S.COST),
    "value_out_of_range": (lambda r: r[2].update({"obs.x": -1e200}), "obs.x"),
    "action_out_of_range": (lambda r: r[2].update({S.ACTION: 7}), S.ACTION),
    "propensity_out_of_range": (lambda r: r[2].update({S.BEHAVIOR_PROB: 0.0}), S.BEHAVIOR_PROB),
    "time_decreasing": (lambda r: r[2].update({S.T_NS: -5}), S.T_NS),
    "null_value": (lambda r: r[2].update({"obs.x": None}), "obs.x"),
}
#: checks of a directory's metadata against its data (tested in test_directory_metadata_checks)
DIRECTORY_CHECKS = {"info_stale", "fingerprint_mismatch", "episodes_stale", "episode_split_across_parts"}


@pytest.mark.parametrize("check", sorted(DEFECTS))
def test_each_defect_class_is_reported_with_file_row_column(check):
    rows = _good()
    block = rows[4:8]  # episode e1, rows 4..7
    mutate, column = DEFECTS[check]
    mutate(block)
    ds = TransitionDataset(pa.Table.from_pylist(rows), INFO)
    origin = RowOrigin(["logs/bad.parquet"], np.zeros(len(ds), int), np.arange(len(ds)) + 100)
    rep = validate(ds, origin=origin)
    hits = rep.findings[rep.findings["check"] == check]
    assert len(hits), f"{check} not reported:\n{rep.to_text()}"
    h = hits.iloc[0]
    assert h["file"] == "logs/bad.parquet"
    assert h[S.EPISODE_ID] == "e1" and 104 <= h["row"] <= 107
    assert h["column"] == column
    assert set(rep.bad_episodes) == {"e1"}, rep.to_text()
    assert check in rep.to_text() and "logs/bad.parquet: row" in rep.to_text()
    assert "np.float64(" not in rep.to_text()  # numbers as numbers (a mismatch printed numpy's repr)


CONTINUOUS = DatasetInfo(features=(Feature("x"),), action_table=ActionTable(
    actions=ActionTable.from_values([0.0, 1.0]).actions, dims=("u",), kind="continuous", low=(-1.0,), high=(1.0,)))
#: checks of the exact commands (a continuous action table): (mutation, expected column)
COMMAND_DEFECTS = {
    "command_out_of_bounds": (lambda r: r[2].update({"action_value.u": 1.5}), "action_value.u"),
    "command_width": (lambda r: [x.pop("action_value.u") for x in r], "action_value.u"),
    "non_finite": (lambda r: r[2].update({"action_value.u": float("nan")}), "action_value.u"),
}


@pytest.mark.parametrize("check", sorted(COMMAND_DEFECTS))
def test_each_command_defect_is_reported_with_file_row_column(check):
    rows = _good()
    for r in rows:
        r["action_value.u"] = 0.25 * r[S.ACTION]
    mutate, column = COMMAND_DEFECTS[check]
    ds = TransitionDataset(pa.Table.from_pylist(rows), CONTINUOUS)
    assert validate(ds).ok
    mutate(rows if check == "command_width" else rows[4:8])
    ds = TransitionDataset(pa.Table.from_pylist(rows), CONTINUOUS)
    origin = RowOrigin(["logs/bad.parquet"], np.zeros(len(ds), int), np.arange(len(ds)) + 100)
    rep = validate(ds, origin=origin)
    hits = rep.findings[rep.findings["check"] == check]
    assert len(hits) and set(hits["column"]) == {column}, rep.to_text()
    assert hits.iloc[0]["file"] == "logs/bad.parquet"
    if check != "command_width":  # a missing column: every episode (its first row)
        assert set(rep.bad_episodes) == {"e1"} and hits.iloc[0]["row"] == 106, rep.to_text()
    else:
        assert set(rep.bad_episodes) == {"e0", "e1", "e2"}


#: Findings the Parquet ingestion passes to the doctor (validate's ``extra``), tested there:
#: test_hardening_ingest.py::test_source_changing_within_an_episode_is_a_finding_naming_file_row_episode
INGEST_CHECKS = {"source_changed"}


def test_every_check_is_covered_by_a_test():
    assert set(DEFECTS) | DIRECTORY_CHECKS | set(COMMAND_DEFECTS) | INGEST_CHECKS == set(CHECKS)


def test_terminated_and_truncated_on_one_row_is_terminated_and_counted():
    """gymnasium reports both flags when the goal is reached on the time-limit step."""
    rows = _good()
    rows[7][S.TERMINATED] = True  # e1's last row: truncated and terminated
    rows[11][S.TERMINATED] = True
    ds = TransitionDataset(pa.Table.from_pylist(rows), INFO)
    rep = validate(ds)
    assert rep.ok, rep.to_text()
    assert rep.summary()["terminated_and_truncated"] == 2
    assert "2 rows both terminated and truncated" in rep.to_text()
    # still a defect when it is not the episode's last row
    rows[5][S.TERMINATED] = rows[5][S.TRUNCATED] = True
    rep = validate(TransitionDataset(pa.Table.from_pylist(rows), INFO))
    assert set(rep.findings["check"]) == {"flag_not_last"}


def _rewrite_parts(d, bounds):
    import pyarrow.parquet as pq

    from offline_adp.data.io import part_files

    t = pa.concat_tables([pq.read_table(p) for p in part_files(d)])
    for p in part_files(d):
        p.unlink()
    for k, (lo, hi) in enumerate(bounds):
        pq.write_table(t.slice(lo, hi - lo), d / "data" / f"part-{k:05d}.parquet")
    return t


@pytest.mark.parametrize("case", ["info_stale", "fingerprint_mismatch", "episodes_stale", "episode_split_across_parts"])
def test_directory_metadata_checks(tmp_path, case):
    import json

    import pyarrow.parquet as pq

    ds = TransitionDataset(pa.Table.from_pylist(_good()), INFO)
    d = tmp_path / "d"
    ds.save(d, rows_per_part=4)
    assert validate_directory(d).ok
    info = json.loads((d / S.INFO_FILE).read_text())
    if case == "info_stale":
        info["n_transitions"] += 4
        (d / S.INFO_FILE).write_text(json.dumps(info))
    elif case == "fingerprint_mismatch":
        p = d / "data" / "part-00001.parquet"
        t = pq.read_table(p)
        pq.write_table(t.set_column(t.schema.get_field_index(S.COST), S.COST, pa.array(np.full(t.num_rows, 2.0))), p)
    elif case == "episodes_stale":
        ep = pq.read_table(d / S.EPISODES_FILE)
        pq.write_table(ep.slice(0, 2), d / S.EPISODES_FILE)
    else:
        _rewrite_parts(d, [(0, 6), (6, 12)])  # episode e1 (rows 4..7) now spans two parts
    rep = validate_directory(d)
    assert set(rep.findings["check"]) == {case}, rep.to_text()
    h = rep.findings.iloc[0]
    if case == "episode_split_across_parts":
        assert h["file"].endswith("part-00001.parquet") and h[S.EPISODE_ID] == "e1" and h["row"] == 0 and h[S.STEP] == 2
    else:
        assert h["file"].endswith("info.json" if case != "episodes_stale" else "episodes.parquet")


def test_quarantine_keeps_every_rejected_row():
    rows = _good(n_eps=5)
    rows[5][S.COST] = float("inf")  # e1
    rows[14]["next_obs.x"] = -1.0  # e3
    ds = TransitionDataset(pa.Table.from_pylist(rows), INFO)
    origin = RowOrigin(["a.parquet", "b.parquet"], np.repeat([0, 1], 10), np.r_[np.arange(10), np.arange(10)])
    rep = validate(ds, origin=origin)
    assert set(rep.findings["file"]) == {"a.parquet", "b.parquet"}
    clean, q = split_quarantine(ds, rep)
    assert len(clean) + q.num_rows == len(ds)
    assert set(q.column(S.EPISODE_ID).to_pylist()) == {"e1", "e3"}
    reasons = q.column("reason").to_pylist()
    assert all(reasons)
    assert any("[non_finite] cost" in r for r in reasons)
    assert any("[next_obs_mismatch]" in r for r in reasons)
    assert any(r.startswith("episode rejected:") for r in reasons)
    assert validate(clean).ok


def test_validate_directory_names_part_files(tmp_path):
    rows = _good()
    rows[6][S.ACTION] = -1
    ds = TransitionDataset(pa.Table.from_pylist(rows), INFO)
    ds.save(tmp_path / "d", rows_per_part=4)
    rep = validate_directory(tmp_path / "d")
    h = rep.findings.iloc[0]
    assert h["file"].endswith("part-00001.parquet") and h["row"] == 2 and h["check"] == "action_out_of_range"


def test_continuity_tolerance_is_numpys_isclose():
    # the doctor's blockwise continuity check flags exactly the rows np.isclose rejects
    from offline_adp.data.info import ActionTable, DatasetInfo, Feature
    from offline_adp.data.validate import _BLOCK

    rng = np.random.default_rng(0)
    n = 2 * _BLOCK + 17  # crosses block boundaries
    obs = rng.normal(scale=1e3, size=n)
    nxt = np.r_[obs[1:], 0.0]
    off = rng.random(n) < 0.01
    nxt[off] += rng.choice([1e-12, 1e-8, 1e-4, 1.0], size=off.sum()) * rng.choice([1.0, 1e3], size=off.sum())
    nxt[rng.random(n) < 0.001] = np.inf
    info = DatasetInfo(features=(Feature("x"),), action_table=ActionTable.from_values([0.0]))
    ds = TransitionDataset.from_arrays(info, episode_id=np.zeros(n).astype(int).astype(str), step=np.arange(n), obs=obs,
                                       action=np.zeros(n, int), cost=np.zeros(n), next_obs=nxt,
                                       terminated=np.zeros(n, bool), truncated=np.arange(n) == n - 1)
    f = validate(ds).findings
    got = np.sort(f.loc[f["check"] == "next_obs_mismatch", "row"].to_numpy())
    truth = np.flatnonzero(~np.isclose(nxt[:-1], obs[1:], atol=1e-9, rtol=1e-7) & np.isfinite(nxt[:-1]))
    np.testing.assert_array_equal(got, truth)
    assert len(truth) > 10
