"""Issue 16, crafted artifacts: each case of the report is refused with one ArtifactError.

The memory-unsafe cases (out-of-range child or feature index, self-loop) are loaded in a
child process, so that on code without the checks they fail as a crash or a timeout
instead of taking pytest down.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from offline_adp.algorithms.fqi import FittedQIteration, save_fqi
from offline_adp.artifacts import load_q
from offline_adp.errors import ArtifactError
from tests.fuzz_util import node_layout

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tree_run(tmp_path_factory, small_pt):
    f = FittedQIteration(n_iterations=2, regressor="extra_trees",
                         regressor_params={"n_estimators": 2, "n_jobs": 1, "min_samples_leaf": 5}).fit(small_pt)
    d = tmp_path_factory.mktemp("trees")
    save_fqi(f, d)
    return d, small_pt.arrays().obs[:50]


def _edit_npz(src: Path, dst: Path, key: str, fn) -> Path:
    import shutil

    shutil.copytree(src, dst)
    with np.load(src / "q.npz") as z:  # per node (format 1, still read): the edits target one node
        arrs = node_layout({k: z[k].copy() for k in z.files})
    arrs[key] = fn(arrs[key], arrs)
    np.savez(dst / "q.npz", **arrs)
    return dst


def _load_in_child(d: Path, width: int, timeout: float = 60) -> str:
    code = (
        "import sys, numpy as np, warnings\nwarnings.simplefilter('ignore')\n"
        "from offline_adp.artifacts import load_q\n"
        "from offline_adp.errors import ArtifactError\n"
        f"try:\n    q, _ = load_q({str(d)!r}); v = q.values(np.random.default_rng(0).normal(size=(64, {width})), 0)\n"
        "    print('LOADED', v.shape)\nexcept ArtifactError as e:\n"
        "    print('ArtifactError:', e)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    try:
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return "HANG"
    if r.returncode != 0:
        return f"CRASH rc={r.returncode} {r.stderr[-300:]}"
    return r.stdout.strip()


def _first_inner(arrs) -> int:
    return int(np.flatnonzero(arrs["q.m0.left"] >= 0)[1])


@pytest.mark.parametrize(
    "case, key, fn",
    [
        ("child index beyond the arrays", "q.m0.left", lambda a, A: np.where(np.arange(len(a)) == 0, 10**7, a)),
        ("child index into another tree", "q.m0.right", lambda a, A: np.where(np.arange(len(a)) == 0, len(a) - 1, a)),
        ("feature index beyond the input", "q.m0.feature", lambda a, A: np.where(np.arange(len(a)) == 0, 10**6, a)),
        ("negative feature index", "q.m0.feature", lambda a, A: np.where(np.arange(len(a)) == 0, -3, a)),
        ("self-loop", "q.m0.left", lambda a, A: np.where(np.arange(len(a)) == _first_inner(A), _first_inner(A), a)),
        ("back edge to the root", "q.m0.right", lambda a, A: np.where(np.arange(len(a)) == _first_inner(A), 0, a)),
        ("non-finite threshold", "q.m0.threshold", lambda a, A: np.where(np.arange(len(a)) == 0, np.nan, a)),
        ("roots out of order", "q.m0.roots", lambda a, A: a[::-1].copy()),
        ("huge tree count", "q.m0.roots", lambda a, A: np.zeros(100_000, np.int64)),
        ("float child indices", "q.m0.left", lambda a, A: a.astype(np.float64)),
        ("2-D value array", "q.m0.value", lambda a, A: a.reshape(-1, 1)),
    ],
)
def test_crafted_tree_arrays_are_one_artifact_error(tree_run, tmp_path, case, key, fn):
    src, obs = tree_run
    d = _edit_npz(src, tmp_path / "run", key, fn)
    out = _load_in_child(d, obs.shape[1])
    assert out.startswith("ArtifactError:"), f"{case}: {out}"
    assert "q.npz" in out or "q.{json,npz}" in out
    assert key in out or key.rsplit(".", 1)[0] in out


def test_feature_within_width_of_the_artifact_but_not_of_the_input(tree_run, tmp_path):
    """A valid artifact evaluated on narrower observations: an error, not stray memory."""
    src, obs = tree_run
    q, _ = load_q(src)
    with pytest.raises(ArtifactError, match="feature|features|shape"):
        q.values(obs[:, :1], 0)


@pytest.mark.parametrize(
    "edit",
    [
        lambda s: s["q"].pop("encoder"),
        lambda s: s["q"]["encoder"].__setitem__("n_actions", "three"),
        lambda s: s["q"]["encoder"].__setitem__("n_actions", 10**9),
        lambda s: s["q"]["encoder"].__setitem__("action_features", "nope"),
        lambda s: s["q"]["encoder"].__setitem__("action_features", 7),
        lambda s: s["q"].__setitem__("models", []),
        lambda s: s["q"].__setitem__("models", [None]),
        lambda s: s["q"]["models"][0].__setitem__("key", "q.m9"),
        lambda s: s["q"]["models"][0].__setitem__("kind", "pickle"),
        lambda s: s["q"].__setitem__("kind", "time_indexed"),
        lambda s: s.__setitem__("q", []),
        lambda s: s.pop("q"),
    ],
    ids=["no-encoder", "n_actions-str", "n_actions-huge", "af-missing", "af-int", "no-models", "model-null",
         "bad-key", "bad-kind", "time-indexed-without-qs", "q-list", "no-q"],
)
def test_malformed_json_is_one_artifact_error(tree_run, tmp_path, edit):
    import shutil

    src, obs = tree_run
    d = tmp_path / "r"
    shutil.copytree(src, d)
    spec = json.loads((d / "q.json").read_text())
    edit(spec)
    (d / "q.json").write_text(json.dumps(spec))
    with pytest.raises(ArtifactError, match=r"q\.(json|npz|\{json,npz\})"):
        q, _ = load_q(d)
        q.values(obs, 0)


def test_npz_header_lying_about_its_size(tree_run, tmp_path):
    """A member whose header declares 10^9 elements in a few bytes: refused from the header."""
    import io
    import zipfile

    src, _ = tree_run
    d = tmp_path / "r"
    import shutil

    shutil.copytree(src, d)
    with np.load(src / "q.npz") as z:
        arrs = node_layout({k: z[k] for k in z.files})
    with zipfile.ZipFile(d / "q.npz", "w") as zf:
        for k, v in arrs.items():
            b = io.BytesIO()
            if k == "q.m0.value":
                np.lib.format.write_array_header_1_0(b, {"descr": "<f8", "fortran_order": False, "shape": (10**9,)})
                b.write(v.tobytes())
            else:
                np.lib.format.write_array(b, v)
            zf.writestr(k + ".npy", b.getvalue())
    with pytest.raises(ArtifactError, match=r"q\.m0\.value"):
        load_q(d)


def test_lightgbm_text_checked_against_features(tmp_path, small_pt):
    f = FittedQIteration(n_iterations=1, regressor="lightgbm", mode="warm_start", trees_per_iteration=2).fit(small_pt)
    save_fqi(f, tmp_path / "r")
    spec = json.loads((tmp_path / "r" / "q.json").read_text())
    text = spec["q"]["boosters"][0]
    spec["q"]["boosters"][0] = text.replace("split_feature=", "split_feature=4000 ",
                                            1).replace("split_feature=4000 ", "split_feature=", 0)
    lines = text.split("\n")
    i = next(i for i, x in enumerate(lines) if x.startswith("split_feature="))
    vals = lines[i].split("=")[1].split()
    vals[0] = "4000"
    lines[i] = "split_feature=" + " ".join(vals)
    spec["q"]["boosters"][0] = "\n".join(lines)
    (tmp_path / "r" / "q.json").write_text(json.dumps(spec))
    out = _load_in_child(tmp_path / "r", small_pt.arrays().obs.shape[1])
    assert out.startswith("ArtifactError:") and "split_feature" in out, out


def test_policy_artifact_of_a_run_is_checked_the_same_way(tree_run, tmp_path):
    """`evaluate` loads RUN/model/policy.json (a greedy policy holding the Q arrays)."""
    from offline_adp.artifacts import load_index_policy, save_policy
    from offline_adp.policies import GreedyPolicy

    src, obs = tree_run
    q, _ = load_q(src)
    save_policy(GreedyPolicy(q), tmp_path / "model")
    with np.load(tmp_path / "model" / "policy.npz") as z:
        arrs = node_layout({k: z[k].copy() for k in z.files})
    key = next(k for k in arrs if k.endswith(".feature"))
    arrs[key][0] = -7
    np.savez(tmp_path / "model" / "policy.npz", **arrs)
    with pytest.raises(ArtifactError, match=r"policy\.\{json,npz\}: .*feature: negative split feature -7"):
        load_index_policy(tmp_path / "model")


@pytest.mark.integration
def test_evaluate_on_a_crafted_run_exits_2_with_one_line(tmp_path):
    """The issue's scenario: a run directory shared by a colleague, with an out-of-range
    feature index in the saved trees; `offline-adp evaluate` used to segfault."""
    from offline_adp.cli import main
    from offline_adp.simulate import simulate

    simulate("gridworld", 3, 3, seed=2, horizon=30).save(tmp_path / "ds")
    (tmp_path / "fit.toml").write_text("[fqi]\nn_iterations = 2\nregressor_params = { n_estimators = 2, n_jobs = 1 }\n")
    assert main(["fit", str(tmp_path / "ds"), "--out", str(tmp_path / "run"), "--algorithm", "fqi",
                 "--config", str(tmp_path / "fit.toml"), "-q"]) == 0
    model = tmp_path / "run" / "model"
    with np.load(model / "q.npz") as z:
        arrs = {k: z[k].copy() for k in z.files}
    arrs["q.m0.feature"][0] = np.iinfo(arrs["q.m0.feature"].dtype).max  # far beyond the 2 features (stored compactly)
    np.savez(model / "q.npz", **arrs)
    rj = json.loads((tmp_path / "run" / "run.json").read_text())
    rj.pop("model_sha256")  # the colleague rewrote run.json too: the structural check must hold on its own
    (tmp_path / "run" / "run.json").write_text(json.dumps(rj))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "offline_adp", "evaluate", str(tmp_path / "run"), "--episodes", "2",
                        "-q"],
                       capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 2, (r.returncode, r.stderr[-500:])
    lines = [x for x in r.stderr.strip().splitlines() if x.strip()]
    assert "Traceback" not in r.stderr and lines[-1].startswith("offline-adp evaluate: error:")
    assert "q.m0.feature" in lines[-1] and "model/q." in lines[-1]


def test_stored_parameters_cannot_make_a_model_edit_its_input(tmp_path, small_pt):
    """Found by the nightly fuzz: a feature map stored with copy=False scaled the caller's
    observations in place (e.g. a dataset's arrays) on every prediction."""
    from sklearn.preprocessing import StandardScaler

    f = FittedQIteration(n_iterations=1, regressor="knn", feature_map=StandardScaler()).fit(small_pt)
    save_fqi(f, tmp_path / "r")
    spec = json.loads((tmp_path / "r" / "q.json").read_text())
    spec["q"]["encoder"]["feature_map"]["params"]["copy"] = False
    (tmp_path / "r" / "q.json").write_text(json.dumps(spec))
    q, _ = load_q(tmp_path / "r")
    obs = small_pt.arrays().obs[:20].copy()
    before = obs.copy()
    np.testing.assert_array_equal(q.values(obs, 0), f.q_function_.values(before, 0))
    np.testing.assert_array_equal(obs, before)
