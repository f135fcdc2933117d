"""`offline-adp evaluate` + `report` end to end: with a simulator and from logs only."""

from __future__ import annotations

import base64
import json
import re

import pytest

from offline_adp.cli import main


@pytest.fixture(scope="module")
def pt_run(tmp_path_factory, small_pt):
    root = tmp_path_factory.mktemp("pt")
    small_pt.save(root / "ds")
    cfg = root / "fqi.toml"
    cfg.write_text("[fqi]\nmode = \"frozen\"\nn_iterations = 10\n[fqi.regressor_params]\nn_estimators = 10\n")
    assert main(["fit", str(root / "ds"), "--config", str(cfg), "--out", str(root / "run"), "--quiet"]) == 0
    return root


def _check_report(run):
    html = (run / "report" / "report.html").read_text()
    names = re.findall(r'<figure id="([a-z_]+)"><img alt="[a-z_]+" src="data:image/png;base64,([A-Za-z0-9+/=]+)"', html)
    assert names, "no figures in the report"
    for name, data in names:
        assert base64.b64decode(data)[:8] == b"\x89PNG\r\n\x1a\n", name
        png = run / "report" / "figures" / f"{name}.png"
        assert png.stat().st_size > 1000, name
    return {n for n, _ in names}


def test_evaluate_and_report_with_simulator(pt_run, capsys):
    run = pt_run / "run"
    assert main(["evaluate", str(run), "--episodes", "40", "--bootstrap", "20", "--fqe-bootstrap", "2", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "cross-track" in out and "FQE" in out
    m = json.loads((run / "evaluation" / "metrics.json").read_text())
    assert m["simulator"] == "path_tracking"
    assert set(m["ope"]) == {"fqe", "model", "is", "wis", "pdis", "wpdis", "dr", "wdr", "mis"}
    for r in m["ope"].values():
        assert len(r["interval"]) == 2 and "rollout_error" in r
    p, d = m["rollout"]["policy"], m["rollout"]["demonstrator"]
    assert p["n_episodes"] == d["n_episodes"] == 40 and p["mean_abs_cross_track_error_m"] > 0
    assert {"recursion", "classifier", "reference:demonstrator"} <= set(m["shift"])
    steps = m["shift"]["classifier"]["per_step"]
    assert all(0.0 <= s["auc"] <= 1.0 and s["sup_ucb"] >= s["supported_sup"] - 1e-12 for s in steps)
    assert set(m["per_source"]) == {"demonstration", "exploration"}
    assert sum(v["data_mass"] for v in m["per_source"].values()) == pytest.approx(1.0)
    # one estimand, declared; the headline quotes the classifier ratios (the most trustworthy diagnostic)
    assert m["estimand"]["horizon"] == m["rollout"]["horizon"] and m["estimand"]["gamma"] == m["gamma"]
    assert m["headline"]["shift"]["method"] == "classifier"
    assert "classifier ratios (simulator)" in out and "verdict:" in out
    worst = min(s["ess_fraction"] for s in steps)
    assert m["headline"]["shift"]["ess_fraction"] == pytest.approx(worst)
    assert main(["report", str(run)]) == 0
    figs = _check_report(run)
    assert {"convergence", "policy_map", "value_map", "ope", "ratios", "coverage", "sources", "traced_e"} <= figs
    html = (run / "report" / "report.html").read_text()
    summary = html[html.index("<section class='summary'>"):html.index("</section>")]
    assert "classifier ratios (simulator)" in summary and "Simulator truth" in summary
    assert html.index("<section class='summary'>") < html.index("<figure")  # summary box first, then figures
    assert "None" not in re.sub(r"<img[^>]*>", "", html)  # no Python reprs


def test_evaluate_and_report_from_logs_only(pt_run, tmp_path):
    run = pt_run / "run"
    assert main(["evaluate", str(run), "--simulator", "none", "--bootstrap", "10", "--fqe-bootstrap", "0",
                 "--quiet"]) == 0
    m = json.loads((run / "evaluation" / "metrics.json").read_text())
    assert "rollout" not in m and m["simulator"] is None
    assert set(m["shift"]) == {"recursion"}
    assert main(["report", str(run)]) == 0
    figs = _check_report(run)
    assert "traced_e" not in figs and {"ope", "ratios", "coverage"} <= figs


def test_evaluate_errors_name_the_problem(tmp_path, capsys):
    assert main(["evaluate", str(tmp_path)]) == 2
    assert "not a run directory" in capsys.readouterr().err
    (tmp_path / "model").mkdir()
    assert main(["report", str(tmp_path)]) == 2
    assert "offline-adp evaluate" in capsys.readouterr().err


@pytest.fixture(scope="module")
def run30(tmp_path_factory):
    """A 30-episode log (15 demonstrations, 15 exploration) and a quick FQI fit."""
    from offline_adp.simulate import simulate

    root = tmp_path_factory.mktemp("pt30")
    simulate("path_tracking", 15, 15, seed=5, horizon=60).save(root / "ds")
    cfg = root / "fqi.toml"
    cfg.write_text("[fqi]\nmode = \"frozen\"\nn_iterations = 10\n[fqi.regressor_params]\nn_estimators = 10\n")
    assert main(["fit", str(root / "ds"), "--config", str(cfg), "--out", str(root / "run"), "--quiet"]) == 0
    return root / "run"


def test_logs_only_report_on_30_episodes_does_not_claim_no_shift(run30, capsys):
    """30 episodes give ~30 states per step: the per-step recursion shrinks to ratio 1 and would read ESS/n 1.0;
    the headline must say it cannot tell instead (and name what it quotes), and say why no simulator ran."""
    assert main(["evaluate", str(run30), "--simulator", "none", "--bootstrap", "20", "--fqe-bootstrap", "0",
                 "--quiet"]) == 0
    out = capsys.readouterr().out
    m = json.loads((run30 / "evaluation" / "metrics.json").read_text())
    sh = m["headline"]["shift"]
    assert "not enough data per step" in sh["text"] and "ESS/n 1.0" not in sh["text"]
    assert sh["ess_fraction"] is None or sh["ess_fraction"] < 0.999
    assert "not enough data per step" in out and "ESS/n 1.000" not in out
    assert "no simulator used" in out and "--simulator NAME" in out
    assert main(["report", str(run30)]) == 0
    html = (run30 / "report" / "report.html").read_text()
    assert "ESS/n 1.000" not in html and "not enough data per step" in html
    # degenerate estimators are never quoted as the best estimate
    best = m["headline"]["best"]
    assert best is None or not m["ope"][best["name"]]["degenerate"]


def test_simulator_note_says_how_to_name_one():
    from offline_adp.evaluation.run import _simulator_note

    assert _simulator_note("path_tracking", None, ["path_tracking"]) is None
    assert _simulator_note(None, "path_tracking", ["path_tracking"]) is None
    note = _simulator_note(None, None, ["car_on_hill", "path_tracking"])
    assert "names no reference problem" in note and "--simulator NAME (car_on_hill, path_tracking)" in note
    assert "--simulator none" in _simulator_note("none", "path_tracking", ["path_tracking"])
