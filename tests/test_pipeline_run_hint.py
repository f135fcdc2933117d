"""A pipeline run directory (``offline-adp run``) holds its fitted run in ``fit/`` and its
metrics and report at the top; ``evaluate``, ``report`` and ``compare`` given the pipeline's
directory say where to look instead of sending the user in a loop ("run evaluate first" ->
"not a run directory")."""

import subprocess
import sys

import pytest

from offline_adp.data.rundir import pipeline_hint
from offline_adp.errors import RunDirectoryError


def _pipeline(tmp_path):
    p = tmp_path / "driving__0__20261128T000000"
    (p / "fit" / "model").mkdir(parents=True)
    (p / "manifest.json").write_text("{}")
    return p


def test_the_hint_names_the_fitted_run_only_for_a_pipeline_directory(tmp_path):
    p = _pipeline(tmp_path)
    hint = pipeline_hint(p)
    assert f"its fitted run is {p / 'fit'}" in hint and str(p / "report.html") in hint
    assert pipeline_hint(tmp_path) == ""  # no fit/model
    (tmp_path / "x" / "fit" / "model").mkdir(parents=True)
    assert pipeline_hint(tmp_path / "x") == ""  # fit/model but no manifest: not a pipeline's


def test_evaluate_report_and_compare_send_a_pipeline_directory_to_its_fit(tmp_path):
    from offline_adp.evaluation.compare import compare_runs
    from offline_adp.evaluation.report import build_report
    from offline_adp.evaluation.run import evaluate_run

    p = _pipeline(tmp_path)
    for call in (lambda: evaluate_run(p), lambda: build_report(p), lambda: compare_runs([p, p])):
        with pytest.raises(RunDirectoryError, match="pipeline run directory.*its fitted run is"):
            call()
    with pytest.raises(RunDirectoryError, match="fit one with `offline-adp fit`"):
        evaluate_run(tmp_path)  # not a pipeline's: the message it always had
    out = subprocess.run([sys.executable, "-m", "offline_adp", "report", str(p)], capture_output=True, text=True)
    assert out.returncode != 0 and "Traceback" not in out.stderr
    assert f"offline-adp report {p / 'fit'}" in out.stderr
