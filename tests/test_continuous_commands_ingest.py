"""Issue 41, part 1: continuous commands kept as logged (Parquet columns or a list column,
MCAP fields): exact round trips, bounds, the doctor's command checks, the CLI."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from offline_adp.data.dataset import read_dataset
from offline_adp.data.io import read_quarantine
from offline_adp.errors import IngestError, SpecError, ValidationError
from offline_adp.ingest.parquet import ingest_parquet
from offline_adp.ingest.spec import parse_parquet_spec

N_EP, T = 4, 6


def _table(steer: np.ndarray | None = None, throttle: np.ndarray | None = None, *, cmd_list: list | None = None,
           fixed: bool = False) -> pa.Table:
    """A transition table of ``N_EP`` episodes of ``T`` steps (rows in episode/step order)
    with a two-component command in ``steer_cmd``/``throttle_cmd`` and in the list column ``cmd``."""
    n = N_EP * T
    rng = np.random.default_rng(7)
    steer = rng.uniform(-0.5, 0.5, n) if steer is None else steer
    throttle = rng.uniform(0.0, 1.0, n) if throttle is None else throttle
    x = np.arange(n, dtype=np.float64)
    step = np.tile(np.arange(T), N_EP)
    cols = {
        "ep": np.repeat([f"e{e}" for e in range(N_EP)], T),
        "k": step,
        "x": x,
        "x_next": x + 1.0,
        "steer_cmd": steer,
        "throttle_cmd": throttle,
        "c": 0.01 * x,
        "trunc": step == T - 1,
    }
    t = pa.table(cols)
    vals = cmd_list if cmd_list is not None else [[float(a), float(b)] for a, b in zip(steer, throttle, strict=True)]
    typ = pa.list_(pa.float64(), 2) if fixed else pa.list_(pa.float64())
    return t.append_column("cmd", pa.array(vals, typ))


def _spec(action: dict, **top) -> dict:
    return {"episode": {"id": "ep", "step": "k"}, "observations": {"columns": ["x"], "next_columns": ["x_next"]},
            "action": action, "cost": {"column": "c"}, "end": {"truncated": "trunc"}, **top}


def _ingest(tmp_path, table, action, **kw):
    path = tmp_path / "log.parquet"
    pq.write_table(table, path)
    spec = parse_parquet_spec(_spec(action), where="spec.toml")
    res = ingest_parquet([path], spec, tmp_path / "ds", **kw)
    return res, read_dataset(tmp_path / "ds"), path


def _expected(table: pa.Table) -> np.ndarray:
    return np.column_stack([table.column("steer_cmd").to_numpy(), table.column("throttle_cmd").to_numpy()])


# ------------------------------------------------------------------------------ Parquet
def test_two_columns_kept_exactly_with_logged_bounds(tmp_path):
    t = _table()
    res, back, _ = _ingest(tmp_path, t, {"columns": ["steer_cmd", "throttle_cmd"], "units": ["rad", "1"]})
    at = back.info.action_table
    assert at.kind == "continuous" and at.dims == ("steer_cmd", "throttle_cmd") and at.units == ("rad", "1")
    cmd = _expected(t)
    np.testing.assert_array_equal(back.commands(), cmd)  # bit for bit
    assert at.low == tuple(cmd.min(axis=0)) and at.high == tuple(cmd.max(axis=0))  # the logged range
    # the coarse action index stays valid for every discrete consumer
    a = back.arrays().action
    assert a.min() >= 0 and a.max() < back.n_actions and at.values.shape == (back.n_actions, 2)
    assert res.report.ok
    info = json.loads((tmp_path / "ds" / "meta" / "info.json").read_text())
    assert info["action_table"]["kind"] == "continuous" and info["action_table"]["low"] == list(cmd.min(axis=0))
    # the exact commands count in the fingerprint of a continuous dataset
    assert back.matches_fingerprint(info["fingerprint"])


@pytest.mark.parametrize("fixed", [False, True])
def test_list_column_kept_exactly_with_declared_bounds_and_names(tmp_path, fixed):
    t = _table(fixed=fixed)
    res, back, _ = _ingest(tmp_path, t, {"column": "cmd", "low": [-0.5, 0.0], "high": [0.5, 1.0]})
    at = back.info.action_table
    assert at.kind == "continuous" and at.dims == ("cmd.0", "cmd.1")
    assert at.low == (-0.5, 0.0) and at.high == (0.5, 1.0)
    np.testing.assert_array_equal(back.commands(), _expected(t))
    (tmp_path / "b").mkdir()
    _, back2, _ = _ingest(tmp_path / "b", t, {"column": "cmd", "type": "continuous", "names": ["steer", "throttle"]})
    assert back2.info.action_table.dims == ("steer", "throttle")
    assert back2.table.column_names.count("action_value.steer") == 1
    np.testing.assert_array_equal(back2.commands(), _expected(t))


def test_binned_vector_keeps_exact_commands_too(tmp_path):
    t = _table()
    _, back, _ = _ingest(tmp_path, t, {"columns": ["steer_cmd", "throttle_cmd"], "n_bins": 3, "names": ["s", "u"]})
    at = back.info.action_table
    assert at.kind == "binned" and at.dims == ("s", "u") and len(at) == 9
    np.testing.assert_array_equal(back.commands(), _expected(t))
    assert at.low == tuple(_expected(t).min(axis=0))  # bounds recorded (logged range)


def test_scalar_binned_spec_keeps_its_table_and_gains_the_exact_commands(tmp_path):
    """An existing single-column binned spec: the same action table (no bounds recorded,
    so the same fingerprint) plus an ``action_value.<dim>`` column."""
    t = _table()
    _, back, _ = _ingest(tmp_path, t, {"column": "steer_cmd", "type": "continuous", "edges": [-1.0, 0.0, 1.0],
                                       "dim": "s"})
    at = back.info.action_table
    assert at.kind == "binned" and at.low is None and at.high is None and at.bin_edges == (-1.0, 0.0, 1.0)
    np.testing.assert_array_equal(back.column("action_value.s"), t.column("steer_cmd").to_numpy())
    np.testing.assert_array_equal(back.arrays().action, (t.column("steer_cmd").to_numpy() >= 0).astype(int))


def test_scalar_continuous_defaults_to_the_column_name(tmp_path):
    t = _table()
    _, back, _ = _ingest(tmp_path, t, {"column": "throttle_cmd", "type": "continuous"})
    assert back.info.action_table.dims == ("throttle_cmd",) and back.info.action_table.kind == "continuous"
    np.testing.assert_array_equal(back.commands()[:, 0], t.column("throttle_cmd").to_numpy())


def _bad(kind: str) -> tuple[pa.Table, dict]:
    """A table with one bad command at row 8 (episode e1, step 2), and the action spec."""
    steer = np.random.default_rng(1).uniform(-0.5, 0.5, N_EP * T)
    if kind == "nan":
        steer[8] = np.nan
        return _table(steer), {"columns": ["steer_cmd", "throttle_cmd"]}
    if kind == "huge":  # beyond float32: the trees would read inf (a fit failed naming nothing)
        steer[8] = 1e200
        return _table(steer), {"columns": ["steer_cmd", "throttle_cmd"]}
    if kind == "bounds":
        steer[8] = 0.9
        return _table(steer), {"columns": ["steer_cmd", "throttle_cmd"], "low": [-0.5, 0.0], "high": [0.5, 1.0]}
    lists = [[float(a), 0.5] for a in steer]
    lists[8] = [0.1, 0.2, 0.3]
    return _table(steer, cmd_list=lists), {"column": "cmd"}


EXPECT = {"nan": ("non_finite", "action_value.steer_cmd"), "bounds": ("command_out_of_bounds",
                                                                      "action_value.steer_cmd"),
          "width": ("command_width", "cmd"), "huge": ("value_out_of_range", "action_value.steer_cmd")}


@pytest.mark.parametrize("kind", sorted(EXPECT))
def test_bad_commands_refused_naming_file_row_column(tmp_path, kind):
    t, action = _bad(kind)
    check, column = EXPECT[kind]
    with pytest.raises(ValidationError) as e:
        _ingest(tmp_path, t, action)
    msg = str(e.value)
    assert f"log.parquet: row 8 (episode e1, step 2) column {column!r}: [{check}]" in msg, msg
    f = e.value.report.findings
    assert list(f["check"]) == [check] and list(f["row"]) == [8] and list(f["column"]) == [column]


@pytest.mark.parametrize("kind", sorted(EXPECT))
def test_bad_commands_quarantined(tmp_path, kind):
    t, action = _bad(kind)
    check, column = EXPECT[kind]
    res, back, _ = _ingest(tmp_path, t, action, on_error="quarantine")
    assert res.quarantined_episodes == 1 and res.quarantined_rows == T
    assert "e1" not in set(back.episode_ids) and back.n_episodes == N_EP - 1
    q = read_quarantine(tmp_path / "ds")
    reasons = q.column("reason").to_pylist()
    assert any(r.startswith(f"[{check}] {column}:") for r in reasons), reasons
    assert q.column("src_row").to_pylist() == list(range(6, 12))
    assert np.isfinite(back.commands()).all()


@pytest.mark.parametrize(
    "action, match",
    [
        ({"columns": ["steer_cmd", "throttle_cmd"], "type": "discrete"}, r"action.columns: several columns"),
        ({"column": "cmd", "columns": ["steer_cmd"]}, r"either 'column'"),
        ({"columns": ["steer_cmd", "throttle_cmd"], "low": [0.0]}, r"action.low: 1 entries for a command of 2"),
        ({"columns": ["steer_cmd", "throttle_cmd"], "names": ["a"]}, r"action.names: 1 names for 2 columns"),
        ({"columns": ["steer_cmd", "throttle_cmd"], "low": [1.0, 0.0], "high": [0.0, 1.0]}, r"low .* exceeds high"),
        ({"columns": ["steer_cmd", "throttle_cmd"], "low": [float("nan"), 0.0]}, r"action.low"),
        ({"column": "steer_cmd", "type": "discrete", "low": -1.0}, r"action.low: only for continuous commands"),
        ({"columns": ["steer_cmd", "throttle_cmd"], "edges": [0.0, 1.0], "n_bins": 2}, r"at most one of 'edges'"),
        ({"columns": ["steer_cmd", "throttle_cmd"], "lows": [0.0]},
         r"action.lows: unknown key \(did you mean 'low'\?\)"),
    ],
)
def test_bad_action_specs_name_the_key(action, match):
    with pytest.raises(SpecError, match=match):
        parse_parquet_spec(_spec(action), where="spec.toml")


def test_list_column_of_text_or_declared_discrete_is_refused(tmp_path):
    t = _table()
    with pytest.raises(IngestError, match=r"column 'steer_cmd' holds one label per row: action.low/high/units"):
        _ingest(tmp_path, t, {"column": "steer_cmd", "low": -1.0})
    with pytest.raises(IngestError, match=r"column 'cmd' holds lists"):
        _ingest(tmp_path, t, {"column": "cmd", "type": "discrete"})
    t2 = t.set_column(t.column_names.index("cmd"), "cmd", pa.array([["a", "b"]] * t.num_rows))
    with pytest.raises(IngestError, match=r"column 'cmd': lists of string are not numeric commands"):
        _ingest(tmp_path, t2, {"column": "cmd"})


def test_round_trip_property():
    """Any finite commands (bounded) come back bit for bit, and inside the logged bounds."""
    import tempfile
    from pathlib import Path

    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st
    from hypothesis.extra.numpy import arrays

    floats = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False, allow_subnormal=True)

    @settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(arrays(np.float64, (N_EP * T, 2), elements=floats))
    def check(cmd):
        with tempfile.TemporaryDirectory() as d:
            t = _table(cmd[:, 0], cmd[:, 1])
            _, back, _ = _ingest(Path(d), t, {"column": "cmd"})
            np.testing.assert_array_equal(back.commands(), cmd + 0.0)
            lo, hi = back.info.action_table.bounds()
            assert (back.commands() >= lo).all() and (back.commands() <= hi).all()

    check()


# ------------------------------------------------------------------------------ CLI
def test_cli_bad_spec_key_exit_2_one_line(tmp_path, capsys):
    from offline_adp.cli import main

    pq.write_table(_table(), tmp_path / "log.parquet")
    spec = tmp_path / "spec.toml"
    spec.write_text('[episode]\nid = "ep"\nstep = "k"\n[observations]\ncolumns = ["x"]\nnext_columns = ["x_next"]\n'
                    '[action]\ncolumns = ["steer_cmd", "throttle_cmd"]\nlow = [-1.0, 0.0]\nhigh = [1.0, 1.0]\n'
                    'unitz = ["rad", "1"]\n[cost]\ncolumn = "c"\n[end]\ntruncated = "trunc"\n')
    assert main(["ingest", "parquet", str(tmp_path / "log.parquet"), "--spec", str(spec), "--out", str(tmp_path / "ds"),
                 "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "action" in err and "unitz" in err and str(spec) in err, err
    spec.write_text(spec.read_text().replace("unitz", "units"))
    assert main(["ingest", "parquet", str(tmp_path / "log.parquet"), "--spec", str(spec), "--out", str(tmp_path / "ds"),
                 "-q"]) == 0
    assert read_dataset(tmp_path / "ds").info.action_table.units == ("rad", "1")


# ------------------------------------------------------------------------------ MCAP
MS = 1_000_000


def _write_mcap(path, steer, throttle, gap_at=None):
    """A 10 Hz clock with the state, and a command message 7 ms after each tick; a 5 s gap
    (a new episode) before tick ``gap_at``."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        ch = {t: w.register_channel(topic=t, message_encoding="json", schema_id=sid) for t in ("/state", "/cmd")}
        for k in range(len(steer)):
            t0 = k * 100 * MS + (5000 * MS if gap_at is not None and k >= gap_at else 0)
            w.add_message(ch["/state"], log_time=t0, publish_time=t0, data=json.dumps({"x": k * 0.5}).encode())
            w.add_message(ch["/cmd"], log_time=t0 + 7 * MS, publish_time=t0 + 7 * MS,
                          data=json.dumps({"steer": float(steer[k]), "throttle": float(throttle[k])}).encode())
        w.finish()


def _mcap_spec(action: dict):
    from offline_adp.ingest.mcap import parse_mcap_spec

    return parse_mcap_spec({
        "clock": {"topic": "/state"}, "episodes": {"gap": 1.0},
        "streams": [{"topic": "/state", "fields": {"x": "x"}, "max_age": 0.001}],
        "action": {"topic": "/cmd", "align": "nearest", "max_age": 0.05, **action},
        "cost": {"terms": [{"field": "x", "op": "square"}]},
    })


def test_mcap_vector_command_kept_exactly(tmp_path):
    from offline_adp.ingest.mcap import ingest_mcap

    rng = np.random.default_rng(3)
    steer, throttle = rng.uniform(-0.4, 0.4, 12), rng.uniform(0, 1, 12)
    _write_mcap(tmp_path / "a.mcap", steer, throttle)
    spec = _mcap_spec({"fields": {"steer": "steer", "throttle": "throttle"}, "type": "continuous",
                       "low": [-0.5, 0.0], "high": [0.5, 1.0], "units": ["rad", "1"]})
    ds, summary = ingest_mcap([tmp_path / "a.mcap"], spec, tmp_path / "ds")
    at = ds.info.action_table
    assert at.kind == "continuous" and at.dims == ("steer",
                                                   "throttle") and at.low == (-0.5, 0.0) and at.units == ("rad", "1")
    n = len(ds)  # the last tick has no next state
    # JSON round-trips floats exactly
    np.testing.assert_array_equal(ds.commands(), np.column_stack([steer, throttle])[:n])
    np.testing.assert_array_equal(read_dataset(tmp_path / "ds").commands(), ds.commands())
    assert summary["doctor"]["ok"]
    # the single-field form: bounds from the logged range, component "a"
    ds1, _ = ingest_mcap([tmp_path / "a.mcap"], _mcap_spec({"field": "throttle", "type": "continuous"}))
    assert ds1.info.action_table.kind == "continuous" and ds1.info.action_table.dims == ("a",)
    np.testing.assert_array_equal(ds1.commands()[:, 0], throttle[:n])
    assert ds1.info.action_table.high == (float(throttle[:n].max()),)


def test_mcap_command_out_of_declared_bounds_refused_or_quarantined(tmp_path):
    from offline_adp.ingest.mcap import ingest_mcap

    steer, throttle = np.linspace(-0.3, 0.3, 24), np.full(24, 0.5)
    steer[4] = 2.0
    _write_mcap(tmp_path / "a.mcap", steer, throttle, gap_at=12)
    spec = _mcap_spec({"fields": {"steer": "steer", "throttle": "throttle"}, "type": "continuous",
                       "low": -1.0, "high": 1.0})
    with pytest.raises(ValidationError,
                       match=r"a.mcap: log_time 4\d+ .* column 'action_value.steer': \[command_out_of_bounds\]"):
        ingest_mcap([tmp_path / "a.mcap"], spec)
    ds, summary = ingest_mcap([tmp_path / "a.mcap"], spec, tmp_path / "ds", on_error="quarantine")
    # the first episode (its last tick has no next state)
    assert ds.n_episodes == 1 and summary["quarantined_rows"] == 11
    np.testing.assert_array_equal(ds.commands(), np.column_stack([steer, throttle])[12:23])
    q = read_quarantine(tmp_path / "ds")
    assert any(r.startswith("[command_out_of_bounds] action_value.steer:") for r in q.column("reason").to_pylist())


def test_mcap_binned_specs_unchanged(tmp_path):
    """edges/n_bins: binned as before (no bounds recorded), the exact commands kept too."""
    from offline_adp.ingest.mcap import ingest_mcap

    steer, throttle = np.linspace(-0.3, 0.3, 12), np.linspace(0, 1, 12)
    _write_mcap(tmp_path / "a.mcap", steer, throttle)
    ds, _ = ingest_mcap([tmp_path / "a.mcap"], _mcap_spec({"fields": {"steer": "steer", "throttle": "throttle"},
                                                           "type": "continuous", "n_bins": 2}))
    at = ds.info.action_table
    assert at.kind == "binned" and len(at) == 4 and at.low is None
    np.testing.assert_array_equal(ds.commands(), np.column_stack([steer, throttle])[:len(ds)])
    with pytest.raises(SpecError, match=r"action.names: the components of a command kept as logged"):
        _mcap_spec({"fields": {"steer": "steer", "throttle": "throttle"}, "type": "continuous", "names": ["a", "b"]})
    with pytest.raises(SpecError, match=r"action.low: 3 entries for the 2 components"):
        _mcap_spec({"fields": {"steer": "steer", "throttle": "throttle"}, "type": "continuous", "low": [0, 0, 0]})


def test_struct_command_column_refused_naming_the_column(tmp_path):
    t = _table()
    s = pa.StructArray.from_arrays([t.column("steer_cmd").combine_chunks(), t.column("throttle_cmd").combine_chunks()],
                                   names=["steer", "throttle"])
    t = t.append_column("cmds", s)  # it became 24 discrete "actions" named after each row's dict
    with pytest.raises(IngestError, match=r"log.parquet: column 'cmds' is a struct .*action.columns"):
        _ingest(tmp_path, t, {"column": "cmds"})


def _float_labels(tmp_path, n_ep: int, declared: bool):
    T_ = 10
    n = n_ep * T_
    step = np.tile(np.arange(T_), n_ep)
    x = np.arange(n, dtype=np.float64)
    t = pa.table({"ep": np.repeat([f"e{e}" for e in range(n_ep)], T_), "k": step, "x": x, "x_next": x + 1.0,
                  "u": np.random.default_rng(3).uniform(-1, 1, n), "c": 0.01 * x, "trunc": step == T_ - 1})
    return _ingest(tmp_path, t, {"column": "u", **({"type": "discrete"} if declared else {})})


def test_a_float_column_read_as_one_label_per_row_is_warned_about(tmp_path):
    with pytest.warns(UserWarning, match=r"'u' was read as discrete labels .* 200 distinct values in 200 rows.*"
                                         r"action.type = 'continuous'"):
        _, back, _ = _float_labels(tmp_path, 20, declared=False)
    assert back.n_actions == 200  # nothing dropped: the documented default, now said out loud
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for sub, n_ep, declared in (("d", 20, True), ("s", 5, False)):  # declared; 50 labels: few enough
            (tmp_path / sub).mkdir()
            _float_labels(tmp_path / sub, n_ep, declared=declared)


def test_a_continuous_run_reads_another_recording_of_the_same_commands(tmp_path):
    """Without declared low/high each log's bounds are its own min/max: a held-out recording of
    the same robot was refused ("evaluate on logs of the same commands")."""
    from offline_adp.errors import IncompatibleError
    from offline_adp.evaluation.run_checks import _check_same_commands

    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "c").mkdir()
    action = {"columns": ["steer_cmd", "throttle_cmd"], "units": ["rad", "1"]}
    _, a, _ = _ingest(tmp_path / "a", _table(), action)
    other = np.random.default_rng(11).uniform(-0.4, 0.45, N_EP * T)
    _, b, _ = _ingest(tmp_path / "b", _table(steer=other), action)
    assert a.info.action_table.low != b.info.action_table.low  # each log's own range
    info = {"dataset": str(tmp_path / "a" / "ds")}
    _check_same_commands(tmp_path / "run", info, b, tmp_path / "b" / "ds")  # accepted
    _, c, _ = _ingest(tmp_path / "c", _table(), {"columns": ["steer_cmd", "throttle_cmd"], "names": ["s", "t"]})
    with pytest.raises(IncompatibleError, match="logs of the same commands"):
        _check_same_commands(tmp_path / "run", info, c, tmp_path / "c" / "ds")


@pytest.mark.parametrize("kind", ["bool", "bigint", "bigint_list"])
def test_commands_a_float64_cannot_keep_are_refused_naming_them(tmp_path, kind):
    t = _table()
    n = t.num_rows
    if kind == "bool":
        t = t.set_column(t.schema.get_field_index("steer_cmd"), "steer_cmd", pa.array(np.arange(n) % 2 == 0))
        action, match = {"columns": ["steer_cmd", "throttle_cmd"]}, r"column 'steer_cmd' holds booleans"
    elif kind == "bigint":
        v = np.arange(n, dtype=np.int64)
        v[9] = 2**53 + 1  # the first integer a float64 rounds (to 2**53)
        t = t.set_column(t.schema.get_field_index("steer_cmd"), "steer_cmd", pa.array(v))
        action, match = {"columns": ["steer_cmd", "throttle_cmd"]}, r"log.parquet: row 9 column 'steer_cmd'.*2\^53"
    else:
        lists = [[i, 1] for i in range(n)]
        lists[7] = [2**62 + 1, 1]
        t = t.set_column(t.schema.get_field_index("cmd"), "cmd", pa.array(lists, pa.list_(pa.int64())))
        action, match = {"column": "cmd"}, r"log.parquet: row 7 column 'cmd'.*2\^53"
    with pytest.raises(IngestError, match=match):
        _ingest(tmp_path, t, action)


@pytest.mark.parametrize("action", [{"column": "cmdj"}, {"column": "cmdj", "names": ["steer", "throttle"]},
                                    {"column": "cmdj", "type": "continuous"}])
def test_json_command_strings_are_refused_naming_file_and_column(tmp_path, action):
    """They became one discrete label per row, or 'action.names has 2 entries for 24 actions'."""
    t = _table()
    t = t.append_column("cmdj", pa.array([json.dumps(v) for v in t.column("cmd").to_pylist()]))
    path = tmp_path / "log.csv"
    import pyarrow.csv as pacsv

    pacsv.write_csv(t.drop_columns(["cmd"]), path)
    with pytest.raises(IngestError, match=r"log.csv: row 0: column 'cmdj' holds JSON text .*JSON commands are not "
                                          r"supported.*separate numeric columns.*list column"):
        ingest_parquet([path], parse_parquet_spec(_spec(action)), tmp_path / "ds")


def test_one_label_per_row_is_warned_about_even_when_declared(tmp_path):
    from offline_adp.errors import LogWarning

    n = 300
    t = pa.table({"ep": ["e"] * n, "k": np.arange(n), "x": np.arange(n, dtype=float), "x_next": np.arange(n) + 1.0,
                  "u": [f"cmd{i}" for i in range(n)], "c": np.zeros(n), "trunc": np.arange(n) == n - 1})
    with pytest.warns(LogWarning, match=r"'u' .* 300 distinct labels in 300 rows .*continuous command"):
        _ingest(tmp_path, t, {"column": "u", "type": "discrete"})


def test_more_names_than_list_entries_is_a_command_width_error(tmp_path):
    """It said "component 'brake': no finite command to infer its bounds from"."""
    with pytest.raises(IngestError, match=r"log.parquet: row 0: column 'cmd': \[command_width\] lists of 2 values "
                                          r"against 3 names \['steer', 'throttle', 'brake'\]"):
        _ingest(tmp_path, _table(), {"column": "cmd", "names": ["steer", "throttle", "brake"]})


def test_mcap_output_over_its_input_or_inside_a_dataset_is_refused(tmp_path):
    """The rule of the Parquet ingest (data.io.check_dataset_output), before anything is written."""
    from offline_adp.errors import OutputExistsError
    from offline_adp.ingest.mcap import ingest_mcap

    (tmp_path / "logs").mkdir()
    _write_mcap(tmp_path / "logs" / "a.mcap", np.linspace(-0.3, 0.3, 12), np.full(12, 0.5))
    spec = _mcap_spec({"fields": {"steer": "steer", "throttle": "throttle"}, "type": "continuous"})
    for out in (tmp_path / "logs" / "a.mcap", tmp_path / "logs"):
        with pytest.raises(OutputExistsError, match=r"the output .* (is|contains) the input"):
            ingest_mcap([tmp_path / "logs" / "a.mcap"], spec, out, overwrite=True)
    assert sorted(p.name for p in (tmp_path / "logs").iterdir()) == ["a.mcap"]
    ingest_mcap([tmp_path / "logs" / "a.mcap"], spec, tmp_path / "ds")
    with pytest.raises(OutputExistsError, match=r"inside the dataset directory"):
        ingest_mcap([tmp_path / "logs" / "a.mcap"], spec, tmp_path / "ds" / "meta", overwrite=True)
    assert (tmp_path / "ds" / "meta" / "info.json").is_file()
