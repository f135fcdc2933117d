"""A corrupt, truncated or wrong-shaped file in a real run directory (``run.json``,
``evaluation/metrics.json``, ``evaluation/ratios.parquet``, ``model/history.csv``) makes
the command that reads it exit 2 with one line on stderr naming the file, never a raw
traceback."""

from __future__ import annotations

import shutil

import pytest

from offline_adp.data.files import read_json_file, read_table_file
from offline_adp.data.rundir import RunDirectory
from offline_adp.errors import ArtifactError
from tests.fuzz_util import gridworld_runs, one_line_error


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    """A small gridworld log, two quick FQI fits, the first evaluated from the logs."""
    root = gridworld_runs(tmp_path_factory.mktemp("corrupt"), extra=("--fqe-bootstrap", "0"))
    assert (root / "a" / "evaluation" / "ratios.parquet").is_file()
    return root


def _copy(root, tmp_path):
    for name in ("a", "b"):
        shutil.copytree(root / name, tmp_path / name)
    return tmp_path / "a", tmp_path / "b"


def _truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _one_line_error(capsys, argv, filename):
    return one_line_error(capsys, argv, filename)


@pytest.mark.parametrize("damage", ["truncate", "garbage", "list"])
def test_evaluate_with_a_corrupt_run_json_exits_2(evaluated, tmp_path, capsys, damage):
    a, _ = _copy(evaluated, tmp_path)
    p = a / "run.json"
    if damage == "truncate":
        _truncate(p)
    elif damage == "garbage":
        p.write_bytes(b"\xff\xfe\x00garbage")
    else:
        p.write_text("[1, 2]")
    _one_line_error(capsys, ["evaluate", str(a), "--simulator", "none", "--quiet"], "run.json")


@pytest.mark.parametrize("name", ["metrics.json", "ratios.parquet"])
def test_report_with_a_corrupt_evaluation_file_exits_2(evaluated, tmp_path, capsys, name):
    a, _ = _copy(evaluated, tmp_path)
    _truncate(a / "evaluation" / name)
    line = _one_line_error(capsys, ["report", str(a)], f"evaluation/{name}")
    assert "corrupt" in line
    assert not (a / "report").exists()


def test_report_with_a_corrupt_history_or_run_json_exits_2(evaluated, tmp_path, capsys):
    a, _ = _copy(evaluated, tmp_path)
    (a / "model" / "history.csv").write_bytes(b'iteration,sup_dq\n1,"unterminated\n')
    _one_line_error(capsys, ["report", str(a)], "history.csv")
    shutil.rmtree(tmp_path / "a")
    a, _ = _copy(evaluated, tmp_path / "again")
    _truncate(a / "run.json")
    _one_line_error(capsys, ["report", str(a)], "run.json")


@pytest.mark.parametrize("name", ["evaluation/metrics.json", "run.json"])
def test_compare_with_a_corrupt_file_exits_2(evaluated, tmp_path, capsys, name):
    a, b = _copy(evaluated, tmp_path)
    _truncate(a / name)
    _one_line_error(capsys, ["compare", str(a), str(b), "--simulator", "none", "--quiet"], name)


def test_readers_name_the_file(tmp_path):
    p = tmp_path / "x.json"
    with pytest.raises(ArtifactError, match="x.json: missing"):
        read_json_file(p)
    p.write_text('{"a": 1')
    with pytest.raises(ArtifactError, match="x.json: not valid JSON"):
        read_json_file(p)
    p.write_text('{"a": 1}')
    assert read_json_file(p) == {"a": 1}
    q = tmp_path / "t.parquet"
    q.write_bytes(b"PAR1 not really")
    with pytest.raises(ArtifactError, match="t.parquet: not a readable Parquet table"):
        read_table_file(q)
    rd = RunDirectory(tmp_path / "run")
    with pytest.raises(ArtifactError, match="run.json: missing"):
        rd.read_json(rd.STATUS)


def _damage_history(hist, damage):
    """Rewrite a checkpoint's history.csv as ``damage`` says; the message the reader gives."""
    import pandas as pd

    if damage == "unparsable":
        hist.write_bytes(b'iteration,sup_dq\n1,"unterminated\n')
        return "checkpoint/history.csv: not a readable CSV table"
    h = pd.read_csv(hist)
    if damage == "text in a number column":
        h["bellman_residual"] = h["bellman_residual"].astype(object)
        h.loc[1, "bellman_residual"] = "oops"
        msg = "checkpoint/history.csv: column 'bellman_residual' must hold numbers, found 'oops' (row 2)"
    elif damage == "missing column":
        h = h.drop(columns=["sup_dq"])
        msg = "checkpoint/history.csv: no column ['sup_dq']"
    elif damage == "text in the structure record":  # a column resume parses (the frozen mode's builds)
        h["structure"] = h["structure"].astype(object)
        h.loc[2, "structure"] = "abc"
        msg = "checkpoint/history.csv: column 'structure' must hold numbers, found 'abc' (row 3)"
    elif damage == "no number where the verdict reads one":
        h.loc[2, "sup_dq"] = float("nan")
        msg = "checkpoint/history.csv: column 'sup_dq' must hold finite numbers"
    elif damage == "a build count that is not one":
        h["structure"] = h["structure"].astype(float)
        h.loc[2, "structure"] = 0.5
        msg = "checkpoint/history.csv: column 'structure' must count builds 1, 2, ..."
    elif damage == "iterations out of order":
        h["iteration"] = h["iteration"][::-1].to_numpy()
        msg = "checkpoint/history.csv: column 'iteration' must count 1, 2, ..., 3"
    else:  # a row fewer than the Q-function's iterations
        h = h.iloc[:-1]
        msg = "checkpoint/history.csv: 2 history rows, but"
    h.to_csv(hist, index=False)
    return msg


@pytest.mark.parametrize("damage", ["unparsable", "text in a number column", "missing column",
                                    "iterations out of order",
                                    "rows not the checkpoint's", "text in the structure record",
                                    "no number where the verdict reads one", "a build count that is not one"])
def test_resume_with_a_corrupt_checkpoint_history_exits_2(tmp_path, capsys, damage):
    """The checkpoint codec (one for local and Dask fits) reads history.csv with checks:
    whatever is wrong with it, ``--resume`` is one line naming the file, exit 2."""
    from offline_adp.runs import fit_run
    from offline_adp.simulate import simulate

    simulate("gridworld", 3, 3, seed=3, horizon=30).save(tmp_path / "ds")
    params = {"n_iterations": 3, "regressor_params": {"n_estimators": 5}}
    fit_run(tmp_path / "ds", tmp_path / "run", params=params)
    shutil.rmtree(tmp_path / "run" / "model")  # killed after the last checkpoint (iteration 3), before model/
    hist = tmp_path / "run" / "checkpoint" / "history.csv"
    assert hist.is_file()
    msg = _damage_history(hist, damage)
    line = _one_line_error(capsys, ["fit", str(tmp_path / "ds"), "--out", str(tmp_path / "run"), "--resume", "--quiet"],
                           "checkpoint/history.csv")
    assert msg in line, line


def test_export_with_a_corrupt_run_json_exits_2(evaluated, tmp_path, capsys):
    a, _ = _copy(evaluated, tmp_path)
    _truncate(a / "run.json")
    _one_line_error(capsys, ["export", str(a), "--out", str(tmp_path / "p.onnx")], "run.json")
    assert not (tmp_path / "p.onnx").exists()


def test_features_reordered_in_the_fitted_datasets_own_info_are_refused(tmp_path, capsys):
    """run.json records the features the fit read; reordering them in the fitted dataset's own
    info.json afterwards gave wrong numbers from evaluate (the check compared the run's dataset
    with itself). Now exit 2 naming run.json's features and the dataset's."""
    import json

    from offline_adp.cli import main
    from offline_adp.simulate import simulate

    simulate("car_on_hill", 0, 20, seed=0, horizon=30).save(tmp_path / "ds")
    (tmp_path / "c.toml").write_text("[fqi]\nn_iterations = 2\n[fqi.regressor_params]\nn_estimators = 3\n")
    assert main(["fit", str(tmp_path / "ds"), "--config", str(tmp_path / "c.toml"), "--out", str(tmp_path / "r"),
                 "-q"]) == 0
    assert json.loads((tmp_path / "r" / "run.json").read_text())["features"] == ["p", "s"]
    info_path = tmp_path / "ds" / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info["features"] = info["features"][::-1]
    info_path.write_text(json.dumps(info))
    line = _one_line_error(capsys, ["evaluate", str(tmp_path / "r"), "--simulator", "none", "--bootstrap", "0",
                                    "--fqe-bootstrap", "0", "--model-particles", "0"], "run.json")
    assert "['p', 's']" in line and "['s', 'p']" in line
