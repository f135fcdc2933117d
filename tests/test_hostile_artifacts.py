"""Hostile model artifacts and exports: crafted ``q.npz`` / ``q.json`` give one clear
error (no traceback, bounded memory), ``offline_adp.load_policy`` carries the run's
signature, ``export`` does not overwrite silently, and the ONNX model takes float32.

Ground truth is the fitted run itself: the policy loaded through the library's own
loader and the dataset's action table.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import offline_adp
from offline_adp.artifacts import load_index_policy, load_q
from offline_adp.errors import ArtifactError, OfflineADPError, SchemaError
from tests.fuzz_util import node_layout, peak_cli

ROOT = Path(__file__).resolve().parents[1]
PEAK_LIMIT_MB = 500


def _cli(*args: str, cwd: Path | None = None, timeout: int = 300) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "offline_adp", *args], capture_output=True, text=True, env=env,
                          cwd=cwd, timeout=timeout)


_peak_cli = peak_cli


def _one_clear_line(r: subprocess.CompletedProcess, *needles: str) -> str:
    err = "\n".join(ln for ln in r.stderr.splitlines() if not ln.startswith("PEAK_KB="))
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert len(lines[0]) < 1000, lines[0]
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A fitted FQI run (extra trees) on a small gridworld dataset."""
    base = tmp_path_factory.mktemp("hostile_art")
    r = _cli("simulate", "gridworld", "--out", str(base / "data"), "--demonstrations", "5", "--exploration", "10",
             "--horizon", "30", "-q")
    assert r.returncode == 0, r.stderr
    (base
     / "fit.toml").write_text('[fqi]\nregressor = "extra_trees"\nn_iterations = 3\nregressor_params = '
                              '{n_estimators = 5}\n')
    r = _cli("fit", str(base / "data"), "--out", str(base / "run"), "--config", str(base / "fit.toml"), "-q")
    assert r.returncode == 0, r.stderr
    return base / "run"


def _copy_run(run: Path, dest: Path) -> Path:
    """A copy of ``run`` without the model hashes of its run.json: an attacker who edits the
    model can rewrite run.json too, so every structural check must hold on its own
    (tests/test_model_hash.py tests the hash)."""
    import shutil

    shutil.copytree(run, dest)
    rj = json.loads((dest / "run.json").read_text())
    rj.pop("model_sha256", None)
    (dest / "run.json").write_text(json.dumps(rj))
    return dest


def _edit_npz(model: Path, edit) -> None:
    """Edit the model's arrays, rewritten per node (artifact format 1, still read: the
    edits target one node; the compact layout's own checks: test_compact_artifacts.py)."""
    with np.load(model / "q.npz", allow_pickle=False) as z:
        arrays = node_layout({k: z[k] for k in z.files})
    edit(arrays)
    np.savez(model / "q.npz", **arrays)


# ----------------------------------------------------------------------------- crafted npz
def _wrong_dtype(a):
    a["q.m0.left"] = a["q.m0.left"].astype(np.float64)


def _negative_child(a):
    left = a["q.m0.left"].copy()
    left[np.flatnonzero(left >= 0)[0]] = -5
    a["q.m0.left"] = left


def _child_out_of_range(a):
    right = a["q.m0.right"].astype(np.int64)
    right[np.flatnonzero(right >= 0)[0]] = 10 * len(right)
    a["q.m0.right"] = right


def _mismatched_lengths(a):
    a["q.m0.threshold"] = a["q.m0.threshold"][:-3]


def _inf_leaf(a):
    v = a["q.m0.value"].copy()
    v[np.flatnonzero(a["q.m0.left"] < 0)[2]] = np.inf
    a["q.m0.value"] = v


def _nan_leaf(a):
    v = a["q.m0.value"].copy()
    v[np.flatnonzero(a["q.m0.left"] < 0)[0]] = np.nan
    a["q.m0.value"] = v


CRAFTED = {
    "wrong_dtype": (_wrong_dtype, "q.m0.left"),
    "negative_child": (_negative_child, "q.m0."),
    "child_out_of_range": (_child_out_of_range, "q.m0.right"),
    "mismatched_lengths": (_mismatched_lengths, "q.m0.threshold"),
    "inf_leaf": (_inf_leaf, "q.m0.value"),
    "nan_leaf": (_nan_leaf, "q.m0.value"),
}


@pytest.mark.parametrize("kind", sorted(CRAFTED))
def test_crafted_npz_is_one_clear_error(run, tmp_path, kind):
    edit, member = CRAFTED[kind]
    # the unmodified copy loads (the test would otherwise pass for the wrong reason)
    good = _copy_run(run, tmp_path / "good")
    load_q(good / "model")
    bad = _copy_run(run, tmp_path / "bad")
    _edit_npz(bad / "model", edit)
    with pytest.raises(ArtifactError, match=member.replace(".", r"\.")) as ei:
        load_q(bad / "model")
    assert "q.{json,npz}" in str(ei.value) and "\n" not in str(ei.value)
    r = _cli("export", str(bad), "--out", str(tmp_path / "p.onnx"))
    _one_clear_line(r, member)
    assert not (tmp_path / "p.onnx").exists()


def test_inf_leaf_value_is_refused_with_node(run, tmp_path):
    bad = _copy_run(run, tmp_path / "bad")
    with np.load(run / "model" / "q.npz") as z:
        leaf = int(np.flatnonzero(node_layout({k: z[k] for k in z.files})["q.m0.left"] < 0)[2])
    _edit_npz(bad / "model", _inf_leaf)
    with pytest.raises(ArtifactError, match=f"node {leaf}: leaf value inf is not finite"):
        load_q(bad / "model")


# ----------------------------------------------------------------------------- memory bombs in q.json
@pytest.mark.parametrize("width", [100_000_000, 2_000_000_000])
def test_declared_width_bomb_is_refused_with_bounded_memory(run, tmp_path, width):
    bad = _copy_run(run, tmp_path / "bad")
    qj = bad / "model" / "q.json"
    spec = json.loads(qj.read_text())
    assert spec["q"]["models"][0]["n_features"] == 4
    spec["q"]["models"][0]["n_features"] = width
    qj.write_text(json.dumps(spec))
    r, peak = _peak_cli("export", str(bad), "--out", str(tmp_path / "p.onnx"))
    line = _one_clear_line(r, "q.m0.n_features", str(width))
    assert peak < PEAK_LIMIT_MB, (peak, line)
    for cmd in (["evaluate", str(bad)], ["compare", str(bad), str(run)]):
        r, peak = _peak_cli(*cmd)
        assert r.returncode == 2 and "Traceback" not in r.stderr and "n_features" in r.stderr, r.stderr[-1500:]
        assert peak < PEAK_LIMIT_MB, (cmd, peak)


def test_largest_allowed_width_probe_stays_bounded(run, tmp_path):
    """The largest width a tree model may declare, with many actions: refused by the probe
    bound (actions x width), not by allocating it."""
    bad = _copy_run(run, tmp_path / "bad")
    qj = bad / "model" / "q.json"
    spec = json.loads(qj.read_text())
    spec["q"]["models"][0]["n_features"] = 1_000_000
    qj.write_text(json.dumps(spec))
    _edit_npz(bad / "model", lambda a: a.update({"q.action_features": np.zeros((40, 2))}))
    spec["q"]["encoder"]["n_actions"] = 40
    qj.write_text(json.dumps(spec))
    r, peak = _peak_cli("export", str(bad), "--out", str(tmp_path / "p.onnx"))
    _one_clear_line(r, "out of proportion")
    assert peak < PEAK_LIMIT_MB


# ----------------------------------------------------------------------------- export overwrite
def test_export_refuses_to_overwrite_without_flag(run, tmp_path):
    out = tmp_path / "p.onnx"
    out.write_bytes(b"precious")
    r = _cli("export", str(run), "--out", str(out))
    _one_clear_line(r, "already exists", "--overwrite")
    assert out.read_bytes() == b"precious"
    r = _cli("export", str(run), "--out", str(out), "--overwrite")
    assert r.returncode == 0, r.stderr
    assert out.read_bytes()[:8] != b"precious" and out.stat().st_size > 1000


# ----------------------------------------------------------------------------- load_policy carries the signature
def test_top_level_load_policy_carries_the_signature(run):
    from offline_adp.data.dataset import read_dataset

    ds = read_dataset(Path(json.loads((run / "run.json").read_text())["dataset"]))
    a = ds.arrays()
    table = ds.info.action_table.values
    ref = load_index_policy(run / "model")  # the index loader: indices, no checks
    idx = ref.act_index(a.obs, 0)
    for path in (run, run / "model"):
        pi = offline_adp.load_policy(path)
        assert pi.signature is not None and list(pi.signature.feature_names) == list(ds.feature_names)
        got = np.asarray(pi.act(a.obs))
        np.testing.assert_array_equal(got.reshape(len(a.obs), -1), table[idx])
        np.testing.assert_array_equal(pi.act(a.obs, return_index=True), idx)
        wide = np.hstack([a.obs[:3], np.ones((3, 1))])
        with pytest.raises(SchemaError, match="3 columns, the policy expects 2"):
            pi.act(wide)
        with pytest.raises(SchemaError):
            pi.act(a.obs[:3, :-1])
    # the index loader is what it says: indices, no signature
    assert ref.signature is None
    assert offline_adp.load_index_policy is load_index_policy


def test_load_policy_without_any_signature_warns(run, tmp_path):
    import shutil

    shutil.copytree(run / "model", tmp_path / "model")
    with pytest.warns(UserWarning, match="returns action indices"):
        pi = offline_adp.load_policy(tmp_path / "model")
    assert pi.signature is None


def test_load_policy_with_a_missing_dataset_is_an_error(run, tmp_path):
    moved = _copy_run(run, tmp_path / "run")
    rj = json.loads((moved / "run.json").read_text())
    rj["dataset"] = str(tmp_path / "gone")
    (moved / "run.json").write_text(json.dumps(rj))
    with pytest.raises(OfflineADPError, match="cannot find the dataset"):
        offline_adp.load_policy(moved)


# ----------------------------------------------------------------------------- ONNX input types
def test_onnx_accepts_float32_with_the_same_actions(run, tmp_path):
    ort = pytest.importorskip("onnxruntime")
    from offline_adp.deploy import export_run, load_run_policy

    pi = load_run_policy(run)
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 8, size=(2000, len(pi.signature.feature_names))).astype(np.float32)
    ref = pi.act(X.astype(np.float64), return_index=True)
    out64 = export_run(run, tmp_path / "p64.onnx")
    out32 = export_run(run, tmp_path / "p32.onnx", input_dtype="float32")
    s32 = ort.InferenceSession(str(out32), providers=["CPUExecutionProvider"])
    s64 = ort.InferenceSession(str(out64), providers=["CPUExecutionProvider"])
    (inp,) = s32.get_inputs()
    assert inp.name == "observation" and inp.type == "tensor(float)" and inp.shape[1] == len(pi.signature.feature_names)
    got32 = dict(zip([o.name for o in s32.get_outputs()], s32.run(None, {"observation": X}), strict=True))
    got64 = dict(zip([o.name for o in s64.get_outputs()], s64.run(None, {"observation": X.astype(np.float64)}),
                     strict=True))
    q = pi.q.values(X.astype(np.float64))
    np.testing.assert_allclose(got32["q_values"], q, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(got32["q_values"], got64["q_values"])
    rows = np.arange(len(ref))
    differ = got32["action_index"] != ref
    assert np.all(np.abs(q[rows, got32["action_index"]] - q[rows, ref])[differ] <= 1e-12)
    meta = {p.key: p.value for p in __import__("onnx").load(str(out32)).metadata_props}
    inputs = json.loads(meta["inputs"])
    assert inputs["observation"]["dtype"] == "float32"
    assert inputs["observation"]["columns"] == list(pi.signature.feature_names)
    with pytest.raises(Exception, match="(?i)type"):  # the float64 model still refuses float32 (documented)
        s64.run(None, {"observation": X})


# ----------------------------------------------------------------------------- finite-horizon ONNX size
def test_finite_horizon_onnx_is_proportional_to_the_model(tmp_path):
    """An 8-step export is about 8 one-step models (each step has its own forest), no
    more; the inputs every step reads (joint pairs, float32 rounding) are built once; and
    onnxruntime's memory to load it stays proportional to the file."""
    pytest.importorskip("onnxruntime")
    import onnx

    from offline_adp.algorithms.fqi import FittedQIteration
    from offline_adp.artifacts import save_q
    from offline_adp.onnx_export import save_onnx
    from offline_adp.simulate import simulate
    from offline_adp.trees import TreeEnsemble

    ds = simulate("path_tracking", 4, 16, seed=3, horizon=40)
    size, nodes, npz, per_node = {}, {}, {}, {}
    for T in (1, 8):
        f = FittedQIteration(horizon=T, regressor="extra_trees", regressor_params={"n_estimators": 10}).fit(ds)
        ens = [TreeEnsemble.from_sklearn(q.models[0]) for q in f.q_function_.qs]
        nodes[T] = sum(len(e.left) for e in ens)
        per_node[T] = sum(a.nbytes for e in ens for a in e.to_arrays(layout="nodes").values())  # artifact format 1
        out = save_onnx(f.policy_, tmp_path / f"p{T}.onnx")
        save_q(f.q_function_, tmp_path / f"q{T}")
        size[T], npz[T] = out.stat().st_size, (tmp_path / f"q{T}" / "q.npz").stat().st_size
    ratio, model_ratio = size[8] / size[1], nodes[8] / nodes[1]
    print(f"\nONNX 1 step {size[1]} B, 8 steps {size[8]} B (x{ratio:.2f}; tree nodes x{model_ratio:.2f}); "
          f"q.npz {npz[1]} / {npz[8]} B")
    assert ratio <= 1.1 * model_ratio
    assert size[8] <= per_node[8]  # the export is no bigger than the model's per-node arrays
    assert npz[8] < per_node[8] / 3  # which the compact q.npz is much smaller than
    g = onnx.load(str(tmp_path / "p8.onnx")).graph
    assert sum(n.op_type == "Tile" for n in g.node) == 1  # the joint (x, a) pairs: once for all 8 steps
    assert sum(n.op_type == "TreeEnsemble" for n in g.node) == 8
    code = ("import psutil, onnxruntime as ort, sys\np = psutil.Process(); b = p.memory_info().rss\n"
            "s = ort.InferenceSession(sys.argv[1], providers=['CPUExecutionProvider'])\nprint(p.memory_info().rss - b)")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "p8.onnx")], capture_output=True, text=True,
                       timeout=300)
    grown = int(r.stdout.split()[-1])
    print(f"onnxruntime load: +{grown / 1e6:.1f} MB for a {size[8] / 1e6:.2f} MB model")
    assert grown < 30 * size[8] + (64 << 20)
