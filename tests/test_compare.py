"""Off-policy selection: ``offline-adp compare`` ranks candidate policies on the same logs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from offline_adp.cli import main
from offline_adp.errors import OfflineADPError
from offline_adp.evaluation.compare import compare_runs, selection_scores


def test_selection_scores_known_answers():
    truth = [1.0, 2.0, 3.0, 4.0]
    s = selection_scores([10.0, 20.0, 30.0, 40.0], truth)  # same order, other scale
    assert s["spearman"] == pytest.approx(1.0) and s["kendall"] == pytest.approx(1.0)
    assert s["regret_top1"] == 0.0 and s["top_pick_is_best"]
    s = selection_scores([4.0, 3.0, 2.0, 1.0], truth)  # reversed: picks the worst
    assert s["spearman"] == pytest.approx(-1.0) and s["regret_top1"] == pytest.approx(3.0)
    assert s["relative_regret_top1"] == pytest.approx(1.0)
    s = selection_scores([1.0, 3.0, 2.0, 4.0], truth)  # one swap in the middle
    assert s["spearman"] == pytest.approx(1 - 6 * 2 / (4 * 15)) and s["regret_top1"] == 0.0


@pytest.fixture(scope="module")
def candidates(tmp_path_factory, small_pt):
    root = tmp_path_factory.mktemp("cmp")
    small_pt.save(root / "ds")
    runs = []
    for k in (1, 4, 10):
        cfg = root / f"fqi{k}.toml"
        cfg.write_text(f"[fqi]\nmode = \"frozen\"\nn_iterations = {k}\n[fqi.regressor_params]\nn_estimators = 10\n")
        assert main(["fit", str(root / "ds"), "--config", str(cfg), "--out", str(root / f"fqi{k}"), "--quiet"]) == 0
        runs.append(root / f"fqi{k}")
    return root, runs


@pytest.mark.integration
def test_compare_ranks_candidates_with_simulator_truth(candidates, capsys):
    root, runs = candidates
    res = compare_runs(runs, evaluate_params={"n_episodes": 30, "n_boot": 20, "n_boot_fqe": 0})
    c = res["candidates"]
    assert len(c) == 3 and {x["run"] for x in c} == {str(r) for r in runs}
    ranked = [x for x in c if x["rank"] is not None]
    assert [x["rank"] for x in ranked] == list(range(1, len(ranked) + 1))
    assert all(a["estimate"] <= b["estimate"] for a, b in zip(ranked, ranked[1:], strict=False))
    assert all(x["truth"] is not None and x["shift"] for x in c)
    sel = res["selection"]
    # the scores are recomputed from the candidates' own numbers (an independent check of the bookkeeping)
    again = selection_scores([x["estimate"] for x in ranked], [x["truth"] for x in ranked])
    assert sel["spearman"] == pytest.approx(again["spearman"])
    assert sel["regret_top1"] == pytest.approx(ranked[0]["truth"] - min(x["truth"] for x in ranked))
    assert -1.0 <= sel["spearman"] <= 1.0 and sel["regret_top1"] >= 0.0
    # the CLI reuses the matching evaluations and prints the table
    out_json = root / "cmp.json"
    assert main(["compare", *map(str, runs), "--json", str(out_json), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "Spearman" in out and "regret of the top pick" in out
    assert json.loads(out_json.read_text())["selection"]["spearman"] == pytest.approx(sel["spearman"])
    assert np.isfinite(sel["kendall"])


def test_compare_needs_two_runs_on_the_same_logs(candidates, tmp_path):
    _, runs = candidates
    with pytest.raises(OfflineADPError, match="at least two"):
        compare_runs(runs[:1])
    with pytest.raises(OfflineADPError, match="not a run directory"):
        compare_runs([runs[0], tmp_path])
    assert main(["compare", str(runs[0]), str(tmp_path)]) == 2


def test_compare_refuses_an_unknown_estimator_before_any_work(tmp_path):
    from offline_adp.errors import OfflineADPError
    from offline_adp.evaluation.compare import compare_runs

    runs = [tmp_path / "a", tmp_path / "b"]
    for r in runs:
        (r / "model").mkdir(parents=True)
    with pytest.raises(OfflineADPError, match="unknown estimator 'fqee'"):
        compare_runs(runs, estimator="fqee")
