"""Checkpoints of a local fit (runs._iterate, FittedQEstimator.checkpoint_q): paced by their
CPU cost, the first and last iteration always; a deferred fit's Q taken from the learner
only when one is written; a fit stopped inside an iteration keeps a consistent checkpoint
(its Q and its history rows agree) that resumes to the uninterrupted result; checkpoints
store their arrays uncompressed and the last one shares the model's file.

Ground truth: the uninterrupted fit_run of the same parameters (bit for bit).
"""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from offline_adp import runs
from offline_adp.algorithms.checkpoint import read_checkpoint
from offline_adp.runs import fit_run
from offline_adp.simulate import simulate

PARAMS = {"n_iterations": 8, "regressor_params": {"n_estimators": 6, "n_jobs": 1}, "random_state": 1}


@pytest.fixture(scope="module")
def pt_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("pt") / "ds"
    simulate("path_tracking", 12, 12, seed=5, horizon=40).save(d)
    return d


@pytest.fixture(scope="module")
def obs():
    return simulate("path_tracking", 2, 2, seed=4, horizon=10).arrays().obs


def _writes(monkeypatch) -> list[int]:
    seen: list[int] = []
    real = runs.write_checkpoint

    def counting(directory, est, rows):
        n = real(directory, est, rows)
        if n:
            seen.append(n)
        return n

    monkeypatch.setattr(runs, "write_checkpoint", counting)
    return seen


def test_a_costly_checkpoint_waits_but_the_first_and_last_are_written(tmp_path, pt_dir, monkeypatch):
    seen = _writes(monkeypatch)
    monkeypatch.setattr(runs, "CHECKPOINT_CPU_SHARE", 1e-12)  # any write costs more than the whole fit
    fit_run(pt_dir, tmp_path / "a", params=PARAMS)
    assert seen == [1, 8]
    seen.clear()
    monkeypatch.setattr(runs, "CHECKPOINT_CPU_SHARE", 1e12)  # writes cost nothing: every iteration
    fit_run(pt_dir, tmp_path / "b", params=PARAMS)
    assert seen == list(range(1, 9))


def test_checkpoints_are_stored_uncompressed_and_the_last_shares_the_model_file(tmp_path, pt_dir, monkeypatch):
    names = []
    real = runs.write_checkpoint

    def look(directory, est, rows):
        n = real(directory, est, rows)
        with zipfile.ZipFile(directory / "q.npz") as z:
            names.append({i.compress_type for i in z.infolist()})
        return n

    monkeypatch.setattr(runs, "write_checkpoint", look)
    fit_run(pt_dir, tmp_path / "r", params=PARAMS)
    assert names and all(kinds == {zipfile.ZIP_STORED} for kinds in names)
    model, ckpt = tmp_path / "r" / "model" / "q.npz", tmp_path / "r" / "checkpoint" / "q.npz"
    assert model.stat().st_ino == ckpt.stat().st_ino
    with zipfile.ZipFile(model) as z:
        assert zipfile.ZIP_DEFLATED in {i.compress_type for i in z.infolist()}  # the model's arrays compressed


@pytest.mark.parametrize("resumed", [False, True])
@pytest.mark.parametrize("mode", ["frozen", "refit"])
def test_stopped_inside_an_iteration_the_checkpoint_is_consistent_and_resumes(tmp_path, pt_dir, obs, monkeypatch, mode,
                                                                              resumed):
    """Ctrl-C inside iteration 6's LEARN step (the deferred fit has no Q of iteration 5 at
    hand then; a resumed one has the Q it resumed from, older than its last checkpoint):
    the checkpoint of iteration 5 stays, its Q and history agree, and --resume reaches the
    uninterrupted fit's Q and history bit for bit."""
    from offline_adp.learn import Learner

    params = {**PARAMS, "mode": mode}
    ref = fit_run(pt_dir, tmp_path / "ref", params=params)
    monkeypatch.setattr(runs, "CHECKPOINT_CPU_SHARE", 1e12)  # a checkpoint at every iteration before the stop
    if resumed:  # stopped after iteration 2 first, then resumed from it
        def stop(row):
            if row["iteration"] == 2:
                raise KeyboardInterrupt
        with pytest.raises(KeyboardInterrupt):
            fit_run(pt_dir, tmp_path / "run", params=params, on_iteration=stop)

    def patch(cls):
        real = cls.fit

        def fit(self, y, k):
            if k == 6:
                raise KeyboardInterrupt
            return real(self, y, k)
        monkeypatch.setattr(cls, "fit", fit)

    for cls in set(_all_subclasses(Learner)):  # whichever LEARN step the mode uses
        if "fit" in vars(cls):
            patch(cls)
    with pytest.raises(KeyboardInterrupt):
        fit_run(pt_dir, tmp_path / "run", params=params, resume=resumed)
    monkeypatch.undo()
    state = read_checkpoint(tmp_path / "run" / "checkpoint")  # consistent, or this raises
    k = json.loads((tmp_path / "run" / "checkpoint" / "q.json").read_text())["iteration"]
    assert k == len(state["history"]) == 5
    assert json.loads((tmp_path / "run" / "run.json").read_text())["status"] == "interrupted"
    est = fit_run(pt_dir, tmp_path / "run", params=params, resume=True)
    np.testing.assert_array_equal(est.predict(obs), ref.predict(obs))
    np.testing.assert_array_equal(est.history_["sup_dq"].to_numpy(), ref.history_["sup_dq"].to_numpy())


def _all_subclasses(cls):
    for c in cls.__subclasses__():
        yield c
        yield from _all_subclasses(c)


@pytest.mark.parametrize("share", [1e12, 1e-12])
@pytest.mark.parametrize("mode", ["frozen", "refit"])
def test_checkpoints_do_not_change_the_fit(tmp_path, pt_dir, obs, monkeypatch, mode, share):
    """A run checkpointed at every iteration (its deferred Q snapshot each time) or only at
    the first and last fits what FittedQIteration.fit fits, bit for bit."""
    from offline_adp.algorithms.fqi import FittedQIteration
    from offline_adp.data.dataset import read_dataset

    params = {**PARAMS, "mode": mode}
    monkeypatch.setattr(runs, "CHECKPOINT_CPU_SHARE", share)
    est = fit_run(pt_dir, tmp_path / "run", params=params)
    api = FittedQIteration(**params).fit(read_dataset(pt_dir))
    np.testing.assert_array_equal(est.predict(obs), api.predict(obs))
    np.testing.assert_array_equal(est.history_["sup_dq"].to_numpy(), api.history_["sup_dq"].to_numpy())
