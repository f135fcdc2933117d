"""``offline-adp evaluate --model-particles`` and a pipeline's ``[evaluate] model_particles``
reach the evaluation with one shared default, explicit counts pass through, and a count
that cannot give a Monte-Carlo interval (1, negative) is refused before anything runs."""

from __future__ import annotations

import pytest

from offline_adp import pipeline
from offline_adp.cli import main
from offline_adp.errors import OfflineADPError
from offline_adp.evaluation import MODEL_PARTICLES_DEFAULT
from offline_adp.evaluation.model_rollouts import N_PARTICLES
from tests.conftest import EvaluateRunCalled


@pytest.fixture
def captured(captured_evaluate_run):
    return captured_evaluate_run


def _pipeline(tmp_path, evaluate: str) -> dict:
    f = tmp_path / "p.toml"
    f.write_text('[data]\nsimulate = "gridworld"\n[fit]\n[evaluate]\n' + evaluate)
    return pipeline.load_pipeline(f)


def test_the_default_is_shared_and_explicit_counts_pass_through(tmp_path, captured):
    (tmp_path / "run" / "model").mkdir(parents=True)
    for cfg in (_pipeline(tmp_path, "episodes = 5\n"), _pipeline(tmp_path, "model_particles = 0\n"),
                _pipeline(tmp_path, "model_particles = 64\n")):
        with pytest.raises(EvaluateRunCalled):
            pipeline._evaluate_stage(cfg, tmp_path / "run", lambda _m: None)
    for extra in ([], ["--model-particles", "0"], ["--model-particles", "64"]):
        with pytest.raises(EvaluateRunCalled):
            main(["evaluate", str(tmp_path / "run"), "--quiet", *extra])
    got = [kw["model_particles"] for kw in captured]
    assert got == [MODEL_PARTICLES_DEFAULT, 0, 64] * 2
    assert MODEL_PARTICLES_DEFAULT == N_PARTICLES


@pytest.mark.parametrize("count", ["1", "-3", "many", "1000000000000"])
def test_the_cli_refuses_a_count_without_an_interval(tmp_path, captured, capsys, count):
    (tmp_path / "run" / "model").mkdir(parents=True)
    with pytest.raises(SystemExit) as e:
        main(["evaluate", str(tmp_path / "run"), "--model-particles", count])
    assert e.value.code == 2 and "--model-particles" in capsys.readouterr().err
    assert not captured


@pytest.mark.parametrize("count", [1, -3, 10**12])
def test_a_pipeline_refuses_a_count_without_an_interval(tmp_path, count):
    with pytest.raises(OfflineADPError, match="model_particles"):
        _pipeline(tmp_path, f"model_particles = {count}\n")


def test_compare_reuses_an_evaluation_only_with_the_same_model_rollouts():
    from offline_adp.evaluation.compare import _same_model_rollouts

    def m(mr, form="finite"):
        return {"estimand": {"form": form}, "ope": {"fqe": {} if mr is None else {"model_rollouts": mr}}}

    ran = m({"estimate": 1.0, "n_particles": 1000, "trust_radius": 0.5, "past_data_cost": 0.0})
    before_trust = m({"estimate": 1.0, "n_particles": 1000})  # bounds on the support radius: redone
    before_past = m({"estimate": 1.0, "n_particles": 1000, "trust_radius": 0.5})  # the model's interval not widened
    off = m({"skipped": "model_particles=0: model rollouts turned off"})
    lattice = m({"skipped": "the logged states repeat exactly (a lattice)"})
    assert _same_model_rollouts(ran, 1000) and not _same_model_rollouts(ran, 200) and not _same_model_rollouts(ran, 0)
    assert not _same_model_rollouts(before_trust, 1000) and not _same_model_rollouts(before_past, 1000)
    assert _same_model_rollouts(off, 0) and not _same_model_rollouts(off, 1000)
    assert _same_model_rollouts(lattice, 1000) and _same_model_rollouts(lattice, 0) is False
    assert not _same_model_rollouts(m(None), 1000)  # made before the model rollouts existed
    assert _same_model_rollouts(m(None, form="infinite"), 1000)  # that estimand runs none
