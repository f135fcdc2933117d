"""``offline-adp evaluate`` and a pipeline's ``[evaluate]`` ask for the same FQE bootstrap
replicates when none are given (one shared default), and that default runs the
replicate rule (the floor when replicates are cheap)."""

from __future__ import annotations

import pytest

from offline_adp import pipeline
from offline_adp.cli import main
from offline_adp.evaluation import FQE_BOOTSTRAP_DEFAULT
from offline_adp.evaluation.fqe_interval import (
    FQE_REPLICATE_FLOOR,
    FQE_REPLICATE_ROUGH,
    fqe_replicates,
)
from tests.conftest import EvaluateRunCalled


@pytest.fixture
def captured(captured_evaluate_run):
    return captured_evaluate_run


def test_pipeline_and_cli_default_fqe_bootstrap_agree(tmp_path, captured):
    cfg_file = tmp_path / "p.toml"
    cfg_file.write_text('[data]\nsimulate = "gridworld"\n[fit]\n[evaluate]\nepisodes = 5\n')
    cfg = pipeline.load_pipeline(cfg_file)
    assert "fqe_bootstrap" not in cfg["evaluate"]
    with pytest.raises(EvaluateRunCalled):
        pipeline._evaluate_stage(cfg, tmp_path / "run", lambda _m: None)
    (tmp_path / "run" / "model").mkdir(parents=True)
    with pytest.raises(EvaluateRunCalled):
        main(["evaluate", str(tmp_path / "run"), "--quiet"])
    from_pipeline, from_cli = (kw["n_boot_fqe"] for kw in captured)
    assert from_pipeline == from_cli == FQE_BOOTSTRAP_DEFAULT
    # what that default runs: the replicate floor when replicates are cheap (not 10, the old pipeline default)
    assert fqe_replicates(FQE_BOOTSTRAP_DEFAULT, cheap=True) == FQE_REPLICATE_FLOOR
    assert fqe_replicates(FQE_BOOTSTRAP_DEFAULT, cheap=False) == FQE_REPLICATE_ROUGH


def test_an_explicit_pipeline_fqe_bootstrap_is_passed_through(tmp_path, captured):
    cfg_file = tmp_path / "p.toml"
    cfg_file.write_text('[data]\nsimulate = "gridworld"\n[fit]\n[evaluate]\nfqe_bootstrap = 7\n')
    with pytest.raises(EvaluateRunCalled):
        pipeline._evaluate_stage(pipeline.load_pipeline(cfg_file), tmp_path / "run", lambda _m: None)
    assert captured[0]["n_boot_fqe"] == 7


def test_an_explicit_replicate_count_is_honoured_even_when_replicates_are_cheap():
    # `--set evaluate.fqe_bootstrap=2` used to run 200 (raised to the floor when cheap)
    assert fqe_replicates(2, cheap=True) == 2
    assert fqe_replicates(7, cheap=False) == 7
    assert fqe_replicates(0, cheap=True) == 0
