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
from offline_adp.data.dataset import TransitionArrays, TransitionDataset
from offline_adp.data.info import Action, ActionTable, DatasetInfo, Feature
from offline_adp.data.io import read_dataset, write_dataset
from offline_adp.data.validate import ValidationReport, validate, validate_directory
from offline_adp.envs import make_problem
from offline_adp.ingest.parquet import ingest_parquet
from offline_adp.policies import (
    DeterministicPolicy,
    EpsilonPolicy,
    FunctionPolicy,
    Policy,
    StochasticFunctionPolicy,
    TabularPolicy,
    UniformPolicy,
)
from offline_adp.simulate import collect, simulate

__all__ = [
    "__version__",
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
