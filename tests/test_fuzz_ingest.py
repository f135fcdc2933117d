"""Fuzzing Parquet/CSV ingestion and ingestion specs: hostile tables and specs end in a
dataset that passes the doctor, or in one of our errors - never another exception.

Tables: random column types and values (null/huge/fractional/negative steps, NaN/inf/huge
floats, labels outside the action table, null/non-bool flags, non-numeric propensities,
null or numeric episode ids), written as Parquet or CSV, ingested with ``fail`` or
``quarantine``. When ingestion succeeds: the directory passes ``validate_directory``,
and kept + quarantined + dropped rows add up to the input rows.

Specs: random TOML-like mappings over the spec's keys, and random bytes as a spec file.

Counts: ``N`` examples per test in CI, ``N_NIGHTLY`` under ``--hypothesis-profile nightly``.
"""

from __future__ import annotations

import shutil
import warnings

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from offline_adp.data.dataset import read_dataset
from offline_adp.data.io import read_quarantine
from offline_adp.data.validate import validate_directory
from offline_adp.errors import OfflineADPError
from offline_adp.ingest.parquet import ingest_parquet
from offline_adp.ingest.spec import load_parquet_spec, parse_parquet_spec
from tests.fuzz_util import edit_json_path, json_paths

NIGHTLY = settings().max_examples >= 1000
N = 2000 if NIGHTLY else 30
SETTINGS = settings(max_examples=N, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

BASE = {"kind": "transitions", "episode": {"id": "ep", "step": "k", "time": "t", "time_unit": "s"},
        "observations": {"columns": ["x"], "next_columns": ["nx"]}, "action": {"column": "a", "values": [0, 1, 2]},
        "cost": {"column": "c"}, "end": {"terminated": "done", "truncated": "cut"}, "propensity": {"column": "p"}}

FLOATS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, 1.0, -1.0, 1e200, 5e-324]))


@st.composite
def column(draw, kind: str, n: int):
    """One column of n values of a randomly chosen (sometimes wrong) type."""
    choice = draw(st.sampled_from(["right"] * 8 + ["null", "other"]))
    if kind == "ep":
        vals = draw(st.lists(st.sampled_from(["a", "b", "c"]), min_size=n, max_size=n))
        if choice == "null":
            vals[draw(st.integers(0, n - 1))] = None
        elif choice == "other":
            vals = draw(st.lists(st.integers(-3, 3), min_size=n, max_size=n))
        return pd.Series(vals, dtype=object if choice != "other" else "int64")
    if kind == "k":
        if choice == "other":
            return pd.Series(draw(st.lists(st.one_of(st.floats(allow_nan=True), st.integers(-(2**40), 2**40)),
                                           min_size=n, max_size=n)), dtype="float64")
        vals = draw(st.lists(st.integers(0, 5), min_size=n, max_size=n))
        if draw(st.integers(0, 3)) == 0:
            vals[draw(st.integers(0, n - 1))] = draw(st.sampled_from([2**31, 2**32, -1, 2**62]))
        s = pd.Series(vals, dtype="Int64")
        if choice == "null":
            s[draw(st.integers(0, n - 1))] = pd.NA
        return s
    if kind in ("x", "nx", "c", "t", "p"):
        if choice == "other":
            return pd.Series(draw(st.lists(st.sampled_from(["0.5", "x", "", "1e3", None]), min_size=n, max_size=n)),
                             dtype=object)
        s = pd.Series(draw(st.lists(st.floats(0.01, 1.0), min_size=n, max_size=n)), dtype="float64")
        if draw(st.integers(0, 3)) == 0:
            s[draw(st.integers(0, n - 1))] = draw(FLOATS)
        if choice == "null":
            s[draw(st.integers(0, n - 1))] = None
        return s
    if kind == "a":
        if choice == "other":
            return pd.Series(draw(st.lists(st.sampled_from(["N", "E", "0", None]), min_size=n, max_size=n)),
                             dtype=object)
        s = pd.Series(draw(st.lists(st.integers(0, 2), min_size=n, max_size=n)), dtype="Int64")
        if draw(st.integers(0, 3)) == 0:
            s[draw(st.integers(0, n - 1))] = draw(st.sampled_from([-1, 3, 4]))
        if choice == "null":
            s[draw(st.integers(0, n - 1))] = pd.NA
        return s
    # flags
    if choice == "other":
        return pd.Series(draw(st.lists(st.one_of(st.integers(-1, 2), st.just(None)), min_size=n, max_size=n)),
                         dtype="Float64")
    s = pd.Series(draw(st.lists(st.booleans(), min_size=n, max_size=n)), dtype="boolean")
    if choice == "null":
        s[draw(st.integers(0, n - 1))] = pd.NA
    return s


@st.composite
def table(draw):
    n = draw(st.integers(1, 12))
    df = pd.DataFrame({k: draw(column(k, n)) for k in ("ep", "k", "x", "nx", "a", "c", "done", "cut", "t", "p")})
    # mostly well-formed episodes: sort-of-contiguous steps, last row flagged
    if draw(st.booleans()):
        df["ep"] = pd.Series(np.repeat(["a", "b", "c"], n)[:n], dtype=object)
        df["k"] = pd.Series(np.concatenate([np.arange(n)] * 3)[:n], dtype="Int64")
    return df


def _write(df: pd.DataFrame, path, fmt: str) -> None:
    if fmt == "csv":
        df.to_csv(path, index=False)
    else:
        pq.write_table(pa.Table.from_pandas(df, preserve_index=False), path)


@SETTINGS
@given(df=table(), fmt=st.sampled_from(["parquet", "csv"]), on_error=st.sampled_from(["fail", "quarantine"]),
       kind=st.sampled_from(["transitions", "steps"]), use_time=st.booleans())
def test_fuzz_tables(tmp_path, df, fmt, on_error, kind, use_time):
    d = tmp_path / "f"
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir()
    src = d / f"in.{fmt}"
    _write(df, src, fmt)
    spec = {**BASE, "kind": kind}
    if not use_time:
        spec = {**spec, "episode": {"id": "ep", "step": "k"}}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = ingest_parquet([src], parse_parquet_spec(spec), d / "out", on_error=on_error)
    except OfflineADPError as exc:
        assert str(exc)
        return
    back = read_dataset(d / "out")
    rep = validate_directory(d / "out")
    assert rep.ok, rep.to_text()
    q = read_quarantine(d / "out")
    assert len(back) + (q.num_rows if q is not None else 0) + res.dropped_last_rows == len(df)


KEYS = {"kind": None, "format": None, "name": None, "on_error": None,
        "episode": ["id", "step", "step_base", "order", "time", "time_unit"],
        "observations": ["columns", "next_columns", "names", "units"],
        "action": ["column", "type", "values", "names", "edges", "n_bins", "bin_value", "dim", "unit", "vectors",
                   "dims"],
        "cost": ["column", "reward"], "end": ["terminated", "truncated"], "source": ["column", "value"],
        "propensity": ["column"], "hints": ["gamma", "horizon"], "csv": ["delimiter"], "bogus": ["x"]}
VALUES = st.one_of(st.none(), st.booleans(), st.integers(-(2**64), 2**64), FLOATS, st.text(max_size=4),
                   st.sampled_from(["transitions", "steps", "csv", "quarantine", "continuous", "mean", "s", ";", ";;",
                                    "x", "nx"]),
                   st.lists(st.one_of(st.integers(-2, 2), FLOATS, st.text(max_size=2)), max_size=4),
                   st.dictionaries(st.text(max_size=3), st.text(max_size=3), max_size=2))


@SETTINGS
@given(edits=st.lists(st.tuples(st.sampled_from(sorted(KEYS)), st.integers(0, 20), VALUES, st.booleans()), max_size=4))
def test_fuzz_spec_mappings(edits):
    import copy

    spec = copy.deepcopy(BASE)
    for top, i, value, delete in edits:
        sub = KEYS[top]
        if sub is None:
            if delete:
                spec.pop(top, None)
            else:
                spec[top] = value
            continue
        table = spec.setdefault(top, {}) if isinstance(spec.get(top, {}),
                                                       dict) else spec.__setitem__(top, {}) or spec[top]
        key = sub[i % len(sub)]
        if delete:
            table.pop(key, None)
        else:
            table[key] = value
    try:
        parse_parquet_spec(spec, where="fuzz.toml")
    except OfflineADPError as exc:
        assert str(exc).startswith("fuzz.toml")


SPEC_TEXT = (b'kind = "steps"\n[episode]\nid = "ep"\nstep = "k"\n[observations]\ncolumns = ["x"]\n'
             b'[action]\ncolumn = "a"\n[cost]\ncolumn = "c"\n[csv]\ndelimiter = ","\n')


@SETTINGS
@given(edits=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), min_size=1, max_size=6))
def test_fuzz_spec_bytes(tmp_path, edits):
    (tmp_path / "ok.toml").write_bytes(SPEC_TEXT)
    load_parquet_spec(tmp_path / "ok.toml")  # the unmutated spec is valid
    raw = bytearray(SPEC_TEXT)
    for pos, b in edits:
        raw[pos % len(raw)] = b
    p = tmp_path / "spec.toml"
    p.write_bytes(bytes(raw))
    try:
        load_parquet_spec(p)
    except OfflineADPError as exc:
        assert "spec.toml" in str(exc)


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    from offline_adp.simulate import simulate

    d = tmp_path_factory.mktemp("dsdir") / "ds"
    simulate("gridworld", 2, 2, seed=4, horizon=20).save(d, rows_per_part=30)
    return d


@SETTINGS
@given(pick=st.integers(0, 10**6), value=st.sampled_from([None, -1, 0, 1, "x", [], {}, True, 1e308, [["a"]],
                                                          {"name": 3}]),
       delete=st.booleans(), part_op=st.sampled_from(["none", "none", "drop", "text", "null"]), col=st.integers(0, 100))
def test_fuzz_dataset_directories(tmp_path, dataset_dir, pick, value, delete, part_op, col):
    """A damaged or hand-edited dataset directory (info.json entries, a part's column
    dropped, turned to text or to nulls) is read and doctored, or refused with our error."""
    import json

    d = tmp_path / "ds"
    shutil.rmtree(d, ignore_errors=True)
    shutil.copytree(dataset_dir, d)
    info = json.loads((d / "meta" / "info.json").read_text())
    paths = [p for p in json_paths(info, max_items=5) if p]
    path = paths[pick % len(paths)]
    edit_json_path(info, path, value, delete)
    (d / "meta" / "info.json").write_text(json.dumps(info))
    if part_op != "none":
        p = d / "data" / "part-00000.parquet"
        t = pq.read_table(p)
        name = t.column_names[col % t.num_columns]
        i = t.schema.get_field_index(name)
        if part_op == "drop":
            t = t.remove_column(i)
        elif part_op == "text":
            t = t.set_column(i, name, pa.array(["x"] * t.num_rows))
        else:
            t = t.set_column(i, name, pa.nulls(t.num_rows, t.schema.field(name).type))
        pq.write_table(t, p)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            validate_directory(d)
            read_dataset(d).arrays()
    except OfflineADPError:
        pass  # refused with one of our errors: fine


@pytest.mark.parametrize("delimiter", [";", "\t", "|"])
def test_spec_delimiters_that_are_accepted_work(tmp_path, delimiter):
    df = pd.DataFrame({"ep": ["a", "a"], "k": [0, 1], "x": [0.0, 1.0], "nx": [1.0, 2.0], "a": [0, 1], "c": [1.0, 2.0]})
    df.to_csv(tmp_path / "t.csv", sep=delimiter, index=False)
    spec = parse_parquet_spec({"episode": {"id": "ep", "step": "k"},
                               "observations": {"columns": ["x"], "next_columns": ["nx"]},
                               "action": {"column": "a"}, "cost": {"column": "c"}, "csv": {"delimiter": delimiter}})
    ds = ingest_parquet([tmp_path / "t.csv"], spec, tmp_path / "ds").dataset
    np.testing.assert_array_equal(ds.arrays().cost, [1.0, 2.0])
