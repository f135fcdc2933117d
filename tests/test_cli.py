"""The offline-adp command line, end to end on small data."""

from __future__ import annotations

import json

import numpy as np
import pytest

from offline_adp.cli import main
from offline_adp.data.dataset import read_dataset


def test_version_and_help_examples(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and "offline-adp 0." in capsys.readouterr().out
    for cmd in (["simulate"], ["ingest", "parquet"], ["validate"], ["inspect"]):
        with pytest.raises(SystemExit):
            main([*cmd, "--help"])
        out = capsys.readouterr().out
        assert "example" in out and "offline-adp " in out


def test_simulate_ingest_validate_inspect(tmp_path, capsys):
    raw = tmp_path / "logs" / "pt.parquet"
    assert main(["simulate", "path_tracking", "--format", "parquet", "--out", str(raw), "--demonstrations", "3",
                 "--exploration", "3", "--horizon", "20", "-q"]) == 0
    spec = tmp_path / "logs" / "pt.spec.toml"
    assert spec.exists()
    assert main(["ingest", "parquet", str(raw), "--spec", str(spec), "--out", str(tmp_path / "ds"), "-q"]) == 0
    assert "pass every check" in capsys.readouterr().out
    assert main(["validate", str(tmp_path / "ds")]) == 0
    assert main(["inspect", str(tmp_path / "ds"), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out.split("\n", 1)[1])
    assert rep["episodes"] == 6 and set(rep["per_source"]) == {"demonstration", "exploration"}
    assert sum(rep["actions"]["coverage"].values()) == rep["transitions"]
    # the direct dataset equals the ingested one
    assert main(["simulate", "path_tracking", "--out", str(tmp_path / "direct"), "--demonstrations", "3",
                 "--exploration", "3", "--horizon", "20", "-q"]) == 0
    assert read_dataset(tmp_path / "direct").fingerprint() == read_dataset(tmp_path / "ds").fingerprint()


def test_errors_are_one_line_with_exit_2(tmp_path, capsys):
    assert main(["inspect", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "not a dataset directory" in err and "Traceback" not in err
    assert main(["simulate", "gridworld", "--out", str(tmp_path / "g"), "--demonstrations", "1", "--exploration", "1",
                 "-q"]) == 0
    assert main(["simulate", "gridworld", "--out", str(tmp_path / "g"), "--demonstrations", "1", "--exploration", "1",
                 "-q"]) == 2
    assert "--overwrite" in capsys.readouterr().err


def test_validate_exit_status_on_defects(tmp_path, capsys):
    import pyarrow.parquet as pq

    assert main(["simulate", "tabular", "--out", str(tmp_path / "t"), "--demonstrations", "2", "--exploration", "2",
                 "-q"]) == 0
    part = next((tmp_path / "t" / "data").glob("part-*.parquet"))
    t = pq.read_table(part).to_pandas()
    t.loc[3, "cost"] = np.inf
    pq.write_table(__import__("pyarrow").Table.from_pandas(t, preserve_index=False), part)
    capsys.readouterr()
    assert main(["validate", str(tmp_path / "t")]) == 1
    out = capsys.readouterr().out
    assert "part-00000.parquet: row 3" in out and "non_finite" in out


@pytest.mark.parametrize("encoding", ["json", "ros2"])
def test_simulate_mcap(tmp_path, encoding):
    from mcap.reader import make_reader

    assert main(["simulate", "path_tracking", "--format", f"mcap-{encoding}", "--out", str(tmp_path / "m"),
                 "--demonstrations", "2", "--exploration", "1", "--horizon", "10", "-q"]) == 0
    files = sorted((tmp_path / "m").glob("*.mcap"))
    assert [f.name for f in files] == ["demonstration.mcap", "exploration.mcap"]
    with open(files[0], "rb") as f:
        s = make_reader(f).get_summary()
    counts = {c.topic: s.statistics.channel_message_counts[i] for i, c in s.channels.items()}
    # 2 episodes x 10 steps: tracking state at every step + final, odometry 5 per step + final
    assert counts["/planning/tracking_state"] == 2 * 11
    assert counts["/vehicle/odometry"] == 2 * (10 * 5 + 1)
    assert counts["/control/steering_cmd"] == 2 * 10
    assert counts["/episode/event"] == 4
    enc = {c.message_encoding for c in s.channels.values()}
    assert enc == ({"cdr"} if encoding == "ros2" else {"json"})
    if encoding == "ros2":
        assert all(b"MSG: std_msgs/Header" in sc.data for sc in s.schemas.values())


def test_simulate_mcap_generic_json(tmp_path):
    from mcap.reader import make_reader

    assert main(["simulate", "car_on_hill", "--format", "mcap-json", "--out", str(tmp_path / "m"), "--demonstrations",
                 "2", "--exploration", "0", "-q"]) == 0
    with open(tmp_path / "m" / "demonstration.mcap", "rb") as f:
        msgs = [(c.topic, json.loads(m.data)) for _, c, m in make_reader(f).iter_messages()]
    obs = [d for t, d in msgs if t == "/observation"]
    acts = [d for t, d in msgs if t == "/action"]
    assert len(obs) == len(acts) + 2  # one final observation per episode
    assert {"p", "s", "step"} <= set(obs[0]) and acts[0]["value"][0] in (-4.0, 4.0)


@pytest.mark.parametrize("args, said", [
    (["--fqe-params", "{bad"], "--fqe-params: not valid JSON"),
    (["--fqe-params", "[1]"], "--fqe-params: expected a JSON object"),
    (["--fqe-params", '{"n_iterationz": 3}'], "did you mean 'n_iterations'"),
    (["--episodes", "0"], "expected an integer from 2 up to"),
    (["--horizon", "-3"], "expected a positive integer"),
])
def test_evaluate_refuses_bad_options_in_one_line(tmp_path, capsys, args, said):
    """Checked before the run directory is even opened: exit 2 and one line, no traceback."""
    try:
        code = main(["evaluate", str(tmp_path / "no-run"), *args])
    except SystemExit as exc:  # argparse usage errors
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2 and said in err and "Traceback" not in err
