"""Fuzzing saved artifacts: every mutation either loads and predicts, or is one ArtifactError.

Saved Q-functions of several kinds (extra-trees, frozen trees, LightGBM warm start,
ridge + scaler pipeline, lookup table, a PSDP-style classifier policy) are mutated at
random - array values (indices, thresholds, dtypes, shapes), JSON entries, LightGBM model
text, raw bytes - and loaded. Required: a clean :class:`ArtifactError`, or a model that
loads and predicts arrays of the right shape (the same values when the mutation changed
nothing). Never another exception, a crash or a hang (``faulthandler`` aborts the run
after ``HANG_S`` seconds, so a hang fails loudly instead of stalling CI).

Counts: CI runs ``N`` examples per strategy; ``pytest --hypothesis-profile nightly``
runs ``N_NIGHTLY``.
"""

from __future__ import annotations

import faulthandler
import io
import json
import shutil
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sklearn.preprocessing import StandardScaler

from offline_adp.algorithms.fqi import FittedQIteration, save_fqi
from offline_adp.artifacts import load_index_policy, load_q
from offline_adp.errors import ArtifactError
from tests.fuzz_util import edit_json_path, json_paths

NIGHTLY = settings().max_examples >= 1000
N = 2000 if NIGHTLY else 40
HANG_S = 60
KINDS = ["trees", "frozen", "warm_start", "ridge", "tabular", "knn", "mlp"]
_FIT = {
    "trees": dict(regressor="extra_trees", regressor_params={"n_estimators": 3, "n_jobs": 1, "min_samples_leaf": 5}),
    "frozen": dict(regressor="extra_trees", regressor_params={"n_estimators": 2, "n_jobs": 1, "min_samples_leaf": 5},
                   mode="frozen"),
    "warm_start": dict(regressor="lightgbm", mode="warm_start", trees_per_iteration=2),
    "ridge": dict(regressor="ridge", action_encoding="per_action"),
    "tabular": dict(regressor="tabular", horizon=2),
    "knn": dict(regressor="knn", feature_map=StandardScaler()),
    "mlp": dict(regressor="mlp", regressor_params={"max_iter": 5, "hidden_layer_sizes": (4,)}),
}


@pytest.fixture(scope="module")
def saved(tmp_path_factory, small_pt):
    """One saved artifact per kind, its reference predictions, and observations."""
    out = {}
    obs = small_pt.arrays().obs[::13]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for kind in KINDS:
            f = FittedQIteration(n_iterations=2, **_FIT[kind]).fit(small_pt)
            d = tmp_path_factory.mktemp(kind)
            save_fqi(f, d)
            out[kind] = (d, f.q_function_.values(obs, 0))
    return out, obs


def _copy(src: Path, dst: Path) -> Path:
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    return dst


def _check(d: Path, obs: np.ndarray, ref: np.ndarray, unchanged: bool, tag: str) -> str:
    """Load + predict; returns "rejected" or "loaded"; any other outcome fails the test."""
    out = _outcome(d, obs, ref, unchanged)
    return out


def _outcome(d: Path, obs: np.ndarray, ref: np.ndarray, unchanged: bool) -> str:
    faulthandler.dump_traceback_later(HANG_S, exit=True)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                q, _ = load_q(d)
                x = obs.copy()
                v = np.asarray(q.values(x, 0))
                np.testing.assert_array_equal(x, obs)  # a crafted artifact must not edit its input
            except ArtifactError as exc:
                assert str(exc) and "\n" not in str(exc).strip().splitlines()[0]
                return "rejected"
    finally:
        faulthandler.cancel_dump_traceback_later()
    assert v.shape == ref.shape
    if unchanged:
        np.testing.assert_array_equal(v, ref)
    return "loaded"


# ----------------------------------------------------------------------------- strategies
INTERESTING_INTS = [-(2**63), -(2**31) - 1, -3, -2, -1, 0, 1, 2, 3, 7, 2**31, 2**62]
INTERESTING_FLOATS = [np.nan, np.inf, -np.inf, 0.0, -0.0, 1e308, -1e308, 5e-324, 0.5]


def _npz_members(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


@st.composite
def array_mutation(draw):
    return {
        "pick": draw(st.integers(0, 10_000)),
        "op": draw(st.sampled_from(["set", "set", "set", "truncate", "extend", "reshape", "dtype", "drop", "object",
                                    "rename"])),
        "pos": draw(st.integers(0, 10_000)),
        "int": draw(st.one_of(st.sampled_from(INTERESTING_INTS), st.integers(-1000, 1000))),
        "float": draw(st.one_of(st.sampled_from(INTERESTING_FLOATS), st.floats(allow_nan=True))),
        "dtype": draw(st.sampled_from(["float32", "int8", "uint64", "bool", "<U3", "complex128"])),
    }


def _apply_array(arrs: dict[str, np.ndarray], m: dict) -> dict[str, np.ndarray]:
    keys = sorted(arrs)
    k = keys[m["pick"] % len(keys)]
    a = arrs[k].copy()
    op = m["op"]
    if op == "set" and a.size:
        flat = a.reshape(-1)
        i = m["pos"] % a.size
        if a.dtype.kind in "iu":
            v = m["int"]
            if a.dtype.kind == "u":
                v = abs(v)
            info = np.iinfo(a.dtype)
            flat[i] = min(max(v, info.min), info.max)
        elif a.dtype.kind == "f":
            flat[i] = m["float"]
        elif a.dtype.kind == "b":
            flat[i] = not flat[i]
        a = flat.reshape(a.shape)
    elif op == "truncate":
        a = a.reshape(-1)[: (m["pos"] % max(a.size, 1))]
    elif op == "extend":
        a = np.concatenate([a.reshape(-1), a.reshape(-1)[:1]]) if a.size else a
    elif op == "reshape":
        a = a.reshape(-1, 1) if a.ndim == 1 else a.reshape(-1)
    elif op == "dtype":
        try:
            a = a.astype(m["dtype"])
        except (TypeError, ValueError):
            pass
    elif op == "drop":
        arrs = {x: y for x, y in arrs.items() if x != k}
        return arrs
    elif op == "object":
        a = np.array([None, 1], dtype=object)
    elif op == "rename":
        arrs = {(x + "x" if x == k else x): y for x, y in arrs.items()}
        return arrs
    arrs = dict(arrs)
    arrs[k] = a
    return arrs


@settings(max_examples=N, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(kind=st.sampled_from(KINDS), m=array_mutation())
def test_fuzz_npz_arrays(saved, tmp_path, kind, m):
    arts, obs = saved
    src, ref = arts[kind]
    d = _copy(src, tmp_path / "a")
    arrs = _apply_array(_npz_members(src / "q.npz"), m)
    np.savez(d / "q.npz", **arrs)  # object arrays are pickled in: an attacker's file may hold them
    unchanged = (set(arrs) == set(_npz_members(src / "q.npz"))) and all(
        arrs[k].dtype == b.dtype and arrs[k].shape == b.shape and arrs[k].tobytes() == b.tobytes()
        for k, b in _npz_members(src / "q.npz").items())
    _check(d, obs, ref, unchanged, "npz arrays")


JSON_VALUES = [None, -1, 0, 1, 2, 10**9, 2**64, -(2**63), "x", "", [], {}, [[]], True, 1e308, float("nan"), "q.m0.left",
               {"kind": "sklearn", "class": "os.system", "params": {}, "attrs": {}}]


@settings(max_examples=N, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(kind=st.sampled_from(KINDS), pick=st.integers(0, 100_000), value=st.sampled_from(JSON_VALUES),
       delete=st.booleans())
def test_fuzz_json(saved, tmp_path, kind, pick, value, delete):
    arts, obs = saved
    src, ref = arts[kind]
    d = _copy(src, tmp_path / "j")
    spec = json.loads((src / "q.json").read_text())
    paths = [p for p in json_paths(spec) if p and p[0] == "q"]
    path = paths[pick % len(paths)]
    edit_json_path(spec, path, value, delete)
    (d / "q.json").write_text(json.dumps(spec))
    _check(d, obs, ref, False, "json entries")


@settings(max_examples=N, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(pick=st.integers(0, 10**9), token=st.sampled_from(["-1", "0", "1", "2", "3", "99", "-99", "nan", "inf", "1e308",
                                                          "x", "", "-2147483648", "2147483647"]),
       which=st.integers(0, 50))
def test_fuzz_lightgbm_text(saved, tmp_path, pick, token, which):
    arts, obs = saved
    src, ref = arts["warm_start"]
    d = _copy(src, tmp_path / "l")
    spec = json.loads((src / "q.json").read_text())
    boosters = spec["q"]["boosters"]
    b = which % len(boosters)
    lines = boosters[b].split("\n")
    numeric = [i for i, line in enumerate(lines) if "=" in line and any(c.isdigit() for c in line.partition("=")[2])]
    i = numeric[pick % len(numeric)]
    key, _, vals = lines[i].partition("=")
    parts = vals.split(" ")
    parts[(pick // len(numeric)) % len(parts)] = token
    lines[i] = key + "=" + " ".join(parts)
    boosters[b] = "\n".join(lines)
    (d / "q.json").write_text(json.dumps(spec))
    _check(d, obs, ref, False, "lightgbm text")


@settings(max_examples=N, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(kind=st.sampled_from(KINDS), target=st.sampled_from(["q.npz", "q.json"]),
       edits=st.lists(st.tuples(st.integers(0, 10**9), st.integers(0, 255)), min_size=1, max_size=8),
       cut=st.integers(0, 20))
def test_fuzz_bytes(saved, tmp_path, kind, target, edits, cut):
    arts, obs = saved
    src, ref = arts[kind]
    d = _copy(src, tmp_path / "b")
    raw = bytearray((src / target).read_bytes())
    for pos, byte in edits:
        raw[pos % len(raw)] = byte
    if cut == 0:  # sometimes truncate
        raw = raw[: edits[0][0] % len(raw)]
    (d / target).write_bytes(bytes(raw))
    _check(d, obs, ref, bytes(raw) == (src / target).read_bytes(), "raw bytes")


def test_policy_artifacts_fuzzed_by_bytes(tmp_path, small_pt):
    """The policy loader gets the same treatment (a tabular policy, byte edits)."""
    from offline_adp.artifacts import save_policy
    from offline_adp.policies import TabularPolicy

    pi = TabularPolicy(np.full((4, 3), 1 / 3))
    save_policy(pi, tmp_path / "p")
    rng = np.random.default_rng(0)
    for trial in range(30 if not NIGHTLY else 1000):
        d = _copy(tmp_path / "p", tmp_path / f"t{trial % 2}")
        target = d / ("policy.npz" if trial % 2 else "policy.json")
        raw = bytearray(target.read_bytes())
        for _ in range(3):
            raw[rng.integers(len(raw))] = rng.integers(256)
        target.write_bytes(bytes(raw))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                p = load_index_policy(d)
                p.probabilities(np.zeros((2, 1), np.int64), 0)
        except ArtifactError:
            pass


def test_compressed_bomb_is_refused_before_allocation(tmp_path, small_pt):
    """A small q.npz whose deflated member expands to ~400 MB is refused by its headers."""
    f = FittedQIteration(n_iterations=1, **_FIT["trees"]).fit(small_pt)
    save_fqi(f, tmp_path / "r")
    path = tmp_path / "r" / "q.npz"
    members = _npz_members(path)
    n = 50_000_000  # float64 zeros: 400 MB, compresses to ~400 KB
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": (n,)})
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for k, v in members.items():
            if k == "q.m0.value":
                continue
            with zf.open(k + ".npy", "w") as fh:
                np.lib.format.write_array(fh, v)
        with zf.open("q.m0.value.npy", "w", force_zip64=True) as fh:
            fh.write(buf.getvalue())
            chunk = bytes(1 << 22)
            for _ in range(n * 8 // len(chunk)):
                fh.write(chunk)
    assert path.stat().st_size < 2_000_000
    with pytest.raises(ArtifactError, match="q.m0.value"):
        load_q(tmp_path / "r")
