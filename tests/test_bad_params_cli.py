"""``offline-adp fit`` refuses every bad parameter value up front, for every algorithm.

For each algorithm of the registry and each of its configurable parameters, a bad value
is derived from the estimator's own declaration (``_parameter_constraints``: below an
``Interval``, a string no ``StrOptions`` holds, a wrong type). The fit must exit with
status 2, print one line naming the parameter, and write nothing, so that the retry
with a corrected configuration is accepted (run once per algorithm, with its iterations
capped, to keep the module fast).
"""

from __future__ import annotations

import json
import math
from numbers import Integral
from pathlib import Path
from typing import Any

import pytest
from sklearn.utils._param_validation import HasMethods, Interval, StrOptions

from offline_adp.algorithms.registry import ALGORITHMS
from offline_adp.cli import main

#: a bad value for a constraint list that no member accepts (None: no value derived)
_NOT_AN_OPTION = "not-an-option"


def bad_value(constraints: list[Any]) -> Any:
    """A value every constraint of ``constraints`` refuses, derived from them."""
    if any(isinstance(c, StrOptions) for c in constraints) or all(
            isinstance(c, HasMethods | type) or c is None or c == "boolean" for c in constraints):
        candidate: Any = _NOT_AN_OPTION  # a string no option holds, or the wrong type
    else:
        iv = next(c for c in constraints if isinstance(c, Interval))
        if iv.left is not None:
            candidate = iv.left - 1
        elif iv.right is not None:
            candidate = iv.right + 1
        else:
            candidate = math.inf  # an unbounded Interval still refuses infinity
        if iv.type is not Integral:
            candidate = float(candidate)
    assert not any(_accepts(c, candidate) for c in constraints), (constraints, candidate)
    return candidate


def _accepts(constraint: Any, value: Any) -> bool:
    from sklearn.utils._param_validation import make_constraint

    return make_constraint(constraint).is_satisfied_by(value)


def _toml(value: Any) -> str:
    if isinstance(value, float) and math.isinf(value):
        return "inf" if value > 0 else "-inf"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + "}"
    return json.dumps(value)


def _cases() -> list[tuple[str, str, Any]]:
    """(algorithm, parameter, bad value) for every configurable, constrained parameter."""
    out = []
    for name, entry in ALGORITHMS.items():
        constraints = entry.estimator_class()._parameter_constraints
        for key in entry.params_model().model_fields:
            if key in constraints and key not in entry.extra:  # extra keys are paths and names, not parameters
                out.append((name, key, bad_value(constraints[key])))
    return out


CASES = _cases()
#: the first case of each algorithm also runs the corrected retry
RETRY = {name: next(c for c in CASES if c[0] == name) for name in ALGORITHMS}


def _fast(name: str, fields: dict[str, Any], policy: Path) -> dict[str, Any]:
    """Settings that make a fit of ``name`` quick on the tiny dataset (derived from the
    configuration model's fields, not listed per algorithm), plus the keys a run needs."""
    trees = {"n_estimators": 2, "n_jobs": 1}
    caps = {"n_iterations": 1, "horizon": 2, "n_samples": 8, "n_rollouts": 1, "n_eval_episodes": 2,
            "regressor_params": trees, "learner_params": trees, "fqe": {"n_iterations": 1, "regressor_params": trees}}
    # what a run needs: a saved policy (the fixture's) and a simulator for the dataset's problem
    needs = {"policy": str(policy), "simulator": "tabular"}
    out = {k: v for k, v in caps.items() if k in fields}
    out.update({k: needs[k] for k in ALGORITHMS[name].required})
    return out


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    ds = tmp_path_factory.mktemp("data") / "ds"
    assert main(["simulate", "tabular", "--out", str(ds), "--demonstrations", "2", "--exploration", "2", "-q"]) == 0
    return ds


@pytest.fixture(scope="module")
def policy(tmp_path_factory, dataset) -> Path:
    """A saved FQI policy for the algorithms that evaluate or improve one (made here, not
    by another test: under xdist the tests of this module may run in any order and process)."""
    out = tmp_path_factory.mktemp("policy") / "run"
    fields = ALGORITHMS["fqi"].params_model().model_fields
    cfg = _write(out.parent / "fqi.toml", "fqi", _fast("fqi", fields, out / "model"))
    assert main(["fit", str(dataset), "--algorithm", "fqi", "--config", str(cfg), "--out", str(out), "-q"]) == 0
    return out / "model"


def _write(path: Path, name: str, params: dict[str, Any]) -> Path:
    path.write_text(f"[{name}]\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in params.items()))
    return path


def test_every_constrained_parameter_has_a_case():
    names = {c[0] for c in CASES}
    assert names == set(ALGORITHMS)
    assert {"mode", "n_iterations", "gamma", "regressor"} <= {c[1] for c in CASES if c[0] == "fqi"}
    assert ("cpi", "step_rule", _NOT_AN_OPTION) in CASES and ("api", "n_iterations", 0) in CASES


@pytest.mark.parametrize(("name", "key", "value"), CASES, ids=[f"{n}.{k}" for n, k, _ in CASES])
def test_bad_value_exits_2_in_one_line_and_writes_nothing(tmp_path_factory, dataset, policy, capsys, name, key, value):
    runs = tmp_path_factory.getbasetemp() / "retries"
    runs.mkdir(exist_ok=True)
    tmp = tmp_path_factory.mktemp(f"{name}-{key}")
    fields = ALGORITHMS[name].params_model().model_fields
    fast = _fast(name, fields, policy)
    out = (runs / f"retry-{name}") if RETRY[name] == (name, key, value) else tmp / "run"
    cfg = _write(tmp / "bad.toml", name, {**fast, key: value})
    capsys.readouterr()
    assert main(["fit", str(dataset), "--algorithm", name, "--config", str(cfg), "--out", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert f"{name}.{key}" in err and str(cfg) in err, err
    assert not out.exists() or not any(out.iterdir()), "a refused configuration must leave no run behind"
    if RETRY[name] != (name, key, value):
        return
    # the retry with the default value (the key left out) into the same --out is accepted
    ok = _write(tmp / "ok.toml", name, fast)
    assert main(["fit", str(dataset), "--algorithm", name, "--config", str(ok), "--out", str(out), "-q"]) == 0, \
        capsys.readouterr().err
    assert (out / "model").is_dir()
