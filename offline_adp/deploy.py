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

from offline_adp.data.files import read_json_file
from offline_adp.data.rundir import check_outside_run, recorded_dataset
from offline_adp.errors import (
    ArtifactError,
    DatasetNotFoundError,
    IncompatibleError,
    OutputExistsError,
    RunDirectoryError,
    SchemaError,
    short_list,
)
from offline_adp.progress import get_logger

log = get_logger(__name__)

EXPORT_FORMATS = ("onnx",)


def _model_dir(run: Path) -> Path:
    for cand in (run, run / "model", run / "fit" / "model"):
        if (cand / "policy.json").exists() or (cand / "q.json").exists():
            return cand
    raise RunDirectoryError(f"{run}: not a run directory (no model/ with policy.json or q.json); fit one with "
                            "`offline-adp fit`")


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
            named = recorded_dataset(rj) if rj.exists() else None
            if named is not None:
                p = Path(named)
                cands += [p, d / p] if not p.is_absolute() else [p]
        cands.append(run / "dataset")
    for c in cands:
        if (c / "meta" / "info.json").exists():
            return c
    raise DatasetNotFoundError(f"{run}: cannot find the dataset it was fitted on (tried {[str(c) for c in cands]}); "
                               "pass --dataset DIR")


def load_policy(path: str | PathLike[str], dataset: str | PathLike[str] | None = None) -> Any:
    """A saved policy, with the run's signature when the run has one (``offline_adp.load_policy``).

    ``path`` is a run directory or its ``model/`` directory. When a signature is found
    (``model/signature.json``, or the ``meta/info.json`` of the dataset named by the
    run's ``run.json`` or by ``dataset``), ``act`` returns action *values* and refuses
    observations of the wrong names or width (:class:`~offline_adp.errors.SchemaError`),
    as :func:`load_run_policy`. A bare model directory with neither gives the policy
    without a signature (a warning says so): its ``act`` takes arrays and returns action
    indices, as :func:`offline_adp.artifacts.load_index_policy` always does.
    """
    import warnings

    p = Path(path)
    model = _model_dir(p)
    try:
        return load_run_policy(p, dataset)
    except DatasetNotFoundError:
        if dataset is not None or _names_dataset(model, p):
            raise
    from offline_adp.artifacts import load_index_policy

    warnings.warn(f"{model}: no signature.json and no run.json naming a dataset: the policy has no signature, so "
                  "act() takes arrays in the fitted column order and returns action indices", UserWarning, stacklevel=2)
    return load_index_policy(model)


def _names_dataset(model: Path, run: Path) -> bool:
    """Whether a run.json next to the model names a dataset."""
    return any((d / "run.json").exists() for d in (model.parent, run, run / "fit"))


def load_run_policy(run_dir: str | PathLike[str], dataset: str | PathLike[str] | None = None) -> Any:
    """The policy of a run directory with its signature attached (see module docstring)."""
    from offline_adp.artifacts import load_index_policy
    from offline_adp.data.info import DatasetInfo
    from offline_adp.policies import PolicySignature

    run = Path(run_dir)
    model = _model_dir(run)
    policy = load_index_policy(model)
    if (model / "signature.json").exists() and dataset is None:
        policy.signature = PolicySignature.from_dict(read_json_file(model / "signature.json"),
                                                     where=str(model / "signature.json"))
    else:
        ds = run_dataset(run, dataset)
        info_json = ds / "meta" / "info.json"  # found by run_dataset; read without the dataset readers (pandas)
        info = DatasetInfo.from_dict(read_json_file(info_json, error=SchemaError), where=str(info_json))
        _check_fitted_on(run, model, info, info_json)
        policy.signature = PolicySignature.from_info(info)
    if len(policy.signature.action_table) != policy.n_actions:
        raise IncompatibleError(f"{run}: the policy has {policy.n_actions} actions, its dataset's action table "
                                f"{len(policy.signature.action_table)}; pass the right --dataset")
    n_dims = getattr(policy, "n_dims", None)  # a distilled continuous policy: one model per component
    if n_dims is not None and n_dims != len(policy.signature.action_table.dims):
        raise IncompatibleError(f"{run}: the policy commands {n_dims} components, its action table has "
                                f"{len(policy.signature.action_table.dims)} "
                                f"({list(policy.signature.action_table.dims)})")
    _probe_width(model, policy)
    return policy


def _probe_width(model: Path, policy: Any) -> None:
    """One action, at the first step and past the last, on a state of the signature's
    width: models that read another width than the signature's (a tampered or mismatched
    model/ or signature.json) fail here as an :class:`ArtifactError`, not at the first
    ``act`` on the robot, and are never exported to a graph that fails at inference."""
    import numpy as np

    names = policy.signature.feature_names
    for t in (0, 1_000_000):
        try:
            a = np.asarray(policy.act_index(np.zeros((2, len(names))), t))
        except Exception as exc:  # whatever the stored models raise on that input
            raise ArtifactError(f"{model}: the policy cannot act on a state of its signature's {len(names)} features "
                                f"{short_list(list(names))} ({type(exc).__name__}: {exc})") from None
        if a.shape[0] != 2:
            raise ArtifactError(f"{model}: the policy returned {a.shape} for 2 states of its signature")


def _check_fitted_on(run: Path, model: Path, info: Any, info_json: Path) -> None:
    """The signature read from ``info_json`` must be the data the run was fitted on: the
    feature names in order and the action values ``run.json`` recorded (runs since
    2026-11-28). Else an error, not a policy whose ``act`` reads columns by the wrong names
    (a relative dataset path read from another directory, or ``--dataset`` of other logs)."""
    import numpy as np


    for d in (model.parent, run, run / "fit"):
        if (d / "run.json").is_file():
            rec = read_json_file(d / "run.json")
            break
    else:
        return
    feats, acts = rec.get("features"), rec.get("action_values")
    if isinstance(feats, list) and all(isinstance(f, str) for f in feats) and feats != list(info.feature_names):
        raise IncompatibleError(f"{run}: fitted on the features {short_list(feats)} (run.json), but {info_json} has "
                                f"{short_list(list(info.feature_names))}: not the data the run was fitted on; pass "
                                "--dataset DIR of those logs")
    if isinstance(acts, list):
        try:
            mine = np.asarray(acts, dtype=np.float64)
        except (TypeError, ValueError):
            return
        theirs = np.asarray(info.action_table.values, dtype=np.float64)
        if mine.shape != theirs.shape or not np.allclose(mine, theirs, rtol=1e-12, atol=0.0):
            raise IncompatibleError(f"{run}: fitted with the action table {short_list(mine.ravel().tolist())} "
                                    f"(run.json), but {info_json} has {short_list(theirs.ravel().tolist())}: not "
                                    "the data the run was fitted on; pass --dataset DIR of those logs")


def export_run(run_dir: str | PathLike[str], out: str | PathLike[str], fmt: str = "onnx",
               dataset: str | PathLike[str] | None = None, *, overwrite: bool = False,
               input_dtype: str = "float64") -> Path:
    """Export a run's policy (``offline-adp export``); ``fmt`` is one of :data:`EXPORT_FORMATS`.

    An existing ``out`` is replaced only with ``overwrite=True`` (``--overwrite``);
    ``input_dtype`` is the observation input's type (``float64`` or ``float32``)."""
    check_outside_run(run_dir, out)
    if Path(out).exists() and not overwrite:
        raise OutputExistsError(f"{out} already exists; pass --overwrite to replace it")
    if fmt not in EXPORT_FORMATS:
        from offline_adp.errors import UnknownNameError

        raise UnknownNameError(f"unknown export format {fmt!r}; known: {list(EXPORT_FORMATS)}")
    from offline_adp.onnx_export import save_onnx

    policy = load_run_policy(run_dir, dataset)
    return save_onnx(policy, out, input_dtype=input_dtype)


def distill_run(run_dir: str | PathLike[str], out: str | PathLike[str], dataset: str | PathLike[str] | None = None, *,
                n_estimators: int = 50, min_samples_leaf: int = 5, max_rate: Any = None, random_state: int = 0,
                overwrite: bool = False) -> dict[str, Any]:
    """Distill a run's continuous greedy policy (``offline-adp distill``) into ``out``, a
    run directory whose policy :func:`load_policy` returns and ``offline-adp export`` writes.

    ``out/model/`` holds ``policy.json`` + ``policy.npz`` (kind ``distilled_command``) and
    ``signature.json`` (so the distilled run needs no dataset to deploy); ``out/run.json``
    names the dataset and the run distilled. See :func:`offline_adp.distill.distill_policy`
    for the fit; returns its report (plus ``out``). An existing ``out`` is replaced only
    with ``overwrite=True``, and only if it is a distilled run (or empty).
    """
    import json

    from offline_adp.artifacts import save_policy
    from offline_adp.data.dataset import TransitionDataset
    from offline_adp.data.files import atomic_directory, locked_directory
    from offline_adp.distill import distill_policy
    from offline_adp.errors import WriteError

    run, dest = Path(run_dir), Path(out)
    check_outside_run(run, dest, directory=True)
    with locked_directory(dest, what="distilled run"):  # a second distill of `out` fails at once
        if dest.exists():
            if not overwrite:
                raise OutputExistsError(f"{dest} already exists; pass --overwrite to replace it")
            rj = dest / "run.json"
            distilled = rj.exists() and read_json_file(rj).get("algorithm") == "distill"
            if not dest.is_dir() or not (distilled or not any(dest.iterdir())):
                raise WriteError(f"{dest} is not a distilled run directory; --overwrite replaces only those (or "
                                 "an empty one)")
        policy = load_run_policy(run, dataset)
        ds_dir = run_dataset(run, dataset)
        ds = TransitionDataset.load(ds_dir)
        if len(ds.info.action_table.dims) != getattr(policy, "n_dims", len(ds.info.action_table.dims)):
            raise IncompatibleError(f"{run}: the policy commands {policy.n_dims} components, the dataset's action "
                                    f"table has {len(ds.info.action_table.dims)}")
        pi = distill_policy(policy, ds, n_estimators=n_estimators, min_samples_leaf=min_samples_leaf,
                            max_rate=max_rate, random_state=random_state)
        # the new run beside the old one, then renamed over it: killed at any moment, `out` is the old run or
        # the new one (it was removed before the rename, and a kill in between lost it)
        with atomic_directory(dest, overwrite=True, clean_stale=True) as tmp:
            save_policy(pi, tmp / "model", extra={"distilled_from": str(run.resolve())})
            (tmp / "model" / "signature.json").write_text(json.dumps(pi.signature.to_dict(), indent=1))
            (tmp / "run.json").write_text(json.dumps({"dataset": str(ds_dir.resolve()), "algorithm": "distill",
                                                      "distilled_from": str(run.resolve()), "distill": pi.report},
                                                     indent=1))
    return {**pi.report, "out": str(dest)}
