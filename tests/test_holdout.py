"""``offline-adp fit --holdout``: episodes kept out of the fit, recorded in ``run.json``, and
``evaluate`` reading the policy on them; on the fit's own logs, the verdict saying so."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pandas as pd
import pytest

from offline_adp.data.dataset import read_dataset
from offline_adp.data.holdout import holdout_split, ids_sha256
from offline_adp.errors import ArtifactError, InvalidArgumentError, RunDirectoryError

FIT = {"n_iterations": 3, "regressor_params": {"n_estimators": 3, "n_jobs": 1}}
QUICK = {"bootstrap": 10, "fqe_bootstrap": 5, "model_particles": 0, "episodes": 10}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A tabular dataset of 20 episodes, a run fitted on all of them and one with 30% held out."""
    from offline_adp.runs import fit_run
    from offline_adp.simulate import simulate

    tmp = tmp_path_factory.mktemp("holdout")
    simulate("tabular", 10, 10, seed=3).save(tmp / "data")
    fit_run(tmp / "data", tmp / "all", params=FIT)
    fit_run(tmp / "data", tmp / "held", params={**FIT, "random_state": 5}, holdout=0.3)
    return tmp


def _record(run):
    return json.loads((run / "run.json").read_text())["holdout"]


def test_the_split_is_seeded_recorded_and_the_fit_never_sees_it(runs, tmp_path):
    from offline_adp.artifacts import load_q
    from offline_adp.runs import fit_run

    ds = read_dataset(runs / "data")
    rec = _record(runs / "held")
    assert (rec["fraction"], rec["seed"], rec["episodes"], rec["of"]) == (0.3, 5, 6, 20)
    assert rec["ids"] == sorted(rec["ids"]) and rec["ids_sha256"] == ids_sha256(rec["ids"])
    _, held, again = holdout_split(ds, 0.3, 5)  # the same rule, the same episodes
    assert sorted(map(str, held.episode_ids)) == rec["ids"] and again == rec
    assert holdout_split(ds, 0.3, 6)[2]["ids"] != rec["ids"]  # the seed chooses them
    assert "holdout" not in json.loads((runs / "all" / "run.json").read_text())
    # the fit saw the other 14 episodes only: the same Q as a fit on a dataset of just those
    ds.select_episodes([e for e in ds.episode_ids if str(e) not in rec["ids"]]).save(tmp_path / "rest")
    fit_run(tmp_path / "rest", tmp_path / "rest_run", params={**FIT, "random_state": 5})
    obs = ds.arrays().obs
    q_held, q_rest = load_q(runs / "held" / "model")[0], load_q(tmp_path / "rest_run" / "model")[0]
    assert np.array_equal(q_held.values(obs), q_rest.values(obs))


def test_evaluate_reads_the_held_out_episodes_only(runs, tmp_path):
    from offline_adp.evaluation.run import evaluate_run
    from offline_adp.evaluation.summary import summary_lines

    ds = read_dataset(runs / "data")
    held = ds.select_episodes(_record(runs / "held")["ids"])
    run = tmp_path / "held"
    shutil.copytree(runs / "held", run)
    m = evaluate_run(run, simulator="none", **QUICK)
    assert m["logs"]["kind"] == "held_out" and m["logs"]["in_sample"] is False
    assert (m["logs"]["episodes"], m["logs"]["of"]) == (6, 20)
    assert m["logs"]["description"] == "held-out episodes (6 of 20) the fit did not see"
    assert (m["dataset"]["transitions"], m["dataset"]["episodes"]) == (len(held), 6) and len(held) < len(ds)
    assert len(pd.read_parquet(run / "evaluation" / "ratios.parquet")) == len(held)
    assert m["headline"]["logs_note"] is None and "fit's own" not in m["headline"]["verdict"]["lines"][2]
    assert "logs: held-out episodes (6 of 20) the fit did not see" in summary_lines(m)
    # the same dataset named with --dataset: the same episodes; other logs: read whole
    assert evaluate_run(run, simulator="none", dataset=runs / "data", **QUICK)["dataset"]["transitions"] == len(held)
    from offline_adp.simulate import simulate

    simulate("tabular", 6, 6, seed=9).save(tmp_path / "other")
    m = evaluate_run(run, simulator="none", dataset=tmp_path / "other", **QUICK)
    assert m["logs"]["kind"] == "other" and not m["logs"]["in_sample"] and m["dataset"]["episodes"] == 12
    # a record that does not hold on the dataset is refused, naming run.json
    rj = json.loads((run / "run.json").read_text())
    rj["holdout"]["ids"] = rj["holdout"]["ids"][1:] + [str(ds.episode_ids[0])]
    (run / "run.json").write_text(json.dumps(rj))
    with pytest.raises(ArtifactError, match="run.json: the held-out episodes it records"):
        evaluate_run(run, simulator="none", **QUICK)


def test_the_fits_own_logs_are_marked_in_sample_unless_the_simulator_is_the_truth(runs, tmp_path):
    from offline_adp.evaluation.report import build_report
    from offline_adp.evaluation.run import evaluate_run
    from offline_adp.evaluation.summary import summary_lines

    run = tmp_path / "all"
    shutil.copytree(runs / "all", run)
    m = evaluate_run(run, simulator="none", **QUICK)
    assert m["logs"] == {"kind": "fit", "in_sample": True, "episodes": 20, "of": 20,
                         "description": "the episodes the run was fitted on (all 20)"}
    note = m["headline"]["logs_note"]
    assert note and "fit's own" in note and "--holdout" in note
    why = m["headline"]["verdict"]["lines"][2]
    assert why.endswith(note) and why.count("fit's own") == 1 and "The logs are the fit's own" in \
        m["headline"]["verdict"]["text"]
    assert any(line.startswith("why: ") and note in line for line in summary_lines(m))
    assert json.loads((run / "evaluation" / "metrics.json").read_text())["logs"]["in_sample"] is True
    assert "fit&#x27;s own" in build_report(run).read_text()
    # the simulator's rollouts measured the estimand: their truth leads, no note (the flag stays)
    m = evaluate_run(run, simulator="tabular", **QUICK)
    assert m["logs"]["in_sample"] is True and m["headline"]["logs_note"] is None
    assert not any("fit's own" in line for line in summary_lines(m))


@pytest.mark.parametrize("bad", [-0.1, 1.0, 1.5, math.nan, True, "0.3"])
def test_a_holdout_outside_0_1_is_refused_naming_the_flag(runs, tmp_path, bad):
    from offline_adp.runs import fit_run

    with pytest.raises(InvalidArgumentError, match="--holdout"):
        fit_run(runs / "data", tmp_path / "r", params=FIT, holdout=bad)
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("fraction", [0.05, 0.95])
def test_a_holdout_leaving_fewer_than_two_episodes_a_side_is_refused(runs, tmp_path, fraction, capsys):
    from offline_adp.cli import main

    assert main(["fit", str(runs / "data"), "--out", str(tmp_path / "r"), "--holdout", str(fraction), "-q"]) == 2
    err = capsys.readouterr().err
    assert "error: --holdout" in err and "each side needs at least 2 episodes" in err and "Traceback" not in err
    assert not (tmp_path / "r").exists()


def test_a_resumed_run_keeps_its_holdout(runs, tmp_path):
    from offline_adp.runs import fit_run

    run = tmp_path / "held"
    shutil.copytree(runs / "held", run)
    with pytest.raises(RunDirectoryError, match="started with --holdout 0.3, not 0.5"):
        fit_run(runs / "data", run, resume=True, holdout=0.5)


def test_compare_refuses_candidates_read_on_different_episodes(runs, tmp_path):
    from offline_adp.errors import IncompatibleError
    from offline_adp.evaluation.compare import compare_runs

    for name in ("all", "held"):
        shutil.copytree(runs / name, tmp_path / name)
    with pytest.raises(IncompatibleError, match=r"read on different episodes of their logs \(all: no holdout; "
                                                r"held: --holdout 0.3 with random_state 5\)"):
        compare_runs([tmp_path / "all", tmp_path / "held"], simulator="none", evaluate_params=QUICK)


def test_the_pipeline_file_takes_holdout_in_its_fit_table(runs, tmp_path):
    from offline_adp.errors import SpecError
    from offline_adp.pipeline import _fit_stage
    from offline_adp.pipeline_file import load_pipeline

    text = '[data]\nsimulate = "tabular"\n[fit]\nalgorithm = "fqi"\nholdout = {}\n'
    (tmp_path / "p.toml").write_text(text.format(0.25))
    assert load_pipeline(tmp_path / "p.toml")["fit"]["holdout"] == 0.25
    (tmp_path / "p.toml").write_text(text.format(1.0))
    with pytest.raises(SpecError, match="holdout"):
        load_pipeline(tmp_path / "p.toml")
    shutil.copytree(runs / "data", tmp_path / "run" / "dataset")  # the fit stage holds the episodes out
    _fit_stage({"fit": {"algorithm": "fqi", "params": FIT, "holdout": 0.3}, "seed": 5}, tmp_path / "run", print)
    assert _record(tmp_path / "run" / "fit") == _record(runs / "held")


def test_an_algorithm_fitted_whole_never_sees_the_held_out_episodes_either(runs, tmp_path):
    from offline_adp.artifacts import load_index_policy
    from offline_adp.runs import fit_run

    api = {"n_iterations": 2, "fqe": {"n_iterations": 3, "mode": "frozen",
                                      "regressor_params": {"n_estimators": 3, "n_jobs": 1}}}
    fit_run(runs / "data", tmp_path / "held", algorithm="api", params=api, holdout=0.3)
    ds = read_dataset(runs / "data")
    ids = _record(tmp_path / "held")["ids"]
    ds.select_episodes([e for e in ds.episode_ids if str(e) not in ids]).save(tmp_path / "rest")
    fit_run(tmp_path / "rest", tmp_path / "rest_run", algorithm="api", params=api)
    obs = ds.arrays().obs
    acts = [load_index_policy(tmp_path / r / "model").act(obs) for r in ("held", "rest_run")]
    assert np.array_equal(*acts)
    whole = tmp_path / "whole"  # (and the test can tell: a fit on every episode acts otherwise)
    fit_run(runs / "data", whole, algorithm="api", params=api)
    assert not np.array_equal(acts[0], load_index_policy(whole / "model").act(obs))


@pytest.mark.parametrize("bad", ["0.3", [0.3], {}, {"fraction": "abc"}, {"fraction": None},
                                 {"fraction": 1.5}, {"fraction": 0.3, "seed": 1e400, "ids_sha256": "x"},
                                 {"fraction": 0.3, "seed": 0}])
def test_a_malformed_holdout_record_is_our_error_never_read_as_none(runs, tmp_path, bad, capsys):
    """run.json is untrusted: a 'holdout' record of another shape must not crash evaluate
    (a traceback) nor be read as "no holdout" (the fit did not see those episodes)."""
    from offline_adp.cli import main
    from offline_adp.evaluation.run import evaluate_run

    run = tmp_path / "held"
    shutil.copytree(runs / "held", run)
    rj = json.loads((run / "run.json").read_text())
    rj["holdout"] = bad
    (run / "run.json").write_text(json.dumps(rj).replace("Infinity", "1e400"))  # a seed beyond any integer
    with pytest.raises(ArtifactError, match=r"run.json: its 'holdout' record is not one this version reads"):
        evaluate_run(run, simulator="none", **QUICK)
    assert main(["evaluate", str(run), "--simulator", "none", "--bootstrap", "10", "--fqe-bootstrap", "5",
                 "--model-particles", "0"]) != 0
    err = capsys.readouterr().err
    assert "Traceback" not in err and "holdout" in err


def test_the_report_says_the_policy_was_read_on_episodes_its_fit_held_out(runs, tmp_path):
    """The report's first line said "fitted ... on" the evaluated episodes: for a held-out run
    those are the ones the fit did NOT see."""
    from offline_adp.evaluation.report import build_report
    from offline_adp.evaluation.run import evaluate_run

    run = tmp_path / "held"
    shutil.copytree(runs / "held", run)
    m = evaluate_run(run, simulator="none", **QUICK)
    sub = build_report(run).read_text().split("<p class='sub'>", 1)[1].split("</p>", 1)[0]
    assert sub.startswith(f"Policy fitted by FQI, evaluated on {m['dataset']['transitions']:,} transitions in the 6 "
                          "episodes its fit held out")
    own = tmp_path / "all"
    shutil.copytree(runs / "all", own)
    evaluate_run(own, simulator="none", **QUICK)
    assert "fitted and evaluated on" in build_report(own).read_text()
