"""A hand-edited or damaged ``evaluation/metrics.json`` - a number as a string, a huge int,
an interval of one number, a stored headline whose entries are of the wrong kind, a key the
readers index removed - is one :class:`ArtifactError` naming the file and the key in
``report``, ``compare`` and the summary ``run`` prints, never a raw TypeError, KeyError,
IndexError or ValueError from deep inside a formatter (each case below escaped before the
structure of :mod:`offline_adp.evaluation.metrics_file` typed what they read).

Counts: CI runs ``N`` random edits; ``pytest --hypothesis-profile nightly`` runs more.
"""

from __future__ import annotations

import json
import shutil

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from offline_adp.cli import main
from offline_adp.errors import ArtifactError, OfflineADPError
from tests.fuzz_util import edit_json_path, gridworld_runs, json_paths, one_line_error

NIGHTLY = settings().max_examples >= 1000
N = 1000 if NIGHTLY else 30
class _Delete:
    """The key is removed (a stable repr: test ids must be the same in every xdist worker)."""

    def __repr__(self) -> str:
        return "DELETE"


DELETE = _Delete()


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    """A small gridworld log, two quick FQI fits, both evaluated from the logs."""
    return gridworld_runs(tmp_path_factory.mktemp("metrics"), evaluate=("a", "b"),
                          extra=("--fqe-bootstrap", "5", "--model-particles", "50"))


def _edited(evaluated, tmp_path, path, value):
    for name in ("a", "b"):
        shutil.copytree(evaluated / name, tmp_path / name)
    p = tmp_path / "a" / "evaluation" / "metrics.json"
    m = json.loads(p.read_text())
    edit_json_path(m, path, value, value is DELETE)
    p.write_text(json.dumps(m))
    return tmp_path / "a", tmp_path / "b", p


def _one_line_error(capsys, argv, key):
    return one_line_error(capsys, argv, "evaluation/metrics.json", key)


#: (key path, value): each escaped ``report`` and ``compare`` before (the error it was).
ESCAPES = [
    (("ope", "mis", "level"), "0.95"),  # ValueError: Unknown format code '%' for object of type 'str'
    (("ope", "mis", "interval"), [1.0]),  # IndexError: list index out of range
    (("ope", "fqe", "model_rollouts"), [1, 2, 3]),  # AttributeError: 'list' object has no attribute 'get'
    (("pooled_shift", "q99"), DELETE),  # KeyError: 'q99'
    (("behaviour_value", "mean"), DELETE),  # KeyError: 'mean'
    (("estimand", "possible_range"), [None, None]),  # TypeError: unsupported operand NoneType - float
    (("discount",), "1.5"),  # AttributeError: 'str' object has no attribute 'get'
    (("behaviour", "support_violations"), 1e308),  # AttributeError: 'float' object has no attribute 'get'
]

#: Escapes of ``compare`` only: it reads the stored headline's verdict (``report`` makes its own).
COMPARE_ESCAPES = [
    (("headline", "convergence", "verdict"), [1]),  # TypeError: unhashable type: 'list'
    (("headline", "convergence"), DELETE),  # KeyError: 'convergence'
    (("headline", "verdict"), 1),  # AttributeError: 'int' object has no attribute 'get'
]

#: Escapes of ``report`` only (what it shows unconditionally).
REPORT_ESCAPES = [
    (("cost_distribution", "policy_logs", "reason"), [1]),  # AttributeError: no attribute 'split'
    (("cost_distribution", "behaviour_logged"), True),  # AttributeError: 'bool' object has no attribute 'get'
    (("cost_distribution", "behaviour_logged", "quantiles", "values", 2), []),  # ValueError: inhomogeneous shape
    (("dataset", "sources"), True),  # AttributeError: 'bool' object has no attribute 'items'
    (("behaviour", "support_violations", "threshold"), None),  # TypeError: NoneType.__format__
    (("behaviour", "clip"), "0.001"),  # ValueError: Unknown format code 'g' for object of type 'str'
]

#: Escapes of the summary ``run`` prints from a stored metrics.json (its stored headline).
SUMMARY_ESCAPES = [
    (("headline", "ranking", 0, "name"), 0),  # AttributeError: 'int' object has no attribute 'upper'
    (("headline", "ranking", 0), True),  # TypeError: 'bool' object is not subscriptable
    (("headline", "verdict"), 1),  # TypeError: 'int' object is not subscriptable
    (("headline", "outcome"), "great"),  # KeyError: 'great' (its colour)
]


def _key(path):
    return "".join(f"[{x}]" if isinstance(x, int) else f".{x}" for x in path)[1:]


@pytest.mark.parametrize(("path", "value"), ESCAPES + COMPARE_ESCAPES, ids=lambda x: repr(x)[:40])
def test_compare_with_a_malformed_metrics_json_exits_2_naming_the_key(evaluated, tmp_path, capsys, path, value):
    a, b, _ = _edited(evaluated, tmp_path, path, value)
    _one_line_error(capsys, ["compare", str(a), str(b), "--simulator", "none", "--model-particles", "50", "--quiet"],
                    _key(path))


@pytest.mark.parametrize(("path", "value"), ESCAPES + REPORT_ESCAPES, ids=lambda x: repr(x)[:40])
def test_report_with_a_malformed_metrics_json_exits_2_naming_the_key(evaluated, tmp_path, capsys, path, value):
    a, _, _ = _edited(evaluated, tmp_path, path, value)
    _one_line_error(capsys, ["report", str(a)], _key(path))
    assert not (a / "report").exists()


@pytest.mark.parametrize(("path", "value"), SUMMARY_ESCAPES, ids=lambda x: repr(x)[:40])
def test_run_summary_of_a_malformed_metrics_json_is_our_error(evaluated, tmp_path, path, value):
    """``offline-adp run`` prints ``summary_lines(read_metrics(RUN/metrics.json))``."""
    from offline_adp.evaluation.summary import read_metrics, summary_lines

    _, _, p = _edited(evaluated, tmp_path, path, value)
    with pytest.raises(ArtifactError, match="metrics.json: " + _key(path).replace("[", r"\[").replace("]", r"\]")):
        summary_lines(read_metrics(p), colour=True)


def test_the_files_evaluate_writes_still_read(evaluated, tmp_path, capsys):
    """The gridworld logs-only metrics.json this version writes reads as it is, and makes a report (the
    other variants, with a simulator, continuous commands, gym, are read by the report and compare tests)."""
    from offline_adp.evaluation.metrics_file import ReportMetricsFile, read_metrics

    p = evaluated / "a" / "evaluation" / "metrics.json"
    assert read_metrics(p, ReportMetricsFile) == json.loads(p.read_text())
    a, _, _ = _edited(evaluated, tmp_path, ("ope", "fqe", "estimate"), 3)  # an int where a float is read: fine
    assert main(["report", str(a)]) == 0, capsys.readouterr().err


def test_a_huge_int_estimate_is_read_as_a_number(evaluated, tmp_path, capsys):
    """An estimate of 10**30 (an int) raised TypeError from numpy's isfinite in compare: now a number."""
    a, b, _ = _edited(evaluated, tmp_path, ("ope", "is", "estimate"), 10**30)
    code = main(["compare", str(a), str(b), "--simulator", "none", "--model-particles", "50", "--quiet"])
    assert code == 0, capsys.readouterr().err


def test_finite_number_takes_huge_ints_and_refuses_bools():
    from offline_adp.evaluation.verdict import _is_finite_number

    assert _is_finite_number(10**30) and not _is_finite_number(10**400)
    assert not _is_finite_number(True) and not _is_finite_number("1.5") and not _is_finite_number(float("nan"))


VALUES = [None, "x", "1.5", -1, 0, 1, True, 1e308, 10**30, 10**400, [], {}, [1], [1, 2, 3], ["a", "b"], {"a": 1},
          [None, None], float("nan"), float("inf"), DELETE]


@settings(max_examples=N, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(pick=st.integers(0, 10**6), value=st.sampled_from(VALUES), keep_headline=st.booleans())
def test_fuzz_metrics_json_readers(evaluated, tmp_path, pick, value, keep_headline):
    """Any one edit of a real metrics.json: the readers of ``run``'s summary and ``compare``'s
    rows work, or refuse it with our error naming the file."""
    from offline_adp.evaluation.compare import _candidate_row, compare_lines
    from offline_adp.evaluation.summary import rank_estimators, read_metrics, summary_lines, withdraw_levels

    p = tmp_path / "metrics.json"
    m = json.loads((evaluated / "a" / "evaluation" / "metrics.json").read_text())
    if not keep_headline:
        del m["headline"]
    paths = [q for q in json_paths(m, max_items=6) if q and q[0] != "warnings"]
    path = paths[pick % len(paths)]
    edit_json_path(m, path, value, value is DELETE)
    p.write_text(json.dumps(m))
    try:
        got = read_metrics(p)
    except ArtifactError as exc:
        assert str(p) in str(exc)
        return
    try:
        summary_lines(got, colour=True)
        row = _candidate_row(evaluated / "a", got, rank_estimators(withdraw_levels(got)), None)
        compare_lines({"dataset": {"path": "ds"}, "estimator": "fqe", "estimand": "x",
                       "candidates": [{**row, "rank": 1}]})
    except OfflineADPError:
        pass


@pytest.mark.parametrize("tol", ["x", [1], True])
def test_report_with_a_malformed_tol_in_config_json_exits_2(evaluated, tmp_path, capsys, tol):
    """A run.json without the fit's verdict sends the report to config.json's params.tol:
    a tol that is not a number was a ValueError / TypeError from float()."""
    a, _, _ = _edited(evaluated, tmp_path, ("ope",), json.loads((evaluated / "a" / "evaluation" / "metrics.json")
                                                                 .read_text())["ope"])
    info = json.loads((a / "run.json").read_text())
    info.pop("verdict", None)
    (a / "run.json").write_text(json.dumps(info))
    cfg = json.loads((a / "config.json").read_text())
    cfg.setdefault("params", {})["tol"] = tol
    (a / "config.json").write_text(json.dumps(cfg))
    code = main(["report", str(a)])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and "config.json: params.tol" in err, err


def test_a_malformed_tol_is_not_read_where_run_json_has_the_verdict(evaluated, tmp_path, capsys):
    """tol is read only for runs whose run.json lacks the fit's verdict: with the verdict, a
    hand-edited tol is never looked at and the report is made."""
    a, _, _ = _edited(evaluated, tmp_path, ("ope",), json.loads((evaluated / "a" / "evaluation" / "metrics.json")
                                                                 .read_text())["ope"])
    assert json.loads((a / "run.json").read_text()).get("verdict")
    cfg = json.loads((a / "config.json").read_text())
    cfg.setdefault("params", {})["tol"] = "x"
    (a / "config.json").write_text(json.dumps(cfg))
    assert main(["report", str(a)]) == 0, capsys.readouterr().err
