"""offline_adp: offline approximate dynamic programming over logged robot and vehicle data.

Public names only; see ``docs/architecture.md`` for the layout. Importing the package is
cheap: each public name is imported from its module on first use (PEP 562
``__getattr__``), so ``offline-adp --version`` and ``import offline_adp`` load no numpy,
pandas or scikit-learn.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from offline_adp._version import __version__

#: public name -> (module, attribute)
_LAZY: dict[str, tuple[str, str]] = {
    "FullModel": ("offline_adp.access", "FullModel"),
    "GenerativeModel": ("offline_adp.access", "GenerativeModel"),
    "ResetModel": ("offline_adp.access", "ResetModel"),
    "Simulator": ("offline_adp.access", "Simulator"),
    "StepResult": ("offline_adp.access", "StepResult"),
    "TraceData": ("offline_adp.access", "TraceData"),
    "FittedQEvaluation": ("offline_adp.algorithms.fqe", "FittedQEvaluation"),
    "FittedQIteration": ("offline_adp.algorithms.fqi", "FittedQIteration"),
    "load_policy": ("offline_adp.deploy", "load_policy"),
    "load_index_policy": ("offline_adp.artifacts", "load_index_policy"),
    "load_q": ("offline_adp.artifacts", "load_q"),
    "save_policy": ("offline_adp.artifacts", "save_policy"),
    "save_q": ("offline_adp.artifacts", "save_q"),
    "TransitionArrays": ("offline_adp.data.dataset", "TransitionArrays"),
    "TransitionDataset": ("offline_adp.data.dataset", "TransitionDataset"),
    "Action": ("offline_adp.data.info", "Action"),
    "ActionTable": ("offline_adp.data.info", "ActionTable"),
    "DatasetInfo": ("offline_adp.data.info", "DatasetInfo"),
    "Feature": ("offline_adp.data.info", "Feature"),
    "read_dataset": ("offline_adp.data.dataset", "read_dataset"),
    "write_dataset": ("offline_adp.data.io", "write_dataset"),
    "ValidationReport": ("offline_adp.data.validate", "ValidationReport"),
    "validate": ("offline_adp.data.validate", "validate"),
    "validate_directory": ("offline_adp.data.validate", "validate_directory"),
    "make_problem": ("offline_adp.envs", "make_problem"),
    "car_on_hill_score": ("offline_adp.envs.car_on_hill", "score"),
    "off_policy": ("offline_adp.evaluation.offpolicy", "off_policy"),
    "build_report": ("offline_adp.evaluation.report", "build_report"),
    "rollout": ("offline_adp.rollout", "rollout"),
    "evaluate_run": ("offline_adp.evaluation.run", "evaluate_run"),
    "shift_diagnostics": ("offline_adp.evaluation.shift", "diagnostics"),
    "ratios_by_classifier": ("offline_adp.evaluation.shift", "ratios_by_classifier"),
    "ratios_by_recursion": ("offline_adp.evaluation.shift", "ratios_by_recursion"),
    "ingest_mcap": ("offline_adp.ingest.mcap", "ingest_mcap"),
    "load_mcap_spec": ("offline_adp.ingest.mcap", "load_mcap_spec"),
    "ingest_parquet": ("offline_adp.ingest.parquet", "ingest_parquet"),
    "run_pipeline": ("offline_adp.pipeline", "run_pipeline"),
    "DeterministicPolicy": ("offline_adp.policies", "DeterministicPolicy"),
    "EpsilonPolicy": ("offline_adp.policies", "EpsilonPolicy"),
    "FunctionPolicy": ("offline_adp.policies", "FunctionPolicy"),
    "GreedyPolicy": ("offline_adp.policies", "GreedyPolicy"),
    "Policy": ("offline_adp.policies", "Policy"),
    "StochasticFunctionPolicy": ("offline_adp.policies", "StochasticFunctionPolicy"),
    "TabularPolicy": ("offline_adp.policies", "TabularPolicy"),
    "UniformPolicy": ("offline_adp.policies", "UniformPolicy"),
    "collect": ("offline_adp.simulate", "collect"),
    "simulate": ("offline_adp.simulate", "simulate"),
}

__all__ = [
    "__version__",
    "FittedQEvaluation",
    "FittedQIteration",
    "GreedyPolicy",
    "build_report",
    "car_on_hill_score",
    "evaluate_run",
    "ingest_mcap",
    "load_mcap_spec",
    "load_index_policy",
    "load_policy",
    "load_q",
    "off_policy",
    "ratios_by_classifier",
    "ratios_by_recursion",
    "rollout",
    "run_pipeline",
    "save_policy",
    "save_q",
    "shift_diagnostics",
    "Action",
    "ActionTable",
    "DatasetInfo",
    "DeterministicPolicy",
    "EpsilonPolicy",
    "Feature",
    "FullModel",
    "FunctionPolicy",
    "GenerativeModel",
    "Policy",
    "ResetModel",
    "Simulator",
    "StepResult",
    "StochasticFunctionPolicy",
    "TabularPolicy",
    "TraceData",
    "TransitionArrays",
    "TransitionDataset",
    "UniformPolicy",
    "ValidationReport",
    "collect",
    "ingest_parquet",
    "make_problem",
    "read_dataset",
    "simulate",
    "validate",
    "validate_directory",
    "write_dataset",
]


def __getattr__(name: str) -> Any:
    try:
        module, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'offline_adp' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), attr)
    globals()[name] = value  # cache: the next lookup does not come here
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


if TYPE_CHECKING:  # static type checkers and IDEs see the real imports
    from offline_adp.access import (
        FullModel,
        GenerativeModel,
        ResetModel,
        Simulator,
        StepResult,
        TraceData,
    )
    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.algorithms.fqi import FittedQIteration
    from offline_adp.artifacts import load_index_policy, load_q, save_policy, save_q
    from offline_adp.data.dataset import TransitionArrays, TransitionDataset, read_dataset
    from offline_adp.data.info import Action, ActionTable, DatasetInfo, Feature
    from offline_adp.data.io import write_dataset
    from offline_adp.data.validate import ValidationReport, validate, validate_directory
    from offline_adp.deploy import load_policy
    from offline_adp.envs import make_problem
    from offline_adp.envs.car_on_hill import score as car_on_hill_score
    from offline_adp.evaluation.offpolicy import off_policy
    from offline_adp.evaluation.report import build_report
    from offline_adp.evaluation.run import evaluate_run
    from offline_adp.evaluation.shift import diagnostics as shift_diagnostics
    from offline_adp.evaluation.shift import ratios_by_classifier, ratios_by_recursion
    from offline_adp.ingest.mcap import ingest_mcap, load_mcap_spec
    from offline_adp.ingest.parquet import ingest_parquet
    from offline_adp.pipeline import run_pipeline
    from offline_adp.policies import (
        DeterministicPolicy,
        EpsilonPolicy,
        FunctionPolicy,
        GreedyPolicy,
        Policy,
        StochasticFunctionPolicy,
        TabularPolicy,
        UniformPolicy,
    )
    from offline_adp.rollout import rollout
    from offline_adp.simulate import collect, simulate
