"""The coverage suite (benchmarks/ope_coverage.py) at a tiny size: structure, not golden numbers.

Full-size numbers are measured by hand and kept in docs/evaluation.md ("Coverage suite").
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _suite():
    spec = importlib.util.spec_from_file_location("ope_coverage", ROOT / "benchmarks" / "ope_coverage.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_coverage_suite_tiny(tmp_path):
    oc = _suite()
    cands = ["fqi_1it", "demonstrator"]  # a fitted candidate and one of the behaviour's components
    out = oc.run_suite(["path_tracking"], [1], "tiny", cands, n_boot=20, say=lambda _m: None)  # the suite's plumbing
    rows, summary = out["rows"], out["summary"]
    assert [r["candidate"] for r in rows] == cands
    for r in rows:
        lo, hi = r["truth_interval"]
        assert lo <= r["truth"] <= hi and hi > lo  # every candidate has a simulator truth
        assert r["behaviour_logged"] is not None
        for key in ("verdict", "verdict_logs_only"):  # and a verdict, checked against the truth
            assert r[key]["performance"] in ("better", "worse", "indistinguishable", "unknown")
            assert r[key]["text"]
            assert r[key]["check"] in ("agrees", "contradicted", "unconfirmed", "no claim")
        # with the simulator the rollouts decide: never contradicted by them
        assert r["verdict"]["check"] != "contradicted", r["verdict"]["text"]
        if r["headline"] is not None:  # a labelled estimate and a baseline: the verdict is the rollouts' side
            assert r["verdict"]["performance"] == r["truth_side"]
        for e in r["estimators"].values():
            if e["labelled_95"]:
                assert e["interval"] is not None and e["covers"] in (True, False)
    s = summary["path_tracking"]
    assert s["candidates"] == len(cands)
    assert 0.0 <= s["labelled_share"] <= 1.0
    assert s["headline_coverage"] is None or 0.0 <= s["headline_coverage"] <= 1.0
    for v in s["per_estimator"].values():
        assert v["coverage"] is None or 0.0 <= v["coverage"] <= 1.0
        assert 0 <= v["covered"] <= v["labelled"] <= len(cands)
    assert s["contradicted_with_simulator"] == 0
    # what a user without a simulator sees may not be contradicted either (the logs-only rule)
    assert s["contradicted_logs_only"] == 0, [r["verdict_logs_only"]["text"] for r in rows]
    assert 0 <= s["contradicted_logs_only"] <= s["claims_logs_only"] <= len(cands)
    # the report and its JSON
    table = oc.table(summary, rows)
    assert "| path_tracking |" in table and all(c in table for c in cands)
    path, again = tmp_path / "cov.json", tmp_path / "again.json"
    path.write_text(json.dumps(oc.json_safe(out)))
    assert oc.main(["--rows-from", str(path), "--json", str(again)]) == 0  # the CLI, re-summarising without a rerun
    data = json.loads(again.read_text())
    assert [r["candidate"] for r in data["rows"]] == cands and data["summary"]["path_tracking"]["candidates"] == len(
        cands
    )


def test_continuous_problems_run_through_the_suite():
    """path_tracking with continuous steering, and with steering and acceleration: logs of
    exact commands, candidates that are deterministic command policies (a FQI fit over
    commands and the demonstrator's noise-free controller), the evaluation a user's
    ``evaluate`` runs (FQE over commands hulled with the model rollouts over commands), a
    simulator truth and checked verdicts. Fewer replicates and particles than a user's
    defaults: plumbing, not coverage (docs/continuous-commands.md has the measured numbers)."""
    oc = _suite()
    cands = ["fqi_1it", "demonstrator"]
    out = oc.run_suite(list(oc.CONTINUOUS), [1], "tiny", cands, n_boot=0, say=lambda _m: None,
                       options={"n_boot_fqe": 20, "model_particles": 200})
    rows, summary = out["rows"], out["summary"]
    assert [(r["problem"], r["candidate"]) for r in rows] == [(p, c) for p in oc.CONTINUOUS for c in cands]
    for r in rows:
        lo, hi = r["truth_interval"]
        assert lo <= r["truth"] <= hi and hi > lo
        # over commands, FQE and the model's own interval run (evaluation/continuous.py)
        assert set(r["estimators"]) == {"fqe", "model"}
        f = r["fqe"]
        assert f["interval"] is not None and f["covers"] in (True, False) and 0 < f["width_over_range"] <= 2
        assert f["unsupported"] is not None and 0.0 <= f["unsupported"] <= 1.0
        e = r["estimators"]["fqe"]
        # a level is the measured one or withdrawn with its reason, never another
        assert e["labelled_95"] == (e["interval"] is not None) and (e["labelled_95"] or f["level_note"])
        assert r["verdict"]["check"] != "contradicted", r["verdict"]["text"]
        assert r["verdict_logs_only"]["check"] != "contradicted", r["verdict_logs_only"]["text"]
    for p in oc.CONTINUOUS:
        s = summary[p]
        assert s["candidates"] == len(cands) and s["fqe_shown"] == len(cands)
        assert s["contradicted_with_simulator"] == 0 and s["contradicted_logs_only"] == 0
    assert "| path_tracking_steer_accel |" in oc.table(summary, rows)
    # the continuous problems' own candidate lists: deterministic command policies only
    assert "exploration" not in oc.CONTINUOUS_CANDIDATES and "fqi_eps30" not in oc.CONTINUOUS_HOLDOUT


def test_the_logs_only_view_restores_only_what_the_simulator_withdrew():
    """A user without a simulator never has the simulator's findings (their withdrawal note is
    undone), but a level withdrawn from the logs alone (a policy replaying the logged commands)
    stays withdrawn."""
    from offline_adp.evaluation.summary import LEVEL_WITHDRAWN

    oc = _suite()
    note = LEVEL_WITHDRAWN.format(level=0.95, model="value model")
    by_sim = {"level": None, "nominal_level": 0.95, "level_note": note, "withdrawn_by": "support"}
    assert oc._level_back(by_sim) == {"level": 0.95}
    by_logs = {"level": None, "nominal_level": 0.95, "level_note": "the policy replays the logs",
               "withdrawn_by": "replay"}
    assert oc._level_back(by_logs) == by_logs
    assert oc._level_back({"level": 0.95}) == {"level": 0.95}
