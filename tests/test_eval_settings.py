"""Issue 43: one typed model of the evaluation's settings
(:class:`offline_adp.evaluation.settings.EvaluationSettings`) serves the CLI flags of
``evaluate`` and ``compare``, a pipeline's ``[evaluate]`` table, the JSON Schema and the
Python API, with each setting's bounds in it.

For every declared setting a bad value is derived from the model's own declaration (past
a bound, a string no ``Literal`` holds, an unknown FQE parameter): ``evaluate``,
``compare`` and ``run`` must exit with status 2 and one line naming the key, no
traceback, before any work. Then each hostile case of the issue, one test each."""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
import typing
from pathlib import Path
from typing import Any

import pytest

from offline_adp import pipeline
from offline_adp.cli import main
from offline_adp.errors import InvalidArgumentError, SpecError
from offline_adp.evaluation.settings import EvaluationOptions, EvaluationSettings, flag
from offline_adp.schemas import schemas

ROOT = Path(__file__).resolve().parents[1]


def bad_values(name: str) -> list[Any]:
    """Values the declaration of setting ``name`` refuses, derived from it."""
    field = EvaluationSettings.model_fields[name]
    ge = next((m.ge for m in field.metadata if hasattr(m, "ge")), None)
    le = next((m.le for m in field.metadata if hasattr(m, "le")), None)
    if ge is not None or le is not None:
        out = [v for v in (None if ge is None else ge - 1, None if le is None else le + 1) if v is not None]
        if (field.json_schema_extra or {}).get("not") == {"const": 1}:
            out.append(1)
        return out
    options = [a for a in typing.get_args(field.annotation)]
    if options and all(isinstance(a, str) for a in options):  # a Literal
        return ["not-an-option"]
    if name == "fqe_params":
        return [{"not_a_parameter": 1}]
    if name == "simulator":
        return ["not-a-simulator"]
    raise AssertionError(f"no bad value derived for {name}: declare its bounds in the settings model")


CASES = [(name, v) for name in EvaluationSettings.model_fields for v in bad_values(name)]


def _text(value: Any) -> str:
    return json.dumps(value) if isinstance(value, dict) else str(value)


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _exit_code(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as exc:  # a refused flag: argparse's exit 2, one line
        return int(exc.code)


@pytest.fixture
def captured(captured_evaluate_run):
    return captured_evaluate_run


def test_every_setting_has_bounds_and_the_cli_pipeline_and_schema_share_them():
    assert set(EvaluationSettings.model_fields) == set(EvaluationOptions.model_fields) | {"seed"}
    ev = schemas()["pipeline"]["$defs"]["EvaluationOptions"]["properties"]
    assert set(ev) == set(EvaluationOptions.model_fields)
    parser_flags = {a.option_strings[0] for a in _subparser("evaluate")._actions if a.option_strings}
    assert {flag(n) for n in EvaluationSettings.model_fields} <= parser_flags
    assert {flag(n) for n in EvaluationSettings.model_fields} <= {
        a.option_strings[0] for a in _subparser("compare")._actions if a.option_strings}
    # the pipeline's seed has the settings' bounds
    top = schemas()["pipeline"]["properties"]["seed"]
    sf = EvaluationSettings.model_json_schema()["properties"]["seed"]
    assert (top["minimum"], top["maximum"]) == (sf["minimum"], sf["maximum"])


def _subparser(name: str):
    from offline_adp.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return sub.choices[name]


@pytest.mark.parametrize("name, value", CASES)
def test_evaluate_refuses_each_bad_setting_in_one_line(tmp_path, capsys, captured, name, value):
    (tmp_path / "run" / "model").mkdir(parents=True)
    code = _exit_code(["evaluate", str(tmp_path / "run"), f"{flag(name)}={_text(value)}"])
    assert code == 2
    assert flag(name) in _one_line(capsys.readouterr().err)
    assert not captured  # nothing ran


@pytest.mark.parametrize("name, value", CASES)
def test_compare_refuses_each_bad_setting_in_one_line(tmp_path, capsys, captured, name, value):
    for r in ("a", "b"):
        (tmp_path / r / "model").mkdir(parents=True)
    code = _exit_code(["compare", str(tmp_path / "a"), str(tmp_path / "b"), f"{flag(name)}={_text(value)}"])
    assert code == 2
    assert flag(name) in _one_line(capsys.readouterr().err)
    assert not captured


def _toml(value: Any) -> str:
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + "}"
    return json.dumps(value)


@pytest.mark.parametrize("name, value", CASES)
def test_a_pipeline_refuses_each_bad_setting_in_one_line(tmp_path, capsys, captured, name, value):
    f = tmp_path / "p.toml"
    if name == "seed":  # a pipeline's one seed, with the settings' bounds
        f.write_text(f'seed = {_toml(value)}\n[data]\nsimulate = "gridworld"\n[fit]\n[evaluate]\n')
        key = "seed"
    else:
        f.write_text(f'[data]\nsimulate = "gridworld"\n[fit]\n[evaluate]\n{name} = {_toml(value)}\n')
        key = f"evaluate.{name}"
    assert main(["run", str(f), "--out", str(tmp_path / "out"), "-q"]) == 2
    assert key in _one_line(capsys.readouterr().err)
    assert not (tmp_path / "out").exists() and not captured
    if name != "seed":  # the same through --set
        good = tmp_path / "good.toml"
        good.write_text('[data]\nsimulate = "gridworld"\n[fit]\n[evaluate]\n')
        assert main(["run", str(good), "--out", str(tmp_path / "out"), "-q", "--set",
                     f"{key}={json.dumps(value)}"]) == 2
        assert key in _one_line(capsys.readouterr().err)
        assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name, value", CASES)
def test_the_python_api_refuses_each_bad_setting(name, value):
    with pytest.raises(InvalidArgumentError, match=name):
        EvaluationSettings.resolve(None, {name: value})


def test_the_api_reads_the_former_keyword_names_and_refuses_unknown_ones():
    s = EvaluationSettings.resolve(None, {"n_episodes": 7, "n_boot": 0, "n_boot_fqe": 2})
    assert (s.episodes, s.bootstrap, s.fqe_bootstrap) == (7, 0, 2)
    assert EvaluationSettings.resolve(s) is s
    with pytest.raises(InvalidArgumentError, match="n_episodez: not an evaluation setting"):
        EvaluationSettings.resolve(None, {"n_episodez": 7})
    with pytest.raises(InvalidArgumentError, match="given twice"):
        EvaluationSettings.resolve(None, {"n_boot": 2, "bootstrap": 3})
    import numpy as np

    assert EvaluationSettings.resolve(None, {"horizon": np.int64(5)}).horizon == 5  # an array's integer
    with pytest.raises(InvalidArgumentError, match="episodes"):
        EvaluationSettings.resolve(None, {"episodes": "5"})  # strict: no strings for numbers
    with pytest.raises(InvalidArgumentError, match="episodes"):
        EvaluationSettings.resolve(None, {"episodes": True})


def test_the_defaults_are_the_ones_the_cli_pipeline_and_api_had():
    from offline_adp.evaluation import FQE_BOOTSTRAP_DEFAULT, MODEL_PARTICLES_DEFAULT

    s = EvaluationSettings()
    assert (s.simulator, s.episodes, s.bootstrap, s.fqe_bootstrap, s.fqe_params, s.horizon, s.estimand, s.seed,
            s.model_particles) == (None, 500, 200, FQE_BOOTSTRAP_DEFAULT, None, None, "finite", 0,
                                   MODEL_PARTICLES_DEFAULT)


# ---------------------------------------------------------------------------- the hostile cases
def _limited() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))  # far below the 3.8 / 5.3 GB they reached


def _cli(*argv: str, cwd: Path | None = None) -> tuple[int, str, float]:
    """The CLI in a child with 3 GB of address space and 120 s: (status, stderr, seconds)."""
    t0 = time.perf_counter()
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    r = subprocess.run([sys.executable, "-m", "offline_adp", *argv], capture_output=True, text=True, timeout=120,
                       preexec_fn=_limited, env=env, cwd=cwd)
    return r.returncode, r.stderr, time.perf_counter() - t0


@pytest.mark.parametrize("argv, said", [
    (["--bootstrap", "1000000000000"], "--bootstrap: expected 0 or an integer from 2 up to 1,000,000"),
    (["--fqe-bootstrap", "1000000000000"], "--fqe-bootstrap: expected 0 or an integer from 2 up to 100,000"),
    (["--seed", "-1"], "--seed: expected a non-negative integer up to 2,147,483,647, got -1"),
    (["--seed", "100000000000000000000000"], "--seed: expected a non-negative integer up to 2,147,483,647"),
    (["--bootstrap", "-5"], "--bootstrap: expected 0 or an integer from 2 up to 1,000,000, got -5"),
])
def test_hostile_evaluate_settings_exit_2_in_one_line_at_once(tmp_path, argv, said):
    (tmp_path / "run" / "model").mkdir(parents=True)
    code, err, seconds = _cli("evaluate", str(tmp_path / "run"), *argv)
    assert code == 2 and said in _one_line(err) and seconds < 60


def test_fqe_params_nested_20000_deep(tmp_path, capsys, captured):
    (tmp_path / "run" / "model").mkdir(parents=True)
    deep = '{"a": ' * 20_000 + "1" + "}" * 20_000
    assert _exit_code(["evaluate", str(tmp_path / "run"), "--fqe-params", deep]) == 2
    assert "--fqe-params: JSON nested deeper than 64 levels" in _one_line(capsys.readouterr().err)
    assert not captured
    with pytest.raises(InvalidArgumentError, match="fqe_params"):  # the API too, however it is built
        EvaluationSettings.resolve(None,
                                   {"fqe_params": {"regressor_params": json.loads('{"a": ' * 100 + "1" + "}" * 100)}})


def _metrics_run(tmp_path: Path, text: str) -> Path:
    run = tmp_path / "run"
    (run / "model").mkdir(parents=True)
    (run / "evaluation").mkdir()
    (run / "evaluation" / "metrics.json").write_text(text)
    return run


def test_report_of_a_metrics_json_nested_200000_deep(tmp_path, capsys):
    run = _metrics_run(tmp_path, '{"ope": ' + "[" * 200_000 + "]" * 200_000 + "}")
    assert main(["report", str(run)]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "metrics.json: JSON nested deeper than 64 levels" in line


def test_report_of_a_metrics_json_whose_ope_is_nonsense(tmp_path, capsys):
    run = _metrics_run(tmp_path, json.dumps({"ope": "nonsense"}))
    assert main(["report", str(run)]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "metrics.json: ope:" in line and "not a metrics.json this version reads" in line


def test_compare_and_run_read_metrics_json_through_the_same_gate(tmp_path):
    from offline_adp.errors import ArtifactError
    from offline_adp.evaluation.compare import _metrics

    run = _metrics_run(tmp_path, json.dumps({"ope": {"fqe": {"estimate": "cheap"}}}))
    with pytest.raises(ArtifactError, match=r"ope\.fqe\.estimate"):
        _metrics(run)


def test_a_json_file_that_is_a_device_is_refused_without_reading(tmp_path):
    from offline_adp.data.files import read_json_file
    from offline_adp.errors import ArtifactError

    with pytest.raises(ArtifactError, match="not a regular file"):
        read_json_file("/dev/zero")


def test_a_pipeline_whose_inputs_name_dev_zero(tmp_path):
    f = tmp_path / "p.toml"
    f.write_text('[data]\nformat = "parquet"\ninputs = ["/dev/zero"]\nspec = "spec.toml"\n[fit]\n')
    code, err, seconds = _cli("run", str(f), "--out", str(tmp_path / "out"), "-q")
    assert code == 2 and seconds < 60
    assert "[data] inputs '/dev/zero': /dev/zero is a device, pipe or socket, not a regular file" in _one_line(err)
    with pytest.raises(SpecError, match="not a regular file"):
        pipeline.load_pipeline(f)


def test_convert_dev_zero_from_d4rl(tmp_path):
    code, err, seconds = _cli("convert", "/dev/zero", "--from", "d4rl", "--out", str(tmp_path / "out"))
    assert code == 2 and seconds < 60
    assert "/dev/zero: not a regular file" in _one_line(err)
    assert not (tmp_path / "out").exists()


def test_set_on_a_data_key_the_pipeline_does_not_read_warns(tmp_path):
    f = tmp_path / "p.toml"
    f.write_text('[data]\nsimulate = "gridworld"\n[fit]\n')
    with pytest.warns(UserWarning, match=r"--set data\.spec: unused, ignored: .*simulate = 'gridworld'"):
        pipeline.load_pipeline(f, {"data.spec": "specs/x.toml"})
    import warnings

    with warnings.catch_warnings():  # a key the source reads: no warning
        warnings.simplefilter("error")
        pipeline.load_pipeline(f, {"data.exploration": 3})


def test_the_cli_reports_the_unused_key_warning(tmp_path, capsys, monkeypatch):
    """Through ``run``: the warning is reported once (here the run stops after loading)."""
    f = tmp_path / "p.toml"
    f.write_text('[data]\nsimulate = "gridworld"\n[fit]\n')

    def stop(*_a, **_k):
        raise SpecError("stopped after loading")

    monkeypatch.setattr(pipeline, "RunDirectory", stop)
    assert main(["run", str(f), "--out", str(tmp_path / "out"), "--set", "data.spec=x.toml"]) == 2
    err = capsys.readouterr().err
    assert "--set data.spec: unused, ignored" in err and "Traceback" not in err

