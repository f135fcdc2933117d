"""Whether a run's policy fits a dataset: it commands the dataset's actions (or, continuous,
its command components, units and bounds) and reads its features, else an
:class:`~offline_adp.errors.IncompatibleError` naming both; and the information of the
dataset a run was fitted on. Used by :func:`offline_adp.evaluation.run.evaluate_run`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.rundir import recorded_dataset
from offline_adp.errors import ArtifactError, IncompatibleError, short_list


def _check_same_actions(run: Path, info: dict[str, Any], policy: Any, ds: TransitionDataset, ds_path: Path) -> None:
    """The policy must command the dataset's actions and read its features: else an error
    naming both (not a shape error deep inside an estimator, nor silently wrong numbers)."""
    values = short_list(ds.info.action_table.values.ravel().tolist())
    if getattr(policy, "continuous", False):
        _check_same_commands(run, info, ds, ds_path)
        return _check_recorded_features(run, info, ds, ds_path)
    if getattr(policy, "n_actions", ds.n_actions) != ds.n_actions:
        raise IncompatibleError(f"{run}: its policy has {policy.n_actions} actions, the dataset {ds_path} has "
                                f"{ds.n_actions} "
                              f"(action table {values}); evaluate or compare runs on data with the action table "
                              "they were fitted on")
    recorded = info.get("action_values")  # the action table the fit read (run.json, runs since 2026-11-29)
    if isinstance(recorded, list):
        mine = np.asarray(recorded, dtype=np.float64) if recorded else np.zeros(0)
        theirs = np.asarray(ds.info.action_table.values, dtype=np.float64)
        if mine.shape != theirs.shape or not np.allclose(mine, theirs, rtol=1e-12, atol=0.0):
            raise IncompatibleError(f"{run}: fitted with the action table {short_list(mine.ravel().tolist())} "
                                    f"(run.json), but the dataset {ds_path} has {values}; evaluate or compare runs "
                                    "on data with the action table they were fitted on, in the same order")
    _check_recorded_features(run, info, ds, ds_path)
    if isinstance(recorded, list) and isinstance(info.get("features"), list):
        return  # both read from run.json above: the fitted dataset's info.json adds nothing
    try:
        own = recorded_dataset(run / "run.json", info)
    except ArtifactError:  # a run.json naming no usable path: the logs given are all there is to check
        return
    if not isinstance(own, str) or not own or not (Path(own) / "meta" / "info.json").is_file():
        return
    if Path(own).resolve() == ds_path.resolve():
        return
    from offline_adp.data.info import DatasetInfo
    from offline_adp.data.io import read_info

    fitted = DatasetInfo.from_dict(read_info(own), where=str(Path(own) / "meta" / "info.json"))
    theirs = fitted.action_table.values
    if theirs.shape != ds.info.action_table.values.shape or not np.allclose(theirs, ds.info.action_table.values):
        raise IncompatibleError(f"{run}: fitted on {own} with the action table {short_list(theirs.ravel().tolist())}, "
                                "but the dataset "
                              f"{ds_path} has {values}; evaluate or compare runs on data with the same action table")
    if list(fitted.feature_names) != list(ds.feature_names):
        raise IncompatibleError(f"{run}: fitted on {own} with features {list(fitted.feature_names)}, but the dataset "
                              f"{ds_path} has {list(ds.feature_names)}; evaluate or compare runs on data with the "
                              "same features")


def _check_recorded_data(run: Path, info: dict[str, Any], ds: TransitionDataset, ds_path: Path) -> None:
    """The dataset found by the path ``run.json`` names (as typed at the fit: a relative one
    is read from the current directory) must be the data the run was fitted on, by its
    fingerprint: else an error, not an evaluation of other data under the run's name."""
    stored = info.get("dataset_fingerprint")
    if stored is None or ds.matches_fingerprint(stored):
        return
    raise IncompatibleError(f"{run}: run.json names the dataset {str(info.get('dataset'))!r}, but {ds_path.resolve()} "
                            "is not the data the run was fitted on (its fingerprint differs: edited since, or "
                            "another directory of that name); pass --dataset DIR to evaluate on it anyway")


def _check_recorded_features(run: Path, info: dict[str, Any], ds: TransitionDataset, ds_path: Path) -> None:
    """The features the fit read, in order (``run.json``'s ``features``, runs written since
    2026-11-28), against the dataset's: the fitted dataset's own ``info.json`` may have been
    edited since, which comparing that dataset with itself cannot see."""
    recorded = info.get("features")
    if isinstance(recorded, list) and all(isinstance(f, str) for f in recorded) and recorded != list(ds.feature_names):
        raise IncompatibleError(f"{run}: fitted on the features {short_list(recorded)} (run.json), but the dataset "
                                f"{ds_path} has {short_list(list(ds.feature_names))}; evaluate or compare runs on data "
                                "with the same features in the same order")


def _fitted_info(info: dict[str, Any]) -> Any:
    """The :class:`DatasetInfo` of the dataset a run was fitted on (None: not found)."""
    try:
        own = recorded_dataset("run.json", info)
    except ArtifactError:
        return None
    if not isinstance(own, str) or not own or not (Path(own) / "meta" / "info.json").is_file():
        return None
    from offline_adp.data.info import DatasetInfo
    from offline_adp.data.io import read_info

    return DatasetInfo.from_dict(read_info(own), where=str(Path(own) / "meta" / "info.json"))


def _check_same_commands(run: Path, info: dict[str, Any], ds: TransitionDataset, ds_path: Path) -> None:
    """A continuous policy reads the dataset's features and commands the same components:
    names and units. The bounds need not agree: without ``low``/``high`` in the spec they are
    each log's own minimum and maximum, so two recordings of one robot differ (the policy
    keeps its own bounds; where it commands beyond what these logs hold, the evaluation's
    command support says so), nor do the coarse bins."""
    at = ds.info.action_table
    if not at.continuous:
        raise IncompatibleError(f"{run}: its policy commands continuous values; the dataset {ds_path} has no exact "
                                f"commands (action table kind {at.kind!r})")
    fitted = _fitted_info(info)
    if fitted is None:
        return
    mine = fitted.action_table
    same = mine.dims == at.dims and (not mine.units or not at.units or tuple(mine.units) == tuple(at.units))
    if not same or list(fitted.feature_names) != list(ds.feature_names):
        raise IncompatibleError(f"{run}: fitted on commands {list(mine.dims)} {list(mine.units)} and features "
                                f"{list(fitted.feature_names)}, but the dataset {ds_path} has {list(at.dims)} "
                                f"{list(at.units)} and {list(ds.feature_names)}; evaluate on logs of the same commands "
                                "(names and units)")
