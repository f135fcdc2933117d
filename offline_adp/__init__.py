"""offline_adp: offline approximate dynamic programming over logged robot and vehicle data.

Public names only; see ``docs/architecture.md`` for the layout.
"""

from offline_adp._version import __version__
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
from offline_adp.artifacts import load_policy, load_q, save_policy, save_q
from offline_adp.data.dataset import TransitionArrays, TransitionDataset
from offline_adp.data.info import Action, ActionTable, DatasetInfo, Feature
from offline_adp.data.io import read_dataset, write_dataset
from offline_adp.data.validate import ValidationReport, validate, validate_directory
from offline_adp.envs import make_problem
from offline_adp.envs.car_on_hill import score as car_on_hill_score
from offline_adp.evaluation.offpolicy import off_policy
from offline_adp.evaluation.report import build_report
from offline_adp.evaluation.rollout import rollout
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
from offline_adp.simulate import collect, simulate

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
