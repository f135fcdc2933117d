"""The one configuration layer: pipeline files and fit configs are checked, values included,
before any stage runs or any directory is created; errors name the file and key."""

from __future__ import annotations

import inspect
import json
from typing import Any

import pytest

from offline_adp.algorithms.registry import ALGORITHMS, get_algorithm
from offline_adp.cli import ALGORITHM_NAMES, main
from offline_adp.config import load_toml
from offline_adp.errors import SpecError, UnknownNameError
from offline_adp.pipeline import load_pipeline, run_pipeline

GOOD = ('name = "p"\nseed = 0\n[data]\nsimulate = "tabular"\nexploration = 3\ndemonstrations = 0\n'
        '[fit]\nalgorithm = "fqi"\n')


def _pipeline(tmp_path, text, name="p.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize(("text", "match"), [
    (GOOD.replace("seed = 0", 'seed = "zero"'), r"seed: Input should be a valid integer"),
    (GOOD.replace('name = "p"', 'name = "*"'), r"name: String should match pattern"),
    (GOOD.replace('name = "p"', 'name = "../../x"'), r"name: String should match pattern"),
    (GOOD.replace('name = "p"', 'name = "/tmp/x"'), r"name: String should match pattern"),
    (GOOD.replace('algorithm = "fqi"', 'algorithm = "fqx"'),
     r"fit.algorithm: expected one of 'fqi', 'fqe', 'api', 'cpi'"),
    (GOOD + "[fit.params]\nn_iteratons = 3\n",
     r"fit.params.n_iteratons: unknown key \(did you mean 'n_iterations'\?\)"),
    (GOOD + '[fit.params]\nmode = "fast"\n', r"fit.params.mode must be a str among"),
    (GOOD + '[fit.params]\nn_iterations = "ten"\n',
     r"fit.params.n_iterations must be an int in the range \[1, inf\) or a str among \{'auto'\}"),
    (GOOD + '[evaluate]\nsimulator = "path_trackin"\n', r"simulator = 'path_trackin': known simulators are"),
    (GOOD + "[evaluate]\nepisodes = 0\n", r"evaluate.episodes: Input should be greater than or equal to 2"),
    (GOOD.replace('simulate = "tabular"', 'simulate = "tabulr"'), r"simulate = 'tabulr': known problems"),
    (GOOD + '[engine]\nkind = "spark"\n', r"engine.kind: expected one of 'local' or 'dask'"),
    ('name = "p"\n[data]\nsimulate = "tabular"\n', r"fit: missing required key"),
    # lax pydantic would read true as 1 / 1.0: n_structures = true ran as 1 build, a bool
    # structure_max_samples was accepted here and failed inside the fit with a traceback
    (GOOD + "[fit.params]\nn_structures = true\n", r"fit.params.n_structures: .*a bool \(true\) is not a valid value"),
    (GOOD + "[fit.params]\nstructure_max_samples = true\n", r"fit.params.structure_max_samples: .*a bool \(true\)"),
    (GOOD + "[fit.params]\ngamma = false\n", r"fit.params.gamma: .*a bool \(false\)"),
    (GOOD + "[fit.params]\nstructure_max_samples = [0.5, true]\n",
     r"fit.params.structure_max_samples: .*a bool \(true\)"),
])
def test_pipeline_file_is_checked_before_anything_runs(tmp_path, text, match):
    p = _pipeline(tmp_path, text)
    with pytest.raises(SpecError, match=match) as err:
        load_pipeline(p)
    assert str(p) in str(err.value)
    runs = tmp_path / "runs"
    assert main(["run", str(p), "--runs", str(runs), "-q"]) == 2
    assert not runs.exists(), "a bad pipeline must not create its run directory"


def test_bool_fields_still_take_bools(tmp_path):
    # fqi's on_divergence is a string, per_action flags etc. are bools: a bool field keeps working
    from offline_adp.config import ConfigModel, validate_config

    class M(ConfigModel):
        flag: bool = False
        either: int | bool = 0
        number: float = 0.0
        flags: tuple[bool, ...] = ()
        numbers: list[float | list[float]] = []
        params: dict[str, Any] = {}
        anything: list = []

    m = validate_config(M, {"flag": True, "either": True, "number": 1, "flags": [True, False],
                            "params": {"bootstrap": True},
                             "anything": [True]}, "x.toml", "s")
    assert m.flag is True and m.either is True and m.flags == (True, False) and m.params == {"bootstrap": True}
    with pytest.raises(SpecError, match=r"s.number: .*a bool"):
        validate_config(M, {"number": True}, "x.toml", "s")
    with pytest.raises(SpecError, match=r"s.numbers: .*a bool \(false\)"):
        validate_config(M, {"numbers": [1.0, [2.0, False]]}, "x.toml", "s")


def test_pipeline_name_from_a_file_name_is_checked(tmp_path):
    p = _pipeline(tmp_path, GOOD.replace('name = "p"\n', ""), name="bad name*.toml")
    with pytest.raises(Exception, match="is not allowed"):
        load_pipeline(p)


def test_non_utf8_and_bad_toml_name_the_file(tmp_path):
    p = tmp_path / "p.toml"
    p.write_bytes(GOOD.encode() + b'description = "\xff"\n')
    with pytest.raises(SpecError, match=r"line 9: not UTF-8"):
        load_toml(p, "pipeline")
    p.write_text("[data\n")
    with pytest.raises(SpecError, match="not valid TOML"):
        load_pipeline(p)


def test_fit_config_errors_leave_nothing_behind(tmp_path, small_pt):
    ds = tmp_path / "ds"
    small_pt.save(ds)
    for body, match in (('mode = "fast"\n', "mode must be a str among"), ('n_iterations = "ten"\n', "valid integer"),
                        ("gama = 0.9\n", "did you mean 'gamma'")):
        cfg = tmp_path / "fqi.toml"
        cfg.write_text("[fqi]\n" + body)
        out = tmp_path / "run"
        assert main(["fit", str(ds), "--config", str(cfg), "--out", str(out), "-q"]) == 2
        assert not out.exists(), match
    # the corrected retry is not refused
    cfg.write_text("[fqi]\nn_iterations = 2\n[fqi.regressor_params]\nn_estimators = 3\n")
    assert main(["fit", str(ds), "--config", str(cfg), "--out", str(tmp_path / "run"), "-q"]) == 0


def test_resume_without_config_is_a_clear_error(tmp_path, small_pt, capsys):
    ds = tmp_path / "ds"
    small_pt.save(ds)
    (tmp_path / "run").mkdir()
    assert main(["fit", str(ds), "--out", str(tmp_path / "run"), "--resume", "-q"]) == 2
    assert "has no config.json" in capsys.readouterr().err


def test_registry_is_the_one_list_of_algorithms():
    assert tuple(ALGORITHMS) == ALGORITHM_NAMES
    with pytest.raises(UnknownNameError, match="known: \\['fqi'"):
        get_algorithm("fqx")
    for entry in ALGORITHMS.values():  # the config model is the constructor's signature, minus objects, plus extras
        cls = entry.estimator_class()
        params = set(inspect.signature(cls.__init__).parameters) - {"self"}
        fields = set(entry.params_model().model_fields)
        assert fields - set(entry.extra) <= params
        assert params - fields <= set(entry.exclude), (entry.name, params - fields)


def test_published_json_schemas_are_current():
    from offline_adp.schemas import SCHEMA_DIR, schemas

    for name, schema in schemas().items():
        path = SCHEMA_DIR / f"{name}.schema.json"
        assert path.exists(), f"run `offline-adp schema --write` ({path} missing)"
        assert json.loads(path.read_text()) == schema, f"run `offline-adp schema --write` ({path} is stale)"


def test_unknown_override_names_the_settings(tmp_path):
    p = _pipeline(tmp_path, GOOD)
    with pytest.raises(SpecError, match="not a pipeline setting"):
        run_pipeline(p, out=tmp_path / "x", say=lambda s: None, overrides={"evaluate.episode": 5})
    with pytest.raises(SpecError, match="data.exploration: Input should be greater than or equal to 0"):
        run_pipeline(p, out=tmp_path / "x", say=lambda s: None, overrides={"data.exploration": -1})
    assert not (tmp_path / "x").exists()
