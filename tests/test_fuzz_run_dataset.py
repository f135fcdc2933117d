"""Hostile values in a run's ``run.json`` and ``model/history.csv``, a dataset's
``meta/info.json`` and parts, and a model's ``params.json``: each case below escaped as a
raw TypeError, ValueError, OverflowError, IndexError or JSONDecodeError (found by a fuzz of
real files: one edit at a time, every reader run) before its reader checked it. Now each is
one of our errors naming the file and the key, column or row; on the CLI one line, exit 2.

Counts: CI runs ``N`` random history edits; ``pytest --hypothesis-profile nightly`` runs more.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from offline_adp.errors import ArtifactError, OfflineADPError
from tests.fuzz_util import gridworld_runs, one_line_error

NIGHTLY = settings().max_examples >= 1000
N = 1000 if NIGHTLY else 25


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A small gridworld log and two quick FQI fits, the first evaluated from the logs."""
    return gridworld_runs(tmp_path_factory.mktemp("runds"), extra=("--fqe-bootstrap", "0", "--model-particles", "0"))


def _copy(root, tmp_path):
    """Copies of the dataset and both runs under ``tmp_path``, the runs naming the copy."""
    shutil.copytree(root / "ds", tmp_path / "ds")
    for name in ("a", "b"):
        shutil.copytree(root / name, tmp_path / name)
        p = tmp_path / name / "run.json"
        p.write_text(json.dumps({**json.loads(p.read_text()), "dataset": str(tmp_path / "ds")}))
    m = tmp_path / "a" / "evaluation" / "metrics.json"
    doc = json.loads(m.read_text())
    doc["dataset"]["path"] = str(tmp_path / "ds")
    m.write_text(json.dumps(doc))
    return tmp_path / "a", tmp_path / "b", tmp_path / "ds"


def _one_line_error(capsys, argv, *names):
    return one_line_error(capsys, argv, *names)


def _edit_json(path, **changes):
    doc = json.loads(path.read_text())
    doc.update(changes)
    path.write_text(json.dumps(doc))


# ----------------------------------------------------------------------------- run.json 'dataset'
#: run.json 'dataset' values that are not a path: Path() raised TypeError in evaluate,
#: compare, export and load_policy
NOT_A_PATH = {"null": None, "int": 5, "list": ["ds"], "object": {"path": "ds"}, "true": True, "float": 1.5}


@pytest.mark.parametrize("value", sorted(NOT_A_PATH))
@pytest.mark.parametrize("command", ["evaluate", "compare", "export"])
def test_run_json_dataset_of_the_wrong_type_exits_2(fitted, tmp_path, capsys, command, value):
    a, b, _ = _copy(fitted, tmp_path)
    _edit_json(a / "run.json", dataset=NOT_A_PATH[value])
    argv = {"evaluate": ["evaluate", str(a), "--simulator", "none", "--bootstrap", "5", "--fqe-bootstrap", "0",
                         "--model-particles", "0", "--quiet"],
            "compare": ["compare", str(a), str(b), "--simulator", "none", "--quiet"],
            "export": ["export", str(a), "--out", str(tmp_path / "p.onnx")]}[command]
    line = _one_line_error(capsys, argv)
    if value != "null":  # null: the run names no dataset (an error saying so and what to pass)
        assert "run.json" in line and "'dataset'" in line, line
    assert "--dataset" in line, line


@pytest.mark.parametrize("value", sorted(NOT_A_PATH))
def test_load_policy_with_a_run_json_dataset_of_the_wrong_type_is_our_error(fitted, tmp_path, value):
    import offline_adp

    a, _, _ = _copy(fitted, tmp_path)
    _edit_json(a / "run.json", dataset=NOT_A_PATH[value])
    with pytest.raises(OfflineADPError, match="run.json: 'dataset'" if value != "null" else "dataset"):
        offline_adp.load_policy(a)


def test_evaluate_of_a_run_naming_no_dataset_does_not_read_the_current_directory(fitted, tmp_path, capsys,
                                                                                  monkeypatch):
    """No 'dataset' key was Path(""): the current directory, a dataset when run from one."""
    a, _, ds = _copy(fitted, tmp_path)
    rj = json.loads((a / "run.json").read_text())
    del rj["dataset"]
    (a / "run.json").write_text(json.dumps(rj))
    monkeypatch.chdir(ds)
    _one_line_error(capsys, ["evaluate", str(a), "--simulator", "none", "--quiet"], "names no dataset", "--dataset")


# ----------------------------------------------------------------------------- model/history.csv
def _history_only(a):
    """The run without its stored fit verdict, so that the summary reads model/history.csv."""
    rj = json.loads((a / "run.json").read_text())
    for k in ("verdict", "verdict_message", "diverged"):
        rj.pop(k, None)
    (a / "run.json").write_text(json.dumps(rj))
    return a / "model" / "history.csv"


def _set_cell(hist, column, row, value):
    h = pd.read_csv(hist)
    h[column] = h[column].astype(object)
    h.loc[row, column] = value
    h.to_csv(hist, index=False)


HISTORY_DAMAGE = {  # (column, row, value): float() and int() of these raised ValueError or OverflowError
    "text in sup_dq": ("sup_dq", 2, "oops"),
    "text in iteration": ("iteration", 2, "x"),
    "NaN iteration": ("iteration", 2, float("nan")),
    "infinite iteration": ("iteration", 2, float("inf")),
    "fractional iteration": ("iteration", 1, 1.5),
    "negative sup_dq": ("sup_dq", 2, -3.0),  # read as converged at any tol before
    "text in step": ("step", 0, "later"),
}


@pytest.mark.parametrize("case", sorted(HISTORY_DAMAGE))
def test_report_with_a_damaged_history_names_column_and_row(fitted, tmp_path, capsys, case):
    a, _, _ = _copy(fitted, tmp_path)
    hist = _history_only(a)
    column, row, value = HISTORY_DAMAGE[case]
    _set_cell(hist, column, row, value)
    _one_line_error(capsys, ["report", str(a)], "model/history.csv", f"column {column!r}", f"(row {row + 1})")


def test_a_history_larger_than_any_fit_writes_is_refused_unread(fitted, tmp_path, capsys, monkeypatch):
    import offline_adp.algorithms.checkpoint as ck

    a, _, _ = _copy(fitted, tmp_path)
    hist = _history_only(a)
    monkeypatch.setattr(ck, "MAX_HISTORY_BYTES", hist.stat().st_size - 1)
    _one_line_error(capsys, ["report", str(a)], "model/history.csv", "bytes")


HOSTILE_CELLS = st.one_of(st.sampled_from(["x", "nan", "inf", "-inf", "1e400", "-1", "0", "0.5", "True", "1,5", '"',
                                           "9" * 40, "", float("nan"), float("inf"), -(2**70)]),
                          st.floats(allow_nan=True, allow_infinity=True))


@settings(max_examples=N, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(column=st.sampled_from(["iteration", "sup_dq", "step"]), row=st.sampled_from([2, 2, 1, 0]), value=HOSTILE_CELLS,
       drop_rows=st.sampled_from([0, 0, 0, 1, 3]))
def test_fuzz_history_cells_give_a_summary_or_our_error(fitted, tmp_path_factory, column, row, value, drop_rows):
    from offline_adp.evaluation.summary import fit_convergence

    a, _, _ = _copy(fitted, tmp_path_factory.mktemp("h"))
    hist = _history_only(a)
    _set_cell(hist, column, row, value)
    h = pd.read_csv(hist, dtype=str, keep_default_na=False)
    h.iloc[:len(h) - drop_rows].to_csv(hist, index=False)
    try:
        out = fit_convergence(a)
    except ArtifactError as exc:
        assert "history.csv" in str(exc)
        return
    assert isinstance(out["text"], str) and out["verdict"]


# ----------------------------------------------------------------------------- meta/info.json
INFO_DAMAGE = {  # info.json edits that reached a TypeError (dims) or int(NaN) (horizon) in a reader
    "dims of numbers": (("action_table", "dims"), [5], "dims"),
    "units of numbers": (("action_table", "units"), [1.5], "units"),
    "NaN horizon": (("horizon",), float("nan"), "horizon"),
    "fractional horizon": (("horizon",), 2.5, "horizon"),
    "boolean gamma": (("gamma",), True, "gamma"),
}


@pytest.mark.parametrize("case", sorted(INFO_DAMAGE))
@pytest.mark.parametrize("command", ["validate", "evaluate"])
def test_info_json_values_of_the_wrong_kind_exit_2(fitted, tmp_path, capsys, command, case):
    a, _, ds = _copy(fitted, tmp_path)
    path, value, key = INFO_DAMAGE[case]
    p = ds / "meta" / "info.json"
    doc = json.loads(p.read_text())
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    parent[path[-1]] = value
    p.write_text(json.dumps(doc))
    argv = ["validate", str(ds)] if command == "validate" else [
        "evaluate", str(a), "--simulator", "none", "--bootstrap", "5", "--fqe-bootstrap", "0", "--model-particles",
        "0", "--quiet"]
    _one_line_error(capsys, argv, "meta/info.json", key)


# ----------------------------------------------------------------------------- parts failing the doctor
def _edit_part(ds, column, fn):
    part = sorted((ds / "data").glob("part-*.parquet"))[0]
    t = pq.read_table(part)
    i = t.column_names.index(column)
    pq.write_table(t.set_column(i, column, fn(t)), part)


PART_DAMAGE = {  # evaluate ran no doctor: IndexError in the behaviour model, the OPE tables, max() of nothing
    "action beyond the table": ("action", lambda t: pa.array(t.column("action").to_numpy() + 100, pa.int32()),
                                "action_out_of_range"),
    "negative action": ("action", lambda t: pa.array(t.column("action").to_numpy() - 100, pa.int32()),
                        "action_out_of_range"),
    "negative steps": ("step", lambda t: pa.array(t.column("step").to_numpy() - 1000, pa.int32()), "step"),
    "no rows": (None, None, "no transitions"),
}


@pytest.mark.parametrize("case", sorted(PART_DAMAGE))
def test_evaluate_on_data_failing_the_doctor_exits_2(fitted, tmp_path, capsys, case):
    a, _, ds = _copy(fitted, tmp_path)
    column, fn, words = PART_DAMAGE[case]
    if column is None:
        part = sorted((ds / "data").glob("part-*.parquet"))[0]
        pq.write_table(pq.read_table(part).slice(0, 0), part)
    else:
        _edit_part(ds, column, fn)
    line = _one_line_error(capsys, ["evaluate", str(a), "--simulator", "none", "--bootstrap", "5",
                                    "--fqe-bootstrap", "0", "--model-particles", "0", "--quiet"], str(ds), words)
    if column is not None:
        assert "part-00000.parquet" in line and f"column {column!r}" in line, line
    assert not (a / "evaluation" / "metrics.json").read_text().count("part-00000")  # the old evaluation kept


# ----------------------------------------------------------------------------- model/params.json
@pytest.mark.parametrize("damage", ["missing", "truncated", "a list"])
def test_load_fqi_with_a_damaged_params_json_is_an_artifact_error(fitted, tmp_path, damage):
    from offline_adp.algorithms.fqi import load_fqi

    a, _, _ = _copy(fitted, tmp_path)
    p = a / "model" / "params.json"
    if damage == "missing":
        p.unlink()
    elif damage == "truncated":
        p.write_text(p.read_text()[:10])
    else:
        p.write_text("[1, 2]")
    with pytest.raises(ArtifactError, match="params.json"):
        load_fqi(a / "model")
    assert np.isfinite(load_fqi(fitted / "a" / "model").gamma_)  # the undamaged one loads


def test_a_part_with_a_column_of_another_type_is_named(tmp_path, capsys):
    """The concatenation's error named the dataset only: now the part, the column and both types."""
    from offline_adp.simulate import simulate

    simulate("gridworld", 4, 4, seed=3, horizon=30).save(tmp_path / "ds", rows_per_part=40)
    parts = sorted((tmp_path / "ds" / "data").glob("part-*.parquet"))
    assert len(parts) >= 2
    t = pq.read_table(parts[1])
    i = t.column_names.index("action")
    pq.write_table(t.set_column(i, "action", pa.array(t.column("action").to_numpy().astype(str))), parts[1])
    _one_line_error(capsys, ["validate", str(tmp_path / "ds")], parts[1].name, "column 'action' is string",
                    f"in {parts[0].name} int32")
