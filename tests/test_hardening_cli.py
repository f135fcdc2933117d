"""Issue 16 item 6 (cases not about configuration files): each former raw traceback is
exit 2 with one line on stderr naming the argument, file, row or column at fault."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from offline_adp.cli import main
from offline_adp.data.dataset import TransitionDataset
from offline_adp.simulate import simulate


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _one_error_line(err: str) -> str:
    lines = [x for x in err.strip().splitlines() if "error:" in x]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--problem-options", "{bad"], "--problem-options: not valid JSON"),
        (["--problem-options", "[1, 2]"], "--problem-options: expected a JSON object"),
        (["--problem-options", '{"size": -5}'], "rejected"),
        (["--demonstrations", "-3"], "n_demonstrations must be an integer in [0,"),
        (["--exploration", "-1"], "n_exploration must be an integer in [0,"),
        (["--horizon", "-1"], "horizon must be an integer in [1,"),
        (["--demonstrations", "0", "--exploration", "0"], "at least one demonstration or exploration episode"),
    ],
)
def test_simulate_bad_arguments_exit_2(tmp_path, capsys, argv, match):
    problem = "tabular" if "size" in " ".join(argv) else "gridworld"
    argv = [a.replace("size", "n_states") for a in argv]
    code, _, err = _run(capsys, "simulate", problem, "--out", str(tmp_path / "d"), "-q", *argv)
    assert code == 2
    assert match in _one_error_line(err)
    assert not (tmp_path / "d").exists()


@pytest.fixture(scope="module")
def grid():
    return simulate("gridworld", 2, 2, seed=1, horizon=30)


def _with(ds: TransitionDataset, column: str, values: np.ndarray) -> TransitionDataset:
    t = ds.table
    return TransitionDataset(t.set_column(t.schema.get_field_index(column), column,
                                          pa.array(values, t.schema.field(column).type)), ds.info)


def test_fit_on_an_empty_dataset_exits_2(tmp_path, capsys, grid):
    TransitionDataset(grid.table.slice(0, 0), grid.info).save(tmp_path / "empty")
    code, _, err = _run(capsys, "fit", str(tmp_path / "empty"), "--out", str(tmp_path / "run"), "--algorithm", "fqi")
    assert code == 2 and "no transitions" in _one_error_line(err)


@pytest.mark.parametrize("algorithm", ["fqi", "api"])
def test_fit_on_huge_values_exits_2_naming_file_row_column(tmp_path, capsys, grid, algorithm):
    c = grid.table.column("cost").to_numpy().copy()
    c[5] = 1e308
    _with(grid, "cost", c).save(tmp_path / "big")
    code, _, err = _run(capsys, "fit", str(tmp_path / "big"), "--out", str(tmp_path / "run"), "--algorithm", algorithm)
    line = _one_error_line(err)
    assert code == 2 and "value_out_of_range" in line and "part-00000.parquet: row 5" in line and "'cost'" in line


def test_fit_on_an_out_of_range_action_exits_2(tmp_path, capsys, grid):
    a = grid.table.column("action").to_numpy().copy()
    a[3] = 99
    _with(grid, "action", a).save(tmp_path / "bad")
    code, _, err = _run(capsys, "fit", str(tmp_path / "bad"), "--out", str(tmp_path / "run"), "--algorithm", "fqi")
    line = _one_error_line(err)
    assert code == 2 and "action_out_of_range" in line and "row 3" in line


def test_inspect_counts_out_of_range_actions_instead_of_crashing(tmp_path, capsys, grid):
    a = grid.table.column("action").to_numpy().copy()
    a[3] = 99
    a[4] = -1
    _with(grid, "action", a).save(tmp_path / "bad")
    code, out, err = _run(capsys, "inspect", str(tmp_path / "bad"))
    assert code == 0, err
    assert "(outside the action table): 2" in out
    counts = np.bincount(a[(a >= 0) & (a < grid.n_actions)], minlength=grid.n_actions)
    for name, c in zip(grid.info.action_table.names, counts, strict=True):
        assert f"{name}: {c}" in out


def test_simulate_python_api_rejects_bad_counts():
    from offline_adp.errors import InvalidArgumentError

    with pytest.raises(InvalidArgumentError, match="n_exploration"):
        simulate("gridworld", 1, -1)
    with pytest.raises(InvalidArgumentError, match="n_demonstrations"):
        simulate("gridworld", True, 1)


def test_ctrl_c_before_the_command_runs_is_one_line_not_a_traceback(monkeypatch, capsys):
    import offline_adp.cli as cli

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)  # Ctrl-C while the parser's imports load
    assert cli.main(["evaluate", "x"]) == 130
    assert capsys.readouterr().err.strip() == "interrupted"


def test_spec_names_must_be_non_empty_and_unique_said_once():
    import pytest

    from offline_adp.errors import SpecError
    from offline_adp.ingest.spec import parse_parquet_spec

    base = {"episode": {"id": "ep", "step": "k"}, "observations": {"columns": ["x"], "next_columns": ["x_next"]},
            "cost": {"column": "c"}, "end": {"truncated": "trunc"}}
    with pytest.raises(SpecError, match=r"action.names\[0\]: String should have at least 1 character"):
        parse_parquet_spec({**base, "action": {"columns": ["a", "b"], "names": ["", "c"]}}, where="s.toml")
    with pytest.raises(SpecError) as e:
        parse_parquet_spec({**base, "action": {"columns": ["a", "b"], "names": ["a", "a"]}}, where="s.toml")
    assert str(e.value).count("['a', 'a']") == 1  # was "got ['a', 'a'], got ['a', 'a']"
