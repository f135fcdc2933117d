"""Parquet/CSV ingestion through a spec."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import pytest

from offline_adp.data import schema as S
from offline_adp.data.dataset import read_dataset
from offline_adp.data.io import read_quarantine
from offline_adp.errors import IngestError, SpecError, ValidationError
from offline_adp.ingest.parquet import ingest_parquet
from offline_adp.ingest.spec import load_parquet_spec, parse_parquet_spec
from offline_adp.simulate import simulate
from offline_adp.simulate.raw import write_raw

FIELDS = ("obs", "action", "cost", "next_obs", "terminated", "truncated", "step", "episode", "behavior_prob")


@pytest.mark.parametrize("problem,fmt", [("path_tracking", "parquet"), ("gridworld", "parquet"), ("car_on_hill", "csv"),
                                         ("tabular", "parquet")])
def test_round_trip_simulate_raw_ingest_is_exact(tmp_path, problem, fmt):
    ds = simulate(problem, 10, 10, seed=5, horizon=40)
    raw, spec = write_raw(ds, tmp_path / f"raw.{fmt}", fmt=fmt)
    res = ingest_parquet([raw], spec, tmp_path / "ds")
    back = read_dataset(tmp_path / "ds")
    a, b = ds.arrays(), back.arrays()
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    assert back.fingerprint() == ds.fingerprint()
    assert res.report.ok and res.quarantined_rows == 0
    prov = back.info.provenance
    assert prov["inputs"][0]["sha256"] and prov["spec_sha256"] and prov["package_version"]
    # every row traces back to its file and row
    np.testing.assert_array_equal(back.table.column("src_row").to_numpy(), np.arange(len(ds)))


def _steps_table():
    # two episodes in a step table: e0 ends terminated, e1 is cut (truncated) by the log
    return pd.DataFrame(
        {
            "ep": ["e0"] * 3 + ["e1"] * 4,
            "t": [0.0, 0.1, 0.2, 5.0, 5.1, 5.2, 5.3],
            "pos": [0.0, 1.0, 2.0, 10.0, 11.0, 12.0, 13.0],
            "steer": [0.05, -0.4, 0.31, 0.0, 0.2, -0.2, 0.1],
            "reward": [-1.0, -2.0, 3.0, 0.5, 0.5, 0.5, 0.5],
            "done": [False, False, True, False, False, False, False],
        }
    )


STEP_SPEC = """
kind = "steps"
[episode]
id = "ep"
order = "t"
time = "t"
time_unit = "s"
[observations]
columns = ["pos"]
units = { pos = "m" }
[action]
column = "steer"
type = "continuous"
edges = [-1.0, -0.1, 0.1, 1.0]
dim = "steering"
unit = "rad"
[cost]
reward = "reward"
[end]
terminated = "done"
[source]
value = "demonstration"
"""


def test_step_table_next_state_binning_reward_and_dropped_rows(tmp_path):
    df = _steps_table()
    df.to_parquet(tmp_path / "steps.parquet")
    (tmp_path / "spec.toml").write_text(STEP_SPEC)
    res = ingest_parquet([tmp_path / "steps.parquet"], tmp_path / "spec.toml", tmp_path / "ds")
    ds = read_dataset(tmp_path / "ds")
    a = ds.arrays()
    # e0: 3 transitions, last terminated with placeholder next_obs = obs
    # e1: last row has no next state -> dropped and counted; row 3 becomes truncated
    assert res.dropped_last_rows == 1 and len(ds) == 6
    np.testing.assert_array_equal(a.next_obs[:, 0], [1.0, 2.0, 2.0, 11.0, 12.0, 13.0])
    np.testing.assert_array_equal(a.terminated, [0, 0, 1, 0, 0, 0])
    np.testing.assert_array_equal(a.truncated, [0, 0, 0, 0, 0, 1])
    np.testing.assert_array_equal(a.cost, [1.0, 2.0, -3.0, -0.5, -0.5, -0.5])  # cost = -reward
    # binning: edges [-1, -0.1, 0.1, 1]; bin values = mean of the commands in each bin
    np.testing.assert_array_equal(a.action, [1, 0, 2, 1, 2, 0])
    at = ds.info.action_table
    assert at.kind == "binned" and at.bin_edges == (-1.0, -0.1, 0.1, 1.0)
    np.testing.assert_allclose(at.values[:, 0], [(-0.4 - 0.2) / 2, (0.05 + 0.0) / 2, (0.31 + 0.2) / 2])
    np.testing.assert_array_equal(ds.table.column(S.T_NS).to_numpy()[:2], [0, 100_000_000])
    assert ds.info.features[0].unit == "m"


def test_quantile_bins_keep_values(tmp_path):
    rng = np.random.default_rng(0)
    n = 400
    df = pd.DataFrame({"ep": np.repeat(np.arange(20), 20).astype(str), "k": np.tile(np.arange(20), 20),
                       "x": rng.normal(size=n), "u": rng.uniform(-1, 1, n), "c": rng.random(n)})
    df.to_parquet(tmp_path / "t.parquet")
    spec = parse_parquet_spec({"kind": "steps", "episode": {"id": "ep", "step": "k"},
                               "observations": {"columns": ["x"], "next_columns": ["x"]},
                               "action": {"column": "u", "type": "continuous", "n_bins": 4}, "cost": {"column": "c"}})
    ds = ingest_parquet([tmp_path / "t.parquet"], spec, tmp_path / "ds").dataset
    counts = np.bincount(ds.arrays().action, minlength=4)
    assert len(ds.info.action_table) == 4 and counts.min() >= 90  # quantile bins are balanced
    vals = ds.info.action_table.values[:, 0]
    assert (np.diff(vals) > 0).all() and vals.min() > -1 and vals.max() < 1


def test_unknown_key_lists_valid_keys(tmp_path):
    (tmp_path / "s.toml").write_text(STEP_SPEC.replace('order = "t"', 'order = "t"\nepisode_col = "x"'))
    with pytest.raises(SpecError, match=r"s.toml: episode.episode_col: unknown key; valid keys are \['id', 'order'"):
        load_parquet_spec(tmp_path / "s.toml")
    with pytest.raises(SpecError, match="valid keys"):
        parse_parquet_spec({"kindd": "steps"})


def test_missing_column_names_file_and_column(tmp_path):
    _steps_table().drop(columns=["reward"]).to_parquet(tmp_path / "steps.parquet")
    (tmp_path / "spec.toml").write_text(STEP_SPEC)
    with pytest.raises(IngestError, match=r"steps.parquet: spec needs columns \['reward'\]"):
        ingest_parquet([tmp_path / "steps.parquet"], tmp_path / "spec.toml", tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


def test_bad_rows_fail_or_quarantine(tmp_path):
    ds = simulate("gridworld", 6, 6, seed=1, horizon=20)
    raw, spec = write_raw(ds, tmp_path / "raw.parquet")
    t = pq.read_table(raw).to_pandas()
    t.loc[7, "action"] = "NE"  # an action outside the declared table
    t.loc[30, "cost"] = np.nan
    t.to_parquet(raw)
    with pytest.raises(ValidationError, match=r"raw.parquet: row 7 .* column 'action'"):
        ingest_parquet([raw], spec, tmp_path / "ds")
    assert not (tmp_path / "ds").exists()
    res = ingest_parquet([raw], spec, tmp_path / "ds", on_error="quarantine")
    q = read_quarantine(tmp_path / "ds")
    bad_eps = {t.loc[7, "episode"], t.loc[30, "episode"]}
    assert set(q.column(S.EPISODE_ID).to_pylist()) == bad_eps
    assert res.quarantined_rows == q.num_rows == int(t["episode"].isin(bad_eps).sum())
    assert len(read_dataset(tmp_path / "ds")) + q.num_rows == len(t)
    assert 7 in q.column("src_row").to_pylist()


def test_episode_ids_across_files_are_an_error(tmp_path):
    ds = simulate("car_on_hill", 2, 2, seed=1)
    raw, spec = write_raw(ds, tmp_path / "a.parquet")
    pq.write_table(pq.read_table(raw), tmp_path / "b.parquet")
    with pytest.raises(IngestError, match="occurs in .*a.parquet and .*b.parquet"):
        ingest_parquet([raw, tmp_path / "b.parquet"], spec, tmp_path / "ds")


def test_several_files_and_unsorted_rows(tmp_path):
    ds = simulate("path_tracking", 6, 6, seed=2, horizon=30)
    table, _ = __import__("offline_adp.simulate.raw", fromlist=["raw_table"]).raw_table(ds)
    raw, spec = write_raw(ds, tmp_path / "all.parquet")
    df = table.to_pandas().sample(frac=1.0, random_state=0)  # shuffled rows
    demo = df[df.source == "demonstration"]
    expl = df[df.source == "exploration"]
    demo.to_parquet(tmp_path / "demo.parquet")
    expl.to_parquet(tmp_path / "expl.parquet")
    back = ingest_parquet([tmp_path / "expl.parquet", tmp_path / "demo.parquet"], spec, tmp_path / "ds").dataset
    assert back.fingerprint() == ds.fingerprint()


def test_discrete_labels_default_to_sorted_distinct(tmp_path):
    df = pd.DataFrame({"ep": ["a", "a", "b"], "k": [0, 1, 0], "x": [0.0, 1.0, 5.0], "nx": [1.0, 2.0, 6.0],
                       "a": ["right", "left", "right"], "c": [1.0, 1.0, 1.0]})
    df.to_csv(tmp_path / "t.csv", index=False)
    spec = parse_parquet_spec({"episode": {"id": "ep", "step": "k"},
                               "observations": {"columns": ["x"], "next_columns": ["nx"]},
                               "action": {"column": "a"}, "cost": {"column": "c"}})
    ds = ingest_parquet([tmp_path / "t.csv"], spec, tmp_path / "ds").dataset
    assert ds.info.action_table.names == ["left", "right"]
    np.testing.assert_array_equal(ds.arrays().action, [1, 0, 1])
    np.testing.assert_array_equal(ds.arrays().truncated, [False, True, True])  # ends are truncated by rule


def test_spec_rejects_inconsistent_choices():
    base = {"episode": {"id": "e", "step": "k"}, "observations": {"columns": ["x"], "next_columns": ["nx"]},
            "action": {"column": "a"}, "cost": {"column": "c"}}
    with pytest.raises(SpecError, match="exactly one of 'column'"):
        parse_parquet_spec({**base, "cost": {"column": "c", "reward": "r"}})
    with pytest.raises(SpecError, match="set type = 'continuous'"):
        parse_parquet_spec({**base, "action": {"column": "a", "n_bins": 3}})
    with pytest.raises(SpecError, match="next_columns"):
        parse_parquet_spec({**base, "observations": {"columns": ["x"]}})
    with pytest.raises(SpecError, match=r"episode.step: Input should be a valid string, got 3"):
        parse_parquet_spec({**base, "episode": {"id": "e", "step": 3}})
    assert isinstance(pa.__version__, str)


def test_checked_in_json_schema_is_the_models():
    """docs/schemas/ingest-spec.schema.json is what the model publishes (regenerate with
    ``offline_adp.config.write_json_schema(ParquetSpecModel, path)``)."""
    import json
    from pathlib import Path

    from offline_adp.ingest.spec import parquet_spec_schema

    path = Path(__file__).resolve().parents[1] / "docs" / "schemas" / "ingest-spec.schema.json"
    assert json.loads(path.read_text()) == parquet_spec_schema()


@pytest.mark.parametrize(
    "edit, match",
    [
        ({"csv": {"delimiter": ";;"}}, r"csv.delimiter: String should have at most 1 character"),
        ({"csv": {"delimiter": ""}}, r"csv.delimiter"),
        ({"hints": {"gamma": 2.0}}, r"hints.gamma: Input should be less than or equal to 1"),
        ({"hints": {"horizon": "ten"}}, r"hints.horizon: Input should be a valid integer"),
        ({"action": {"column": "a", "type": "discret"}},
         r"action.type: expected one of 'discrete' or 'continuous', got 'discret'"),
        ({"action": {"column": "a", "type": "continuous", "n_bins": 0}},
         r"action.n_bins: Input should be greater than or equal to 1"),
        ({"action": {"column": "a", "type": "continuous", "edges": [1.0, 0.0]}}, r"action.edges"),
        ({"action": {"column": "a", "values": [1, 1]}}, r"action.values: entries must be unique"),
        ({"observations": {"columns": ["x", "x"], "next_columns": ["a", "b"]}}, r"observations.columns"),
        ({"episode": {"id": "e", "step": "k", "time_unit": "h"}}, r"episode.time_unit: expected one of"),
        ({"on_error": "ignore"}, r"on_error: expected one of 'fail' or 'quarantine'"),
    ],
)
def test_spec_values_are_checked_naming_the_key(edit, match):
    base = {"episode": {"id": "e", "step": "k"}, "observations": {"columns": ["x"], "next_columns": ["nx"]},
            "action": {"column": "a"}, "cost": {"column": "c"}}
    with pytest.raises(SpecError, match=match):
        parse_parquet_spec({**base, **edit}, where="my.toml")


def test_csv_and_parquet_inputs_with_text_sources_and_row_groups_mix(tmp_path):
    # the Parquet file in small row groups (chunked columns), the other half as CSV: the
    # source labels arrive dictionary-encoded from one and as text from the other
    ds = simulate("path_tracking", 6, 6, seed=3, horizon=30)
    table, _ = __import__("offline_adp.simulate.raw", fromlist=["raw_table"]).raw_table(ds)
    _, spec = write_raw(ds, tmp_path / "all.parquet")
    df = table.to_pandas()
    demo, expl = df[df.source == "demonstration"], df[df.source == "exploration"]
    pq.write_table(pa.Table.from_pandas(demo, preserve_index=False), tmp_path / "demo.parquet", row_group_size=37)
    pacsv.write_csv(pa.Table.from_pandas(expl, preserve_index=False), tmp_path / "expl.csv")
    back = ingest_parquet([tmp_path / "demo.parquet", tmp_path / "expl.csv"], spec, tmp_path / "ds").dataset
    assert back.fingerprint() == ds.fingerprint()
    assert back.source_counts() == ds.source_counts() == {"demonstration": len(demo), "exploration": len(expl)}
    assert read_dataset(tmp_path / "ds").fingerprint() == ds.fingerprint()


def test_fingerprint_of_dictionary_sources_is_that_of_their_strings():
    from offline_adp.data.dataset import TransitionDataset

    ds = simulate("car_on_hill", 3, 3, seed=4, horizon=20)
    words = ds.column(S.SOURCE)  # plain strings: the ground truth
    n = len(words)
    # the same labels as a chunked dictionary column whose chunks have different
    # dictionaries, one of them repeating a word
    k = n // 2
    first = pa.DictionaryArray.from_arrays(pa.array(np.where(words[:k] == "demonstration", 0, 2).astype(np.int32)),
                                           pa.array(["demonstration", "unused", "exploration"]))
    second = pa.DictionaryArray.from_arrays(pa.array(np.where(words[k:] == "demonstration", 1, 0).astype(np.int32)),
                                            pa.array(["exploration", "demonstration", "exploration"]))
    t = ds.table.set_column(ds.table.column_names.index(S.SOURCE), S.SOURCE, pa.chunked_array([first, second]))
    as_dict = TransitionDataset(t, ds.info)
    as_text = TransitionDataset(ds.table.set_column(ds.table.column_names.index(S.SOURCE), S.SOURCE,
                                                    pa.array(words.astype(str), pa.string())), ds.info)
    assert as_dict.fingerprint() == as_text.fingerprint() == ds.fingerprint()
    assert as_dict.source_counts() == ds.source_counts()


@pytest.mark.parametrize("cut", [1, 3, 4, 5])
def test_sorted_encoding_across_chunks_is_the_hashed_encoding(cut):
    from offline_adp.data.columns import encode_strings, sorted_encoding

    ids = ["a", "a", "b", "b", "b", "c"]
    order = np.array([0, 1, 0, 1, 2, 0])
    chunked = pa.chunked_array([pa.array(ids[:cut]), pa.array(ids[cut:])])
    enc = sorted_encoding(chunked, order)
    truth = encode_strings(pa.array(ids))
    assert enc.dictionary.to_pylist() == truth.dictionary.to_pylist() == ["a", "b", "c"]
    np.testing.assert_array_equal(enc.indices.to_numpy(), truth.indices.to_numpy())
    # a decrease of the id, or of the order within an id, wherever it falls, is "not sorted"
    bad_ids = ids[:cut] + ["0"] + ids[cut:]  # "0" < "a": a decrease at the chunk boundary
    assert sorted_encoding(pa.chunked_array([pa.array(bad_ids[:cut]), pa.array(bad_ids[cut:])]),
                           np.r_[order[:cut], 5, order[cut:]]) is None
    assert sorted_encoding(pa.chunked_array([pa.array(bad_ids[:cut + 1]), pa.array(bad_ids[cut + 1:])]),
                           np.r_[order[:cut], 5, order[cut:]]) is None  # and inside a chunk
    bad_order = order.copy()
    bad_order[4] = 0
    assert sorted_encoding(chunked, bad_order) is None


def test_parts_share_one_schema_when_a_column_has_nulls_in_one_part_only(tmp_path):
    """Columns without nulls are written as required; a column with a null anywhere is
    optional in every part, so readers of single parts (Dask) see one schema, and the
    values (nulls included) read back as written."""
    from offline_adp.data.dataset import TransitionDataset
    from offline_adp.data.io import part_files, write_dataset

    ds = simulate("car_on_hill", 4, 4, seed=3, horizon=25)
    t = ds.table
    bp = t.column(S.BEHAVIOR_PROB).to_pylist()
    bp[len(bp) - 2] = None  # in the last part only
    t = t.set_column(t.column_names.index(S.BEHAVIOR_PROB), S.BEHAVIOR_PROB, pa.array(bp, pa.float64()))
    with_null = TransitionDataset(t, ds.info)
    out = write_dataset(with_null, tmp_path / "d", rows_per_part=30)
    parts = part_files(out)
    assert len(parts) > 2
    schemas = [pq.read_schema(p) for p in parts]
    assert all(s.equals(schemas[0]) for s in schemas)
    assert schemas[0].field(S.BEHAVIOR_PROB).nullable and not schemas[0].field(S.COST).nullable
    assert pq.read_table(parts[0]).column(S.BEHAVIOR_PROB).null_count == 0
    back = read_dataset(out)
    assert back.table.column(S.BEHAVIOR_PROB).to_pylist() == bp
    for name in t.column_names:
        assert back.table.column(name).to_pylist() == with_null.table.column(name).to_pylist(), name
    assert back.fingerprint() == with_null.fingerprint()


def test_api_takes_one_path_and_refuses_wrong_arguments_with_our_error(tmp_path):
    """A str was iterated character by character; None gave a plain TypeError."""
    from offline_adp.errors import InvalidArgumentError

    ds = simulate("car_on_hill", 2, 2, seed=1)
    raw, spec = write_raw(ds, tmp_path / "a.parquet")
    for k, one in enumerate((str(raw), raw)):
        assert ingest_parquet(one, spec, tmp_path / f"ds{k}").dataset.fingerprint() == ds.fingerprint()
    for inputs, sp, out, arg in ((None, spec, tmp_path / "o", "inputs"), ([raw, 3], spec, tmp_path / "o", "inputs"),
                                 ([raw], spec, None, "out"), ([raw], {"kind": "steps"}, tmp_path / "o", "spec")):
        with pytest.raises(InvalidArgumentError, match=rf"^{arg} must be"):
            ingest_parquet(inputs, sp, out)
    assert not (tmp_path / "o").exists()


def test_output_that_is_inside_or_holds_an_input_or_a_dataset_is_refused_before_writing(tmp_path):
    """--overwrite replaced the input file, the folder holding it, or an existing dataset's data/."""
    from offline_adp.errors import OutputExistsError

    ds = simulate("car_on_hill", 2, 2, seed=1)
    raw, spec = write_raw(ds, tmp_path / "in" / "a.parquet")
    before = raw.read_bytes()
    for out, what in ((raw, "is the input"), (tmp_path / "in", "contains the input"),
                      (raw / "sub", "lies inside the input")):
        with pytest.raises(OutputExistsError, match=what):
            ingest_parquet([raw], spec, out, overwrite=True)
    assert raw.read_bytes() == before and not list((tmp_path / "in").glob(".*"))  # not even a lock file
    ingest_parquet([raw], spec, tmp_path / "ds")
    with pytest.raises(OutputExistsError, match=r"lies inside the dataset directory .*ds"):
        ingest_parquet([raw], spec, tmp_path / "ds" / "data", overwrite=True)
    assert read_dataset(tmp_path / "ds").fingerprint() == ds.fingerprint()
    ingest_parquet(str(raw), spec, tmp_path / "ds", overwrite=True)  # replacing the dataset itself is --overwrite
    from offline_adp.data.io import check_dataset_output

    check_dataset_output(tmp_path / "in" / "ds", [tmp_path / "in"])  # inside an input directory (a bag): allowed


def test_the_doctor_says_how_its_rows_count_and_a_csv_s_line_is_row_plus_two(tmp_path):
    """A newcomer read "row 37" of a CSV as its 37th line: the report says rows count data
    rows from 0, and a CSV's line is row + 2; the line named holds the bad value."""
    from offline_adp.errors import ValidationError

    n = 60
    df = pd.DataFrame({"ep": np.repeat([0, 1], n // 2), "k": np.tile(np.arange(n // 2), 2),
                       "x": np.arange(n, dtype=float), "c": np.ones(n)})
    df["nx"] = df["x"] + 1.0
    df.loc[37, "c"] = np.nan
    df.to_csv(tmp_path / "t.csv", index=False)
    spec = parse_parquet_spec({"episode": {"id": "ep", "step": "k"},
                               "observations": {"columns": ["x"], "next_columns": ["nx"]},
                               "action": {"column": "k"}, "cost": {"column": "c"}})
    with pytest.raises(ValidationError) as e:
        ingest_parquet([tmp_path / "t.csv"], spec, tmp_path / "ds")
    text = str(e.value)
    assert ("(rows count each file's data rows from 0; in a CSV without blank lines or cells over several lines, "
            "the line is row + 2)") in text
    row = int(text.split("t.csv: row ")[1].split(" ")[0])
    line = (tmp_path / "t.csv").read_text().splitlines()[row + 2 - 1]  # 1-based line numbers
    assert row == 37 and line.split(",")[3] == ""  # the NaN cost written as an empty cell
    assert "column 'cost' (input column 'c'): [non_finite]" in text  # the dataset's column and the file's


def _eps(n_eps=4, L=5):
    rows = [dict(episode=f"ep{e}", t=0.1 * s, x=float(10 * e + s), next_x=float(10 * e + s + 1), a=s % 2,
                 cost=1.0, src="01" if e % 2 else "2") for e in range(n_eps) for s in range(L)]
    return pd.DataFrame(rows)


_TIME_SPEC = {"episode": {"id": "episode", "time": "t", "time_unit": "s"},
              "observations": {"columns": ["x"], "next_columns": ["next_x"]},
              "action": {"column": "a"}, "cost": {"column": "cost"}}


def test_a_missing_time_is_the_doctors_and_inputs_may_be_a_generator(tmp_path):
    """A review of this session's hardening: a null time made the whole ingest fail (the
    order column's check ran on ``episode.time`` too), and a generator of inputs was read
    twice (the second time empty)."""
    df = _eps()
    df.loc[7, "t"] = np.nan  # episode ep1
    df.to_parquet(tmp_path / "a.parquet")
    spec = parse_parquet_spec({**_TIME_SPEC, "on_error": "quarantine"})
    res = ingest_parquet((p for p in [tmp_path / "a.parquet"]), spec, tmp_path / "ds")
    assert res.dataset.n_episodes == 3 and res.quarantined_episodes == 1 and "ep1" not in list(res.dataset.episode_ids)


def test_an_empty_csv_source_cell_is_a_missing_source_not_a_label(tmp_path):
    df = _eps()
    df["src"] = df["src"].astype(object)
    df.loc[df["episode"] == "ep0", "src"] = None  # written as empty cells: one episode without a source
    df.to_csv(tmp_path / "a.csv", index=False)
    spec = parse_parquet_spec({**_TIME_SPEC, "source": {"column": "src"}, "on_error": "quarantine"})
    res = ingest_parquet([tmp_path / "a.csv"], spec, tmp_path / "ds")
    assert "" not in res.dataset.source_counts() and res.quarantined_episodes == 1
    assert set(res.dataset.source_counts()) == {"01", "2"}  # labels as written (text, not numbers)
