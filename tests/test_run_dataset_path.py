"""A run finds the data it was fitted on from any directory, and never attaches the
signature of other logs (issue #44 audit: a relative ``dataset`` in run.json was read from
the current directory, so another directory's ``data/x`` with its columns in another order
gave a policy that read ``v`` as ``e``).

Ground truth: the run's own policy read through the index loader (no signature) on the
fitted dataset's states, and the feature order the fit recorded."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import offline_adp
from offline_adp.artifacts import load_index_policy
from offline_adp.data.dataset import read_dataset
from offline_adp.errors import IncompatibleError
from offline_adp.runs import fit_run
from offline_adp.simulate import simulate


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A run fitted with a *relative* dataset path (as the README's tour types it)."""
    base = tmp_path_factory.mktemp("reldata")
    simulate("gridworld", 3, 6, seed=1, horizon=20).save(base / "data" / "g")
    old = Path.cwd()
    try:
        import os

        os.chdir(base)
        fit_run("data/g", "runs/g", params={"n_iterations": 3, "regressor_params": {"n_estimators": 5}})
    finally:
        os.chdir(old)
    return base


def _swapped_copy(src: Path, dest: Path) -> None:
    """``src`` with its two state features' names exchanged in meta/info.json: other logs."""
    shutil.copytree(src, dest)
    info = json.loads((dest / "meta" / "info.json").read_text())
    names = info["features"]
    assert len(names) >= 2
    names[0], names[1] = names[1], names[0]
    (dest / "meta" / "info.json").write_text(json.dumps(info))


def test_run_json_records_the_absolute_path(fitted):
    rj = json.loads((fitted / "runs" / "g" / "run.json").read_text())
    assert rj["dataset"] == "data/g"  # as typed
    assert Path(rj["dataset_resolved"]) == (fitted / "data" / "g").resolve()


def test_load_policy_from_another_directory_reads_the_fitted_data(fitted, tmp_path, monkeypatch):
    # another directory holding its own data/g: other logs, features in another order
    _swapped_copy(fitted / "data" / "g", tmp_path / "data" / "g")
    monkeypatch.chdir(tmp_path)
    run = fitted / "runs" / "g"
    pi = offline_adp.load_policy(run)
    ds = read_dataset(fitted / "data" / "g")
    assert list(pi.signature.feature_names) == list(ds.feature_names)
    obs = ds.arrays().obs
    idx = load_index_policy(run / "model").act_index(obs, 0)
    np.testing.assert_array_equal(pi.act(obs, return_index=True), idx)


def test_a_run_without_the_resolved_path_refuses_other_logs(fitted, tmp_path, monkeypatch):
    # a run written before dataset_resolved: the relative path finds the other directory's logs
    run = tmp_path / "old_run"
    shutil.copytree(fitted / "runs" / "g", run)
    rj = json.loads((run / "run.json").read_text())
    del rj["dataset_resolved"]
    (run / "run.json").write_text(json.dumps(rj))
    _swapped_copy(fitted / "data" / "g", tmp_path / "data" / "g")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(IncompatibleError, match="fitted on the features"):
        offline_adp.load_policy(run)
    # and so does export, with its message naming the run
    from offline_adp.deploy import export_run

    with pytest.raises(IncompatibleError, match="not the data the run was fitted on"):
        export_run(run, tmp_path / "p.onnx")
    assert not (tmp_path / "p.onnx").exists()


def test_an_explicit_dataset_of_other_logs_is_refused(fitted, tmp_path):
    _swapped_copy(fitted / "data" / "g", tmp_path / "other")
    with pytest.raises(IncompatibleError, match="fitted on the features"):
        offline_adp.load_policy(fitted / "runs" / "g", dataset=tmp_path / "other")


def test_a_dataset_path_edited_since_the_fit_is_read_as_edited(fitted, tmp_path):
    """`dataset_resolved` is the typed path's absolute form; once `dataset` is edited (to
    other logs at another relative path) it no longer ends with it and the edit wins."""
    from offline_adp.data.rundir import recorded_dataset

    rj = json.loads((fitted / "runs" / "g" / "run.json").read_text())
    assert recorded_dataset("run.json", rj) == rj["dataset_resolved"]
    assert recorded_dataset("run.json", {**rj, "dataset": "data/other"}) == "data/other"
    assert recorded_dataset("run.json", {**rj, "dataset": "../g"}) == "../g"
