"""Issue 16, hostile Parquet/CSV input: each case is one of our errors naming file, row and
column (or a doctor finding that fails or quarantines the episode), never wrong data or a
raw traceback. Also issue 14 item 6: gymnasium's both-flags rows ingest as terminated.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from offline_adp.data import schema as S
from offline_adp.data.dataset import read_dataset
from offline_adp.errors import IngestError, SpecError, ValidationError
from offline_adp.ingest.parquet import ingest_parquet
from offline_adp.ingest.spec import parse_parquet_spec

ROOT = Path(__file__).resolve().parents[1]
BASE = {"episode": {"id": "ep", "step": "k"}, "observations": {"columns": ["x"], "next_columns": ["nx"]},
        "action": {"column": "a"}, "cost": {"column": "c"}, "end": {"terminated": "done"}}


def _df() -> pd.DataFrame:
    return pd.DataFrame({"ep": ["a", "a", "b"], "k": [0, 1, 0], "x": [0.0, 1.0, 5.0], "nx": [1.0, 2.0, 6.0],
                         "a": [0, 1, 0], "c": [1.0, 1.0, 1.0], "done": [False, True, True],
                         "t": [0.0, 1.0, 0.0], "p": [0.5, 0.5, 0.5]})


def _ingest(tmp_path, frames, spec=BASE, **kw):
    paths = []
    for i, f in enumerate(frames if isinstance(frames, list) else [frames]):
        p = tmp_path / f"in{i}.parquet"
        f.to_parquet(p)
        paths.append(p)
    return ingest_parquet(paths, parse_parquet_spec(spec), tmp_path / "out", **kw)


def test_steps_beyond_int32_are_refused_not_wrapped(tmp_path):
    t = _df()
    t["k"] = [2**32, 2**32 + 1, 0]  # int32 casting would silently make these 0, 1
    with pytest.raises(IngestError, match=r"in0.parquet: row 0.*'k'.*4294967296"):
        _ingest(tmp_path, t)
    assert not (tmp_path / "out").exists()


def test_fractional_step_is_refused(tmp_path):
    t = _df()
    t["k"] = [0.0, 1.5, 0.0]  # would be truncated to 1
    with pytest.raises(IngestError, match=r"in0.parquet: row 1.*'k'.*1.5 is not a whole number"):
        _ingest(tmp_path, t)


def test_null_terminated_is_a_finding_not_a_truncation(tmp_path):
    t = _df()
    t["done"] = pd.array([False, None, True], dtype="boolean")
    with pytest.raises(ValidationError, match=r"in0.parquet: row 1 .*column 'terminated'.*null_value"):
        _ingest(tmp_path, t)
    res = _ingest(tmp_path, t, on_error="quarantine")
    assert res.quarantined_episodes == 1 and set(read_dataset(tmp_path / "out").episode_ids) == {"b"}


def test_nan_time_is_a_finding_not_int64_min(tmp_path):
    t = _df()
    t["t"] = [np.nan, 1.0, 0.0]
    spec = {**BASE, "episode": {"id": "ep", "step": "k", "time": "t", "time_unit": "s"}}
    with pytest.raises(ValidationError, match=r"in0.parquet: row 0 .*column 't_ns'.*null_value"):
        _ingest(tmp_path, t, spec)
    _ingest(tmp_path, t, spec, on_error="quarantine")
    ts = read_dataset(tmp_path / "out").table.column(S.T_NS).to_pylist()
    assert ts == [0]  # episode a quarantined; nothing at INT64_MIN


def test_string_in_propensity_column_names_file_row_column(tmp_path):
    t = _df()
    t["p"] = ["0.5", "x", "0.5"]
    with pytest.raises(IngestError, match=r"in0.parquet: row 1: column 'p': 'x' is not a number"):
        _ingest(tmp_path, t, {**BASE, "propensity": {"column": "p"}})


def test_null_episode_id_names_file_row_column(tmp_path):
    t = _df()
    t["ep"] = ["a", None, "b"]
    with pytest.raises(IngestError, match=r"in0.parquet: row 1 column 'ep': episode id is missing"):
        _ingest(tmp_path, t)


def test_incompatible_types_across_files_name_the_column_and_files(tmp_path):
    t2 = _df()
    t2["ep"] = ["c", "c", "d"]
    t2["x"] = ["s", "t", "u"]
    with pytest.raises(IngestError, match=r"column 'x' is double in .*in0.parquet but .*string in .*in1.parquet"):
        _ingest(tmp_path, [_df(), t2])


def test_non_utf8_csv_names_file_row_column(tmp_path):
    p = tmp_path / "latin1.csv"
    p.write_bytes("ep,k,x,nx,a,c,done,lab\na,0,0,1,0,1,false,ok\na,1,1,2,1,1,true,caf\xe9\n".encode("latin-1"))
    spec = {**BASE, "source": {"column": "lab"}}
    with pytest.raises(IngestError, match=r"latin1.csv: row 1 column 'lab': not UTF-8"):
        ingest_parquet([p], parse_parquet_spec(spec), tmp_path / "out")


def test_non_utf8_spec_is_a_spec_error(tmp_path):
    from offline_adp.ingest.spec import load_parquet_spec

    p = tmp_path / "spec.toml"
    p.write_bytes('kind = "steps"\nname = "caf\xe9"\n'.encode("latin-1"))
    with pytest.raises(SpecError, match=r"spec.toml: line 2: not UTF-8"):
        load_parquet_spec(p)


def test_csv_delimiter_must_be_one_character():
    with pytest.raises(SpecError, match=r"csv.delimiter"):
        parse_parquet_spec({**BASE, "csv": {"delimiter": ";;"}})


def test_cli_prints_one_line_and_exits_2(tmp_path):
    t = _df()
    t["p"] = ["0.5", "x", "0.5"]
    t.to_parquet(tmp_path / "in.parquet")
    (tmp_path / "spec.toml").write_text(
        '[episode]\nid = "ep"\nstep = "k"\n[observations]\ncolumns = ["x"]\nnext_columns = ["nx"]\n'
        '[action]\ncolumn = "a"\n[cost]\ncolumn = "c"\n[end]\nterminated = "done"\n[propensity]\ncolumn = "p"\n')
    r = subprocess.run([sys.executable, "-m", "offline_adp", "ingest", "parquet", str(tmp_path / "in.parquet"),
                        "--spec", str(tmp_path / "spec.toml"), "--out", str(tmp_path / "out")],
                       capture_output=True, text=True, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and "row 1" in r.stderr and "'p'" in r.stderr


def _mountain_car_log(n_episodes: int = 3, seed: int = 0) -> tuple[pd.DataFrame, int]:
    """A gymnasium MountainCar-v0 log where an episode reaches the goal on the time-limit step.

    An energy-pumping policy (push in the direction of the velocity) reaches the goal in
    about 100 steps; the time limit is set to exactly the step at which the goal is
    reached, so gymnasium returns ``terminated`` and ``truncated`` both true there.
    """
    import gymnasium as gym

    def policy(obs):
        return 2 if obs[1] >= 0 else 0

    # find the goal step under the default limit, then re-run with the limit at that step
    env = gym.make("MountainCar-v0")
    obs, _ = env.reset(seed=seed)
    for k in range(1, 201):
        obs, _, term, trunc, _ = env.step(policy(obs))
        if term:
            goal_step = k
            break
    else:  # pragma: no cover - the heuristic reaches the goal
        raise AssertionError("heuristic did not reach the goal")
    rows = []
    both = 0
    for e in range(n_episodes):
        env = gym.make("MountainCar-v0", max_episode_steps=goal_step if e == 0 else 200)
        obs, _ = env.reset(seed=seed)
        for k in range(200):
            a = policy(obs) if e < 2 else int(np.random.default_rng(e + k).integers(3))
            nxt, r, term, trunc, _ = env.step(a)
            rows.append({"episode": e, "step": k, "position": obs[0], "velocity": obs[1], "action": a, "reward": r,
                         "next_position": nxt[0], "next_velocity": nxt[1], "terminated": term, "truncated": trunc})
            both += bool(term and trunc)
            obs = nxt
            if term or trunc:
                break
    return pd.DataFrame(rows), both


def test_gymnasium_mountain_car_goal_on_time_limit_step_ingests(tmp_path):
    df, both = _mountain_car_log()
    assert both == 1  # gymnasium set both flags on the goal step of episode 0
    df.to_parquet(tmp_path / "mc.parquet")
    spec = {"episode": {"id": "episode", "step": "step"},
            "observations": {"columns": ["position", "velocity"], "next_columns": ["next_position", "next_velocity"]},
            "action": {"column": "action", "values": [0, 1, 2]}, "cost": {"reward": "reward"},
            "end": {"terminated": "terminated", "truncated": "truncated"}}
    res = ingest_parquet([tmp_path / "mc.parquet"], parse_parquet_spec(spec), tmp_path / "ds")
    assert res.report.ok and res.summary()["terminated_and_truncated"] == 1
    ds = read_dataset(tmp_path / "ds")
    a = ds.arrays()
    assert len(ds) == len(df)
    ep0_last = np.flatnonzero(ds.episode_ids[ds.episode_index] == "0")[-1]
    assert a.terminated[ep0_last] and a.truncated[ep0_last]  # absorbing: terminated wins
    assert a.next_obs[ep0_last, 0] >= 0.5  # the goal position
    import json

    stats = json.loads((tmp_path / "ds" / S.STATS_FILE).read_text())
    assert stats["terminated_and_truncated"] == 1


def test_text_with_nulls_in_a_feature_column_names_file_row_column(tmp_path):
    """Found by the nightly fuzz profile: a string column with nulls crashed in Arrow's cast."""
    t = _df()
    t["x"] = pd.Series(["0.5", None, "x"], dtype=object)
    with pytest.raises(IngestError, match=r"in0.parquet: row 2: column 'x': 'x' is not a number"):
        _ingest(tmp_path, t)


def _csv(tmp_path, df: pd.DataFrame, name: str = "in.csv") -> Path:
    p = tmp_path / name
    df.to_csv(p, index=False)
    return p


def test_csv_episode_ids_are_the_files_text(tmp_path):
    """Type inference made '007' and '7' (and '1.1' and '1.10') one episode, '000' -> '0'."""
    t = pd.DataFrame({"ep": ["007", "007", "7", "1.1", "1.10", "000"], "k": [0, 1, 0, 0, 0, 0],
                      "x": [0.0, 1.0, 5.0, 2.0, 3.0, 4.0], "nx": [1.0, 2.0, 6.0, 3.0, 4.0, 5.0],
                      "a": [0, 1, 0, 1, 0, 1], "c": 1.0, "done": [False, True, True, True, True, True]})
    p = _csv(tmp_path, t)
    ingest_parquet([p], parse_parquet_spec(BASE), tmp_path / "out")
    ds = read_dataset(tmp_path / "out")
    assert sorted(set(ds.episode_ids)) == ["000", "007", "1.1", "1.10", "7"]
    assert len(ds) == 6


def test_csv_source_and_text_action_labels_are_the_files_text(tmp_path):
    t = _df()
    t["src"] = ["01", "01", "1"]
    t["a"] = ["01", "1", "01"]
    p = _csv(tmp_path, t)
    spec = {**BASE, "action": {"column": "a", "values": ["01", "1"]}, "source": {"column": "src"}}
    ingest_parquet([p], parse_parquet_spec(spec), tmp_path / "out")
    ds = read_dataset(tmp_path / "out")
    assert ds.source_counts() == {"01": 2, "1": 1}
    assert ds.table.column(S.ACTION).to_pylist() == [0, 1, 0]


def test_csv_empty_episode_id_is_missing(tmp_path):
    t = _df()
    t["ep"] = ["a", None, "b"]
    with pytest.raises(IngestError, match=r"in.csv: row 1 column 'ep': episode id is missing"):
        ingest_parquet([_csv(tmp_path, t)], parse_parquet_spec(BASE), tmp_path / "out")


def test_csv_header_not_utf8_names_the_file(tmp_path):
    p = tmp_path / "latin1.csv"
    p.write_bytes("ep,k,x,nx,a,c,done,caf\xe9\na,0,0,1,0,1,true,1\n".encode("latin-1"))
    with pytest.raises(IngestError, match=r"latin1.csv: the header .*not UTF-8.*save the file as UTF-8"):
        ingest_parquet([p], parse_parquet_spec(BASE), tmp_path / "out")


@pytest.mark.parametrize("labels", [["L", None, "R"], ["L", None, "None"]])
def test_null_action_label_is_a_null_finding_not_a_label(tmp_path, labels):
    t = _df()
    t["a"] = pd.Series(labels, dtype=object)
    with pytest.raises(ValidationError, match=r"in0.parquet: row 1 .*column 'action'.*null_value"):
        _ingest(tmp_path, t)
    res = _ingest(tmp_path, t, on_error="quarantine")
    assert res.quarantined_episodes == 1
    assert [a.name for a in res.dataset.info.action_table.actions] == sorted({"L", labels[2]})
    assert res.quarantine.column(S.ACTION).to_pylist() == [0, None]


def test_null_source_is_a_null_finding_not_a_source(tmp_path):
    t = _df()
    t["src"] = pd.Series(["demo", None, "demo"], dtype=object)
    spec = {**BASE, "source": {"column": "src"}}
    with pytest.raises(ValidationError, match=r"in0.parquet: row 1 .*column 'source'.*null_value"):
        _ingest(tmp_path, t, spec)
    res = _ingest(tmp_path, t, spec, on_error="quarantine")
    assert res.dataset.source_counts() == {"demo": 1}


def test_uint64_step_beyond_int64_is_reported_as_logged_not_wrapped(tmp_path):
    t = _df()
    t["k"] = np.array([0, 1, 2**64 - 100], dtype=np.uint64)
    with pytest.raises(IngestError, match=r"in0.parquet: row 2: column 'k': step 18446744073709551516 is outside"):
        _ingest(tmp_path, t)


@pytest.mark.parametrize("col", ["x", "nx", "c"])
def test_integer_beyond_2_53_in_a_float_column_is_refused_not_rounded(tmp_path, col):
    t = _df()
    t[col] = np.array([1, 2**53 + 1, 3], dtype=np.int64)
    with pytest.raises(IngestError, match=rf"in0.parquet: row 1: column '{col}': integer 9007199254740993 is beyond "
                                          r"2\^53"):
        _ingest(tmp_path, t)


def test_integers_up_to_2_53_in_a_float_column_are_kept(tmp_path):
    t = _df()
    t["x"] = np.array([0, 2**53, -(2**53)], dtype=np.int64)
    t["nx"] = t["x"]
    res = _ingest(tmp_path, t, on_error="quarantine")
    assert res.dataset.table.column(S.obs_column("x")).to_pylist() == [-(2.0**53)]


@pytest.mark.parametrize("values,what", [(pa.array([0.0, float("nan"), 0.0]), "NaN"),
                                         (pa.array([0, None, 0], pa.int64()), r"missing \(null\)")])
def test_missing_or_nan_order_value_is_refused_like_a_null_step(tmp_path, values, what):
    t = pa.Table.from_pandas(_df(), preserve_index=False)
    t = t.set_column(t.column_names.index("t"), "t", values)
    pq.write_table(t, tmp_path / "in0.parquet")
    spec = {**BASE, "episode": {"id": "ep", "order": "t"}}
    with pytest.raises(IngestError, match=rf"in0.parquet: row 1: column 't': the order value is {what}"):
        ingest_parquet([tmp_path / "in0.parquet"], parse_parquet_spec(spec), tmp_path / "out")


def test_source_changing_within_an_episode_is_a_finding_naming_file_row_episode(tmp_path):
    t = _df()
    t["src"] = ["demo", "explore", "demo"]
    spec = {**BASE, "source": {"column": "src"}}
    with pytest.raises(ValidationError, match=r"in0.parquet: row 1 \(episode a, step 1\) column 'src': "
                                              r"\[source_changed\] source 'explore' after 'demo'"):
        _ingest(tmp_path, t, spec)
    res = _ingest(tmp_path, t, spec, on_error="quarantine")
    assert res.quarantined_episodes == 1 and res.dataset.source_counts() == {"demo": 1}
    # a steps table whose dropped last rows shift the rows: the message stays with its row
    s = pd.DataFrame({"ep": ["a"] * 3 + ["b"] * 3, "k": [0, 1, 2] * 2, "x": [0.0, 1, 2, 0, 1, 2], "a": 0, "c": 1.0,
                      "done": False, "src": ["d", "d", "d", "d", "e", "e"]})
    steps = {**spec, "kind": "steps", "observations": {"columns": ["x"]}}
    with pytest.raises(ValidationError, match=r"row 4 \(episode b, step 1\) column 'src': \[source_changed\] source "
                                              r"'e' after 'd'"):
        _ingest(tmp_path, s, steps, overwrite=True)
