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
    assert [r["candidate"] for r in data["rows"]] == cands and data["summary"]["path_tracking"]["candidates"] == len(cands)
