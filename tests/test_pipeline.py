"""`offline-adp run`: every shipped pipeline at reduced size, stage reuse, resume, errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from offline_adp.cli import main
from offline_adp.errors import SpecError
from offline_adp.pipeline import load_pipeline, run_pipeline

ROOT = Path(__file__).resolve().parents[1]
PIPELINES = ROOT / "pipelines"
#: Reduced sizes so every shipped pipeline runs in seconds.
SMALL = {
    "driving": {"fit.params.n_iterations": 10, "evaluate.episodes": 40, "evaluate.bootstrap": 20,
                "evaluate.fqe_bootstrap": 2,
                "evaluate.horizon": 20, "evaluate.fqe_params": {"n_iterations": 10}},
    "car_on_hill": {"data.exploration": 60, "fit.params.n_iterations": 10, "evaluate.episodes": 30,
                    "evaluate.bootstrap": 20,
                    "evaluate.fqe_bootstrap": 0, "evaluate.horizon": 30, "evaluate.fqe_params": {"n_iterations": 10}},
    "gridworld_divergence": {"fit.params.n_iterations": 30, "evaluate.episodes": 30,
                             "evaluate.bootstrap": 20, "evaluate.fqe_params": {"mode": "refit", "n_iterations": 5}},
    "psdp_driving": {"fit.params.horizon": 8, "fit.params.n_samples": 40, "fit.params.n_rollouts": 1,
                     "evaluate.episodes": 30, "evaluate.bootstrap": 20, "evaluate.fqe_bootstrap": 0,
                     "evaluate.horizon": 8,
                     "evaluate.fqe_params": {"n_iterations": 10}},
}


def quiet(_msg: str) -> None:
    pass


@pytest.mark.parametrize("name", sorted(SMALL))
def test_every_shipped_pipeline_runs(name, tmp_path):
    run = run_pipeline(PIPELINES / f"{name}.toml", out=tmp_path / name, say=quiet, overrides=SMALL[name])
    man = json.loads((run / "manifest.json").read_text())
    assert all(s["status"] == "completed" for s in man["stages"].values()), man["stages"]
    assert {"data", "fit", "evaluate", "report"} <= set(man["stages"])
    assert (run / "report.html").stat().st_size > 10_000 and (run / "metrics.json").exists()
    m = json.loads((run / "metrics.json").read_text())
    assert "rollout" in m
    if name == "car_on_hill":
        assert "car_on_hill_score" in m["named"]
    if name == "gridworld_divergence":
        assert (run / "figures" / "convergence.png").exists()


#: The driving pipeline at plumbing size (one log, 100 episodes; a few trees, iterations and
#: rollouts): what reuse is tested on (stages, not numbers).
TINY = {"data.inputs": ["../data/driving/exploration.mcap"], "fit.params.n_iterations": 2,
        "fit.params.regressor_params": {"n_estimators": 3}, "evaluate.episodes": 4,
        "evaluate.bootstrap": 0, "evaluate.fqe_bootstrap": 0, "evaluate.horizon": 5,
        "evaluate.fqe_params": {"n_iterations": 2, "regressor_params": {"n_estimators": 3}}}


def test_second_run_reuses_every_stage_and_metrics_are_identical(tmp_path):
    over = TINY
    run = run_pipeline(PIPELINES / "driving.toml", runs_root=tmp_path, say=quiet, overrides=over)
    first = (run / "metrics.json").read_bytes()
    again = run_pipeline(PIPELINES / "driving.toml", runs_root=tmp_path, say=quiet, overrides=over)
    assert again == run
    man = json.loads((run / "manifest.json").read_text())
    assert all(s["reused"] for s in man["stages"].values()) and man["runs"] == 2
    assert (run / "metrics.json").read_bytes() == first
    # a changed setting recomputes that stage and everything after it, nothing before
    over2 = {**over, "evaluate.episodes": over["evaluate.episodes"] + 1}
    run_pipeline(PIPELINES / "driving.toml", runs_root=tmp_path, say=quiet, overrides=over2)
    st = json.loads((run / "manifest.json").read_text())["stages"]
    assert st["data"]["reused"] and st["fit"]["reused"] and not st["evaluate"]["reused"] and not st["report"]["reused"]
    # same pipeline, seed and inputs in a fresh directory: the same metrics
    fresh = run_pipeline(PIPELINES / "driving.toml", out=tmp_path / "fresh", say=quiet, overrides=over)
    a = json.loads(first)
    b = json.loads((fresh / "metrics.json").read_text())
    for m in (a, b):
        m["dataset"].pop("path")
    assert a == b


def test_interrupted_fit_resumes_from_last_completed_stage(tmp_path, monkeypatch):
    over = {**SMALL["driving"], "fit.params.mode": "refit", "fit.params.n_iterations": 4,
            "fit.params.regressor_params": {"n_estimators": 5}}
    import offline_adp.runs as runs

    calls = {"n": 0}
    real = runs._write_checkpoint

    def crash_after_two(run, est, rows):
        real(run, est, rows)
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(runs, "_write_checkpoint", crash_after_two)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(PIPELINES / "driving.toml", out=tmp_path / "r", say=quiet, overrides=over)
    man = json.loads((tmp_path / "r" / "manifest.json").read_text())
    assert man["stages"]["data"]["status"] == "completed" and man["stages"]["fit"]["status"] == "interrupted"
    monkeypatch.setattr(runs, "_write_checkpoint", real)
    said: list[str] = []
    run_pipeline(PIPELINES / "driving.toml", out=tmp_path / "r", say=said.append, overrides=over)
    man = json.loads((tmp_path / "r" / "manifest.json").read_text())
    assert man["stages"]["data"]["reused"] and man["stages"]["fit"]["status"] == "completed"
    assert any("resuming from the last checkpointed iteration" in s for s in said)
    assert man["stages"]["fit"]["iterations"] == 4


def test_pipeline_errors_name_the_key(tmp_path):
    bad = tmp_path / "p.toml"
    bad.write_text('name = "x"\n[data]\nsimulate = "tabular"\nexplorations = 3\n[fit]\n')
    with pytest.raises(SpecError, match="explorations.*valid keys"):
        load_pipeline(bad)
    bad.write_text('[data]\nformat = "mcap"\ninputs = ["nothing/*.mcap"]\nspec = "s.toml"\n[fit]\n')
    with pytest.raises(SpecError, match="matches no file"):
        load_pipeline(bad)
    bad.write_text('[data]\nsimulate = "tabular"\n')
    with pytest.raises(SpecError, match=r"fit: missing required key"):
        load_pipeline(bad)
    assert main(["run", str(bad), "--out", str(tmp_path / "o")]) == 2


def test_unknown_override_is_refused(tmp_path):
    with pytest.raises(SpecError, match=r"not a pipeline setting \(did you mean 'evaluate.episodes'\?\)"):
        run_pipeline(PIPELINES / "driving.toml", out=tmp_path / "x", say=quiet, overrides={"evaluate.episode": 5})


def test_from_a_stage_with_nothing_to_reuse_says_so(tmp_path):
    """`run --from evaluate` in a directory without a previous run (e.g. after `make demo`, which
    writes under demo_out/) ran every stage saying only "running"; it says why now."""
    said: list[str] = []
    run_pipeline(PIPELINES / "driving.toml", out=tmp_path / "a", from_stage="evaluate", say=said.append,
                 overrides=TINY)
    first = [s for s in said if s.startswith("[data]")]
    assert first and "no completed data stage" in first[0] and "--from evaluate" in first[0]
    assert not any("nothing" in s or "no completed" in s for s in said if s.startswith(("[evaluate]", "[report]")))
    said.clear()  # again in the same directory: the stages before evaluate are reused, nothing to explain
    run_pipeline(PIPELINES / "driving.toml", out=tmp_path / "a", from_stage="evaluate", say=said.append,
                 overrides=TINY)
    assert "[data] reused (inputs, settings and code unchanged)" in said
    assert not any("no completed" in s for s in said)


def test_another_version_recomputes_every_stage_and_resumes_no_fit_of_the_old_one(tmp_path, monkeypatch):
    """A stage computed by another version of the library is not reused (its manifest would name
    the new version over the old code's numbers), and its fit's checkpoints are not resumed."""
    import offline_adp.artifacts as artifacts
    import offline_adp.runs as runs

    run = run_pipeline(PIPELINES / "driving.toml", out=tmp_path / "r", say=quiet, overrides=TINY)
    real = artifacts.versions()
    upgraded = {**real, "offline_adp": real["offline_adp"] + ".post1"}
    monkeypatch.setattr(artifacts, "versions", lambda: upgraded)
    monkeypatch.setattr(runs, "versions", lambda: upgraded)
    said: list[str] = []
    run_pipeline(PIPELINES / "driving.toml", out=run, say=said.append, overrides=TINY)
    man = json.loads((run / "manifest.json").read_text())
    assert man["versions"] == upgraded and not any(s["reused"] for s in man["stages"].values())
    assert not any("resuming" in s for s in said)
    assert json.loads((run / "fit" / "run.json").read_text())["versions"] == upgraded
    said.clear()
    run_pipeline(PIPELINES / "driving.toml", out=run, say=said.append, overrides=TINY)  # the same version again
    assert all(s["reused"] for s in json.loads((run / "manifest.json").read_text())["stages"].values())


def test_other_code_recomputes_every_stage(tmp_path, monkeypatch):
    """A local edit of the library (same version string) changes the code's fingerprint: nothing
    computed by the old code is reused (make demo printed the old evaluation as "reused" after one)."""
    import offline_adp.pipeline as pipeline

    run = run_pipeline(PIPELINES / "driving.toml", out=tmp_path / "r", say=quiet, overrides=TINY)
    assert json.loads((run / "manifest.json").read_text())["code"] == pipeline.code_fingerprint()
    monkeypatch.setattr(pipeline, "code_fingerprint", lambda: "0" * 64)
    said: list[str] = []
    run_pipeline(PIPELINES / "driving.toml", out=run, say=said.append, overrides=TINY)
    man = json.loads((run / "manifest.json").read_text())
    assert man["code"] == "0" * 64 and not any(s["reused"] for s in man["stages"].values())
    assert not any("resuming" in s for s in said)


def test_a_stage_whose_outputs_are_gone_is_recomputed(tmp_path):
    """The manifest alone decided reuse: a run killed while `--force` cleared it (fit/ gone,
    manifest.json still there), or a model deleted by hand, printed "[fit] reused" and left
    no fit (a crash audit). A stage is reused only with its outputs in place now."""
    import shutil

    run = run_pipeline(PIPELINES / "driving.toml", out=tmp_path / "r", say=quiet, overrides=TINY)
    shutil.rmtree(run / "fit" / "model")
    said: list[str] = []
    run_pipeline(PIPELINES / "driving.toml", out=run, say=said.append, overrides=TINY)
    assert "[data] reused (inputs, settings and code unchanged)" in said and "[fit] running" in said
    assert (run / "fit" / "model").is_dir() and "[evaluate] running" in said  # downstream of the fit, too
    (run / "report.html").unlink()
    said.clear()
    run_pipeline(PIPELINES / "driving.toml", out=run, say=said.append, overrides=TINY)
    assert "[evaluate] reused (inputs, settings and code unchanged)" in said and "[report] running" in said
    assert (run / "report.html").is_file()


def test_an_fqe_pipeline_reads_its_policy_relative_to_the_file_and_by_its_contents(tmp_path, monkeypatch):
    """`[fit.params] policy` was read from the current directory (run --help says paths are
    relative to the file), and only its path was in the fit's key: a policy replaced at the
    same path was "reused" with the old one's value (5.99 against a fresh 16.39; crash audit)."""
    import shutil

    from offline_adp.runs import fit_run
    from offline_adp.simulate import simulate

    simulate("gridworld", 3, 10, seed=0, horizon=30).save(tmp_path / "logs")
    for name, its in (("a", 1), ("b", 30)):
        fit_run(tmp_path / "logs", tmp_path / name,
                params={"n_iterations": its, "regressor_params": {"n_estimators": 3}})
    shutil.copytree(tmp_path / "a", tmp_path / "pol")
    (tmp_path / "pl").mkdir()
    (tmp_path / "pl" / "fqe.toml").write_text('name = "fqe"\n[data]\nsimulate = "gridworld"\ndemonstrations = 3\n'
                                              'exploration = 10\nhorizon = 30\n[fit]\nalgorithm = "fqe"\n'
                                              '[fit.params]\npolicy = "../pol/model"\nn_iterations = 30\n'
                                              'regressor_params = {n_estimators = 3}\n')
    monkeypatch.chdir(tmp_path)  # not the pipeline file's folder
    run = run_pipeline(tmp_path / "pl" / "fqe.toml", out=tmp_path / "r", say=quiet)
    first = json.loads((run / "fit" / "run.json").read_text())["value"]
    shutil.rmtree(tmp_path / "pol")
    shutil.copytree(tmp_path / "b", tmp_path / "pol")  # another policy at the same path
    said: list[str] = []
    run_pipeline(tmp_path / "pl" / "fqe.toml", out=run, say=said.append)
    assert "[data] reused (inputs, settings and code unchanged)" in said and "[fit] running" in said
    second = json.loads((run / "fit" / "run.json").read_text())["value"]
    # oracle: a fresh FQE of each policy on the run's data (the fits are deterministic)
    fresh = {}
    for name in ("a", "b"):
        fit_run(run / "dataset", tmp_path / f"f{name}", algorithm="fqe",
                params={"policy": str(tmp_path / name / "model"), "n_iterations": 30,
                        "regressor_params": {"n_estimators": 3}})
        fresh[name] = json.loads((tmp_path / f"f{name}" / "run.json").read_text())["value"]
    assert fresh["a"] != fresh["b"] and (first, second) == (fresh["a"], fresh["b"])
