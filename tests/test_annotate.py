"""`offline-adp annotate`: the log's messages plus four JSON topics whose values equal the
policy's on the ingested steps, stamped with the steps' log times."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")

from offline_adp.ingest.mcap import ingest_mcap  # noqa: E402
from offline_adp.simulate import simulate  # noqa: E402
from offline_adp.simulate.mcap_writer import write_mcap  # noqa: E402

SPEC = Path(__file__).resolve().parents[1] / "data" / "specs" / "path_tracking_mcap.toml"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from offline_adp.runs import fit_run

    tmp = tmp_path_factory.mktemp("annotate")
    files = write_mcap(simulate("path_tracking", 4, 4, seed=2, horizon=50), tmp / "logs", encoding="json", seed=1)
    ingest_mcap(files, SPEC, tmp / "data")
    fit_run(tmp / "data", tmp / "run", params={"regressor": "extra_trees", "n_iterations": 3,
                                               "regressor_params": {"n_estimators": 5, "n_jobs": 1}})
    return tmp, files


def _read(path):
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        msgs = [(ch.topic, sc, m) for sc, ch, m in reader.iter_messages(log_time_order=False)]
    return msgs


def test_annotated_log_carries_the_four_topics_with_the_policys_values(run):
    from offline_adp.cli import main
    from offline_adp.deploy import load_run_policy

    tmp, files = run
    log = files[0]
    out = tmp / "annotated.mcap"
    assert main(["annotate", str(tmp / "run"), "--log", str(log), "--out", str(out), "-q"]) == 0
    orig, ann = _read(log), _read(out)
    added = [x for x in ann if x[0].startswith("/offline_adp/")]
    # every original message is kept, byte for byte
    assert Counter((t, m.log_time, m.data) for t, _, m in orig) == Counter((t, m.log_time, m.data) for t, _, m in ann
                                                                           if not t.startswith("/offline_adp/"))
    topics = {t for t, _, _ in added}
    assert topics == {"/offline_adp/action", "/offline_adp/q_gap", "/offline_adp/density_ratio", "/offline_adp/support"}
    for _, schema, _ in added:
        assert schema.encoding == "jsonschema" and json.loads(schema.data)["type"] == "object"
    # reference: the same steps ingested independently, and the policy on them
    steps, _ = ingest_mcap([log], SPEC)
    pi = load_run_policy(tmp / "run")
    a = steps.arrays()
    idx = pi.act(a.obs, a.step, return_index=True)
    q = pi.q.values(a.obs)
    lt = steps.column("src_log_time")  # the log_time of the message that made each step
    by = {t: sorted([m for tt, _, m in added if tt == t], key=lambda m: m.sequence) for t in topics}
    for t in topics:
        assert [m.log_time for m in by[t]] == lt.tolist()  # stamped with the annotated messages' log times
    act = [json.loads(m.data) for m in by["/offline_adp/action"]]
    np.testing.assert_array_equal([d["policy_action_index"] for d in act], idx)
    np.testing.assert_array_equal([d["logged_action_index"] for d in act], a.action)
    np.testing.assert_array_equal([d["policy_action"][0] for d in act], pi.act(a.obs))
    gap = np.array([json.loads(m.data)["q_gap"] for m in by["/offline_adp/q_gap"]])
    rows = np.arange(len(idx))
    np.testing.assert_allclose(gap, q[rows, a.action] - q[rows, idx], rtol=0, atol=1e-12)
    assert (gap >= 0).all() and (gap[a.action == idx] == 0).all()  # greedy: the logged action is never cheaper
    dr = [json.loads(m.data) for m in by["/offline_adp/density_ratio"]]
    ratio = np.array([d["ratio"] for d in dr])
    np.testing.assert_allclose(ratio, (a.action == idx) / np.array([d["behaviour_prob"] for d in dr]))
    sup = [json.loads(m.data) for m in by["/offline_adp/support"]]
    assert all(d["out_of_support"] == (d["behaviour_prob_of_policy_action"] < d["threshold"]) for d in sup)
    assert [d["episode_id"] for d in sup] == steps.column("episode_id").astype(str).tolist()


def test_annotate_errors_are_one_line(run, capsys):
    from offline_adp.cli import main

    tmp, files = run
    assert main(["annotate", str(tmp / "run"), "--log", str(files[0]), "--out", str(files[0])]) == 2
    assert "is the input log" in capsys.readouterr().err
    assert main(["annotate", str(tmp / "nope"), "--log", str(files[0]), "--out", str(tmp / "x.mcap")]) == 2
    assert "not a run directory" in capsys.readouterr().err


def test_a_continuous_policy_annotates_its_commands_q_gap_and_support(tmp_path):
    """Continuous commands (a cmd_vel-style log) were refused ("a continuous policy has none
    of them yet"). Now: /offline_adp/command (policy vs logged command), /offline_adp/q_gap
    by the policy's own Q at both commands, /offline_adp/support as the evaluation's command
    support. Oracles: the loaded policy's commands, its trees read at [x, u] directly, and the
    evaluation's own command-support fraction on the same steps."""
    from offline_adp.annotate import annotate_mcap
    from offline_adp.deploy import load_run_policy
    from offline_adp.evaluation.continuous import command_support
    from offline_adp.ingest.mcap import parse_mcap_spec
    from offline_adp.runs import fit_run
    from tests.test_ingest_mcap_streaming import write_log

    rng = np.random.default_rng(0)
    msgs, x = [], 0.0
    for j in range(600):
        if j % 60 == 0:
            x = float(rng.uniform(-1, 1))
        u = [float(rng.uniform(-1, 1)), float(rng.uniform(0, 0.5))]
        msgs.append(("/state", 10**9 + j * 10**8 + (j // 60) * 3 * 10**9,
                     {"x": x, "v": u[0], "w": u[1], "c": x * x + 0.1 * u[0] ** 2}))
        x = 0.9 * x + 0.2 * u[0] - 0.1 * u[1]
    log = write_log(tmp_path / "drive.mcap", msgs)
    spec = parse_mcap_spec({
        "clock": {"topic": "/state"}, "episodes": {"gap": 1.0},
        "streams": [{"topic": "/state", "fields": {"x": "x"}, "max_age": 0.001},
                    {"topic": "/state", "role": "cost", "fields": {"c": "c"}, "max_age": 0.001}],
        "action": {"topic": "/state", "fields": {"v": "v", "w": "w"}, "type": "continuous", "max_age": 0.001},
        "cost": {"field": "c"}})
    ds, _ = ingest_mcap([log], spec, tmp_path / "data")
    fit_run(tmp_path / "data", tmp_path / "run", params={"n_iterations": 3, "regressor_params": {"n_estimators": 5}})
    s = annotate_mcap(tmp_path / "run", log, tmp_path / "out.mcap", spec=spec)
    added = [x for x in _read(tmp_path / "out.mcap") if x[0].startswith("/offline_adp/")]
    by = {t: [json.loads(m.data) for _, _, m in sorted([x for x in added if x[0] == t], key=lambda x: x[2].sequence)]
          for t in ("/offline_adp/command", "/offline_adp/q_gap", "/offline_adp/support")}
    assert {t for t, _, _ in added} == set(by) and s["steps"] == len(ds) and s["agreement"] is None
    steps, _ = ingest_mcap([log], spec)
    pi = load_run_policy(tmp_path / "run")
    a, u = steps.arrays(), steps.commands()
    np.testing.assert_array_equal([d["policy_command"] for d in by["/offline_adp/command"]], pi.act(a.obs))
    np.testing.assert_array_equal([d["logged_command"] for d in by["/offline_adp/command"]], u)
    trees = pi.q.models[0]  # Q(x, u) = the joint forest read at [x, u]
    q_gap = trees.predict(np.hstack([a.obs, u])) - trees.predict(np.hstack([a.obs, pi.act(a.obs)]))
    np.testing.assert_allclose([d["q_gap"] for d in by["/offline_adp/q_gap"]], q_gap, rtol=0, atol=1e-9)
    sup = by["/offline_adp/support"]
    assert all(d["out_of_support"] == (d["distance"] > d["radius"]) for d in sup)
    assert np.mean([d["out_of_support"] for d in sup]) == pytest.approx(command_support(ds, pi)["fraction"])


def test_annotate_holds_its_output_and_never_writes_into_the_run(run, tmp_path):
    """Two annotates of one --out used one fixed temporary name: in 2 of 8 races the file
    was neither run's output while both said they succeeded; and --out inside the run
    directory (e.g. RUN/model/q.npz --overwrite) destroyed the run."""
    import subprocess
    import sys
    import time

    from offline_adp.annotate import annotate_mcap
    from offline_adp.errors import LockedError, WriteError

    tmp, files = run
    out = tmp_path / "a.mcap"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom offline_adp.data.files import "
                               f"locked_directory\nwith locked_directory({str(out)!r}):\n    print('held', flush=True)"
                               "\n    time.sleep(30)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        t0 = time.monotonic()
        with pytest.raises(LockedError):
            annotate_mcap(tmp / "run", files[0], out, spec=SPEC)
        assert time.monotonic() - t0 < 10 and not out.exists()  # at once, nothing written
    finally:
        holder.kill()
        holder.wait()
    before = (tmp / "run" / "run.json").read_bytes()
    with pytest.raises(WriteError, match="inside the run directory"):
        annotate_mcap(tmp / "run", files[0], tmp / "run" / "run.json", spec=SPEC, overwrite=True)
    assert (tmp / "run" / "run.json").read_bytes() == before
