"""Compact tree artifacts (format 2): the file is proportional to the model, loading it
predicts bit for bit what the saved Q-function predicted, format-1 files still load, a
shared structure is stored once, and a crafted compact file is one ArtifactError.

Ground truth: the in-memory Q-function before saving, and the float32 comparison rule
(``x <= threshold`` on float32 inputs) checked exhaustively near each threshold.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from sklearn.ensemble import ExtraTreesRegressor

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.artifacts import load_q, save_q
from offline_adp.errors import ArtifactError
from offline_adp.qfunctions import QEncoder, TreeQ
from offline_adp.simulate import simulate
from offline_adp.trees import TreeEnsemble
from offline_adp.trees.ensemble import float32_floor
from tests.fuzz_util import node_layout


@pytest.fixture(scope="module")
def forest_q():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(4000, 4))
    y = np.sin(X[:, 0]) + X[:, 1] * X[:, 2] + rng.normal(0, 0.1, 4000)
    f = ExtraTreesRegressor(n_estimators=20, random_state=0).fit(X, y)
    q = TreeQ([TreeEnsemble.from_sklearn(f) for _ in range(2)], QEncoder(2, np.zeros((2, 0)), per_action=True))
    return q, X


def _states(q, X, rng):
    """Random states, and states exactly at, one float32 step above and below split thresholds."""
    ens = q.models[0]
    inner = np.flatnonzero(ens.left >= 0)[:3000]
    t32 = ens.threshold[inner].astype(np.float32)
    at = np.tile(X[:len(inner)], (3, 1)).astype(np.float32)
    for k, t in enumerate((t32, np.nextafter(t32, np.float32(np.inf)), np.nextafter(t32, np.float32(-np.inf)))):
        at[k * len(inner) + np.arange(len(inner)), ens.feature[inner]] = t
    return np.r_[rng.normal(size=(10_000, X.shape[1])) * 2, at.astype(np.float64)]


def test_saved_size_is_proportional_to_the_nodes_and_predictions_identical(forest_q, tmp_path):
    q, X = forest_q
    save_q(q, tmp_path / "m")
    nodes = sum(len(e.left) for e in q.models)
    size = (tmp_path / "m" / "q.npz").stat().st_size
    assert size / nodes < 8, size / nodes  # per-node layout (format 1): 26 bytes a node
    q2, meta = load_q(tmp_path / "m")
    assert meta["artifact_version"] == "2"
    obs = _states(q, X, np.random.default_rng(1))
    np.testing.assert_array_equal(q2.values(obs), q.values(obs))
    for a, b in zip(q.models, q2.models, strict=True):  # same leaves (renumbered), same leaf values
        ea = TreeEnsemble(a.left, a.right, a.feature, a.threshold, a.value, a.roots)  # numpy / rebuilt lookups
        np.testing.assert_array_equal(ea.value[ea.apply(obs)], b.value[b.apply(obs)])


def test_float32_floor_sends_every_float32_the_same_way():
    rng = np.random.default_rng(2)
    t = np.r_[rng.normal(size=20_000) * 10.0 ** rng.integers(-30, 30, 20_000), 0.0, -0.0, 1e300, -1e-300, 3.5]
    t32 = float32_floor(t)
    near = t.astype(np.float32)
    for x in (near, np.nextafter(near, np.float32(np.inf)), np.nextafter(near, np.float32(-np.inf))):
        np.testing.assert_array_equal(x.astype(np.float64) <= t, x <= t32)


def test_default_fit_builder_trees_and_format_1_files_load_identically(tmp_path):
    ds = simulate("path_tracking", 5, 10, seed=1, horizon=40)
    f = FittedQIteration(n_iterations=4, regressor_params={"n_estimators": 8, "n_jobs": 1}).fit(ds)
    obs = simulate("path_tracking", 3, 3, seed=9, horizon=30).arrays().obs
    save_q(f.q_function_, tmp_path / "v2")
    q2, _ = load_q(tmp_path / "v2")
    np.testing.assert_array_equal(q2.values(obs), f.q_function_.values(obs))
    # a format-1 file (per-node arrays) of the same model still loads, to the same values
    (tmp_path / "v1").mkdir()
    with np.load(tmp_path / "v2" / "q.npz") as z:
        np.savez(tmp_path / "v1" / "q.npz", **node_layout({k: z[k] for k in z.files}))
    spec = json.loads((tmp_path / "v2" / "q.json").read_text())
    (tmp_path / "v1" / "q.json").write_text(json.dumps({**spec, "artifact_version": "1"}))
    q1, _ = load_q(tmp_path / "v1")
    np.testing.assert_array_equal(q1.values(obs), f.q_function_.values(obs))
    spec["artifact_version"] = "99"
    (tmp_path / "v1" / "q.json").write_text(json.dumps(spec))
    with pytest.raises(ArtifactError, match="artifact format '99'"):
        load_q(tmp_path / "v1")


def test_a_finite_horizon_frozen_structure_is_stored_once(tmp_path):
    ds = simulate("path_tracking", 5, 10, seed=1, horizon=40)
    f = FittedQIteration(horizon=5, mode="frozen", regressor_params={"n_estimators": 6, "n_jobs": 1}).fit(ds)
    save_q(f.q_function_, tmp_path / "m")
    with np.load(tmp_path / "m" / "q.npz") as z:
        structures = [k for k in z.files if k.endswith("leaf_bits")]
    lefts = {id(q.models[0].left) for q in f.q_function_.qs}
    assert len(structures) == len(lefts) < 5
    q2, _ = load_q(tmp_path / "m")
    obs = simulate("path_tracking", 3, 3, seed=9, horizon=30).arrays().obs
    for t in range(5):
        np.testing.assert_array_equal(q2.values(obs, t), f.q_function_.values(obs, t))


def _bits(a):
    return np.unpackbits(a["q.m0.leaf_bits"])


CRAFTED = {
    "padding bit set": (
        "q.m0.leaf_bits",
        lambda a: a.__setitem__("q.m0.leaf_bits", np.r_[a["q.m0.leaf_bits"][:-1], 255].astype(np.uint8)),
    ),
    "flags not trees": (
        "q.m0.leaf_bits",
        lambda a: a.__setitem__(
            "q.m0.leaf_bits", np.packbits(np.roll(_bits(a)[: len(a["q.m0.feature"]) + len(a["q.m0.value_code"])], 1))
        ),
    ),
    "one leaf value missing": ("q.m0.leaf_bits", lambda a: a.__setitem__("q.m0.value_code", a["q.m0.value_code"][:-1])),
    "code beyond the table": (
        "q.m0.value_code",
        lambda a: a.__setitem__("q.m0.value_code", np.full_like(a["q.m0.value_code"], len(a["q.m0.value_table"]))),
    ),
    "non-finite value": (
        "q.m0.value_table",
        lambda a: a.__setitem__("q.m0.value_table", np.r_[np.nan, a["q.m0.value_table"][1:]]),
    ),
    "feature beyond the width": (
        "q.m0.feature",
        lambda a: a.__setitem__("q.m0.feature", np.full_like(a["q.m0.feature"], 200)),
    ),
    "non-finite threshold": (
        "q.m0.threshold",
        lambda a: a.__setitem__("q.m0.threshold", np.r_[np.inf, a["q.m0.threshold"][1:]].astype(np.float32)),
    ),
    "roots out of order": ("q.m0.roots", lambda a: a.__setitem__("q.m0.roots", a["q.m0.roots"][::-1].copy())),
    "signed leaf bits": (
        "q.m0.leaf_bits",
        lambda a: a.__setitem__("q.m0.leaf_bits", a["q.m0.leaf_bits"].astype(np.int8)),
    ),
}


@pytest.mark.parametrize("kind", sorted(CRAFTED))
def test_crafted_compact_file_is_one_clear_error(tmp_path, kind):
    rng = np.random.default_rng(3)
    X = rng.normal(size=(300, 3))
    f = ExtraTreesRegressor(n_estimators=4, random_state=0).fit(X, np.round(X[:, 0], 1))
    q = TreeQ([TreeEnsemble.from_sklearn(f)], QEncoder(2, np.array([[0.0], [1.0]]), per_action=False))
    q.models[0].n_features_in_ = 3
    save_q(q, tmp_path / "m")
    assert load_q(tmp_path / "m")[0].values(X[:, :2]).shape == (300, 2)  # the unmodified file loads
    member, edit = CRAFTED[kind]
    with np.load(tmp_path / "m" / "q.npz") as z:
        arrays = {k: z[k] for k in z.files}
    assert "q.m0.value_code" in arrays
    edit(arrays)
    np.savez_compressed(tmp_path / "m" / "q.npz", **arrays)
    with pytest.raises(ArtifactError, match=member.replace(".", r"\.")) as ei:
        load_q(tmp_path / "m")
    assert "\n" not in str(ei.value)


def test_finished_run_keeps_one_copy_and_the_summary_names_the_size(tmp_path, capsys):
    from offline_adp.cli import main

    simulate("path_tracking", 5, 10, seed=1, horizon=40).save(tmp_path / "ds")
    (tmp_path
     / "fit.toml").write_text("[fqi]\nn_iterations = 3\n[fqi.regressor_params]\nn_estimators = 5\nn_jobs = 1\n")
    assert main(["fit", str(tmp_path / "ds"), "--out", str(tmp_path / "run"), "--config",
                 str(tmp_path / "fit.toml")]) == 0
    out = capsys.readouterr().out
    model, ckpt = tmp_path / "run" / "model" / "q.npz", tmp_path / "run" / "checkpoint" / "q.npz"
    line = next(x for x in out.splitlines() if x.startswith("model: "))
    assert str(model) in line and f"{model.stat().st_size / 1e6:.1f} MB" in line
    assert model.stat().st_ino == ckpt.stat().st_ino  # one copy on disk
    obs = simulate("path_tracking", 2, 2, seed=4, horizon=10).arrays().obs
    expected = load_q(model.parent)[0].values(obs)
    model.unlink()  # the checkpoint still reads on its own
    np.testing.assert_array_equal(load_q(ckpt.parent)[0].values(obs), expected)


def test_a_file_declaring_nodes_out_of_proportion_to_its_size_is_refused_before_expansion():
    """Deflate lets a small file declare millions of compact nodes (a bit each) that cost
    ~140 bytes each to expand; the loader refuses more than MAX_NODES_PER_FILE_BYTE a byte."""
    import offline_adp.artifacts.checks as C

    members = {"q.m0.leaf_bits": (np.dtype(np.uint8), (1_048_576,)), "q.m0.feature": (np.dtype(np.uint8), (4_000_000,))}
    nodes = 8 * 1_048_576
    C.check_node_budget(members, nodes // C.MAX_NODES_PER_FILE_BYTE, "ok.npz")  # at the limit: accepted
    with pytest.raises(ArtifactError, match=r"crafted.npz: declares 8388608 tree nodes in a file of 1000000 bytes"):
        C.check_node_budget(members, 1_000_000, "crafted.npz")
