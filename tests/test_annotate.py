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
    assert "already exists" in capsys.readouterr().err
    assert main(["annotate", str(tmp / "nope"), "--log", str(files[0]), "--out", str(tmp / "x.mcap")]) == 2
    assert "not a run directory" in capsys.readouterr().err
