"""Saved runs that load and export: what an export audit found (2026-11-29).

- a PSDP run fitted with ``drop_features`` (the ``fit --help`` example) could not be
  exported once saved: the loaded column map is wrapped by the artifact loader's guard;
- a model reading another width than its signature (a tampered ``n_features`` and split
  feature, a distilled ``n_features``) loaded, and ``export`` wrote a graph that failed
  at inference; a ``signature.json`` with fewer units than names gave the CLI a traceback;
- a logged state of 1e300 in a continuous policy's candidates loaded, and ``act`` raised
  scipy's bare ``ValueError``; a column map with a negative column loaded and read the last
  feature in place of the first.

Ground truth: the run's policy before tampering (its actions, and its graph's)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
import onnxruntime as ort  # noqa: E402

import offline_adp  # noqa: E402
from offline_adp.artifacts.storage import model_hashes  # noqa: E402
from offline_adp.deploy import export_run  # noqa: E402
from offline_adp.errors import ArtifactError, OfflineADPError, SchemaError  # noqa: E402
from offline_adp.runs import fit_run  # noqa: E402
from offline_adp.simulate import simulate  # noqa: E402


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile_exports")
    simulate("path_tracking", 3, 3, seed=2, horizon=30).save(root / "data")
    fit_run(root / "data", root / "fqi", params={"n_iterations": 3, "regressor_params": {"n_estimators": 5}})
    return root


def _tampered(run, dest, edit):
    """A copy of ``run`` with ``edit(model_dir)`` applied and run.json's hashes updated (as anyone
    editing a run can)."""
    shutil.copytree(run, dest)
    edit(dest / "model")
    rj = json.loads((dest / "run.json").read_text())
    if isinstance(rj.get("model_sha256"), dict):
        rj["model_sha256"] = model_hashes(dest / "model")
        (dest / "run.json").write_text(json.dumps(rj))
    return dest


def _edit_json(path, fn):
    d = json.loads(path.read_text())
    fn(d)
    path.write_text(json.dumps(d))


def _edit_npz(path, fn):
    z = dict(np.load(path, allow_pickle=False))
    fn(z)
    np.savez(path.with_suffix(""), **z)


def test_saved_psdp_run_with_drop_features_exports_and_agrees(base, tmp_path):
    run = tmp_path / "psdp"
    fit_run(base / "data", run, algorithm="psdp",
            params={"simulator": "path_tracking", "horizon": 3, "n_samples": 60, "n_rollouts": 1,
                    "learner": "classification", "drop_features": ["s"], "learner_params": {"n_estimators": 5}})
    out = export_run(run, tmp_path / "p.onnx")
    pi = offline_adp.load_policy(run)
    X = offline_adp.TransitionDataset.load(base / "data").arrays().obs
    t = np.arange(len(X)) % 5  # steps past the horizon use the last rule
    sess = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    got = sess.run(["action_index"], {"observation": X, "t": t.astype(np.int64)})[0]
    np.testing.assert_array_equal(got, pi.act(X, t, return_index=True))


def test_a_model_wider_than_its_signature_is_refused_at_load(base, tmp_path):
    def edit(m):
        _edit_json(m / "q.json", lambda d: d["q"]["models"][0].__setitem__("n_features", 9))
        _edit_npz(m / "q.npz", lambda z: z["q.m0.feature"].__setitem__(0, 8))

    bad = _tampered(base / "fqi", tmp_path / "wide", edit)
    with pytest.raises(ArtifactError, match="cannot act on a state of its signature's 7 features"):
        offline_adp.load_policy(bad)
    with pytest.raises(ArtifactError, match="cannot act on a state"):
        export_run(bad, tmp_path / "w.onnx")
    assert not (tmp_path / "w.onnx").exists()


def test_a_negative_column_map_is_refused(base, tmp_path):
    cols = {"kind": "sklearn", "class": "SelectColumns", "params": {"columns": [-1, 1, 2, 3, 4, 5, 6]}, "attrs": {}}
    bad = _tampered(base / "fqi", tmp_path / "neg",
                    lambda m: _edit_json(m / "q.json", lambda d: d["q"]["encoder"].__setitem__("feature_map", cols)))
    with pytest.raises(ArtifactError, match=r"columns \[-1\] are not indices 0..6"):
        offline_adp.load_policy(bad)


def test_a_signature_with_fewer_units_than_names_is_a_clear_error(base, tmp_path):
    run = _tampered(base / "fqi", tmp_path / "sig", lambda m: None)
    sig = offline_adp.load_policy(base / "fqi").signature.to_dict()
    sig["feature_units"] = sig["feature_units"][:-1]
    (run / "model" / "signature.json").write_text(json.dumps(sig))
    with pytest.raises(SchemaError, match="feature_units must be one string per feature"):
        offline_adp.load_policy(run)
    from offline_adp.cli import main

    assert main(["export", str(run), "--out", str(tmp_path / "s.onnx")]) != 0  # an error line, not a traceback
    for broken in ({**sig, "feature_names": ["e", "e"]}, {**sig, "feature_names": "e"}, [1, 2]):
        (run / "model" / "signature.json").write_text(json.dumps(broken))
        with pytest.raises(OfflineADPError):
            offline_adp.load_policy(run)


def test_huge_candidate_points_are_refused_at_load():
    from offline_adp.artifacts.q_kinds import _read_candidates

    arrays = {"p": np.array([[0.0, 1.0], [1e300, 0.0]]), "c": np.zeros((2, 1)), "m": np.zeros(2), "s": np.ones(2)}
    entry = {"candidates": {"kind": "neighbour_commands", "points": "p", "commands": "c", "center": "m",
                            "scale": "s", "k": 2}}
    with pytest.raises(ArtifactError, match="candidates.points: a scaled logged state of magnitude 1e\\+300"):
        _read_candidates(entry, arrays, "q.npz", 2, 1)
    arrays["p"][1, 0] = 3.0  # the same entry with a sane state loads
    assert _read_candidates(entry, arrays, "q.npz", 2, 1).k == 2
