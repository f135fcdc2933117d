"""From a run directory to a deployable policy: load it with its signature, export it.

A run directory is what ``offline-adp fit`` writes (``RUN/model/``, ``RUN/run.json``
naming the dataset), a pipeline run (``RUN/fit/model/``, ``RUN/dataset/``) or a model
directory itself. The policy's :class:`~offline_adp.policies.PolicySignature` (feature
names and units, action table) comes from ``model/signature.json`` when present, else
from the ``meta/info.json`` of the dataset the run was fitted on.
"""

from __future__ import annotations

from os import PathLike
from pathlib import Path
from typing import Any

from offline_adp.data.io import read_info
from offline_adp.data.rundir import read_json_file
from offline_adp.errors import DatasetNotFoundError, OfflineADPError
from offline_adp.progress import get_logger

log = get_logger(__name__)

EXPORT_FORMATS = ("onnx",)


def _model_dir(run: Path) -> Path:
    for cand in (run, run / "model", run / "fit" / "model"):
        if (cand / "policy.json").exists() or (cand / "q.json").exists():
            return cand
    raise OfflineADPError(f"{run}: not a run directory (no model/ with policy.json or q.json); fit one with `offline-adp fit`")


def run_dataset(run_dir: str | PathLike[str], dataset: str | PathLike[str] | None = None) -> Path:
    """The dataset directory a run was fitted on (``dataset`` overrides)."""
    run = Path(run_dir)
    model = _model_dir(run)
    cands: list[Path] = []
    if dataset is not None:
        cands = [Path(dataset)]
    else:
        for d in (model.parent, run, run / "fit"):
            rj = d / "run.json"
            if rj.exists():
                p = Path(read_json_file(rj).get("dataset", ""))
                cands += [p, d / p] if not p.is_absolute() else [p]
        cands.append(run / "dataset")
    for c in cands:
        if (c / "meta" / "info.json").exists():
            return c
    raise DatasetNotFoundError(f"{run}: cannot find the dataset it was fitted on (tried {[str(c) for c in cands]}); "
                               "pass --dataset DIR")


def load_run_policy(run_dir: str | PathLike[str], dataset: str | PathLike[str] | None = None) -> Any:
    """The policy of a run directory with its signature attached (see module docstring)."""
    from offline_adp.artifacts import load_policy
    from offline_adp.data.info import DatasetInfo
    from offline_adp.policies import PolicySignature

    run = Path(run_dir)
    model = _model_dir(run)
    policy = load_policy(model)
    if (model / "signature.json").exists() and dataset is None:
        policy.signature = PolicySignature.from_dict(read_json_file(model / "signature.json"),
                                                     where=str(model / "signature.json"))
    else:
        ds = run_dataset(run, dataset)
        info = DatasetInfo.from_dict(read_info(ds), where=str(ds / "meta" / "info.json"))
        policy.signature = PolicySignature.from_info(info)
    if len(policy.signature.action_table) != policy.n_actions:
        raise OfflineADPError(f"{run}: the policy has {policy.n_actions} actions, its dataset's action table "
                              f"{len(policy.signature.action_table)}; pass the right --dataset")
    return policy


def export_run(run_dir: str | PathLike[str], out: str | PathLike[str], fmt: str = "onnx",
               dataset: str | PathLike[str] | None = None) -> Path:
    """Export a run's policy (``offline-adp export``); ``fmt`` is one of :data:`EXPORT_FORMATS`."""
    if fmt not in EXPORT_FORMATS:
        from offline_adp.errors import UnknownNameError

        raise UnknownNameError(f"unknown export format {fmt!r}; known: {list(EXPORT_FORMATS)}")
    from offline_adp.onnx_export import save_onnx

    policy = load_run_policy(run_dir, dataset)
    return save_onnx(policy, out)
