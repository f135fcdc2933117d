"""Fits are bit-for-bit the same on any x86-64 CPU (issue: same results on every machine).

The compiled tree builder is compiled by numba for the CPU it runs on. Two compilations of
it, one for this machine's CPU and one for a generic x86-64 (``NUMBA_CPU_NAME=generic``:
no AVX, no FMA), each in a fresh process with an empty compilation cache, fit the same
small problem with the default FQI; the two fitted Q-functions must be equal to the last
bit (leaf values, thresholds, and Q on the logged states). A kernel compiled with
reassociating or contracting fast-math flags fails this on a machine with FMA.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from offline_adp.trees import builder as extra_trees

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not extra_trees.available(), reason="numba is not installed")]

_FIT = textwrap.dedent("""
    import hashlib, json, warnings
    import numpy as np
    from offline_adp.algorithms.fqi import FittedQIteration, structure_builds
    from offline_adp.simulate import simulate
    from offline_adp.trees import builder as extra_trees

    ds = simulate("car_on_hill", 20, 80, seed=3, horizon=60)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        f = FittedQIteration(gamma=0.95, n_iterations=12, random_state=0).fit(ds)
    a = ds.arrays()
    q = np.ascontiguousarray(f.q_function_.values(a.obs), dtype=np.float64)
    builders = sorted({b["builder"] for b in structure_builds(f.history_) if b["builder"]})
    print(json.dumps({"q": hashlib.sha256(q.tobytes()).hexdigest(), "n": int(q.size),
                      "q_sum": float(q.sum()), "builders": builders,
                      "compiled": extra_trees.available()}))
""")


def _fit_in_fresh_process(tmp: Path, cpu_name: str | None) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env["NUMBA_CACHE_DIR"] = str(tmp)  # an empty cache: the kernel is compiled here, for this CPU
    if cpu_name is not None:
        env["NUMBA_CPU_NAME"] = cpu_name
        env["NUMBA_CPU_FEATURES"] = ""
    out = subprocess.run([sys.executable, "-c", _FIT], env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_tree_builder_compiled_for_host_and_generic_cpu_fits_the_same_q(tmp_path):
    host = _fit_in_fresh_process(tmp_path / "host", None)
    generic = _fit_in_fresh_process(tmp_path / "generic", "generic")
    assert host["builders"] == generic["builders"] == ["compiled"]  # the kernel under test grew the trees
    assert host["n"] == generic["n"] > 0
    assert host["q"] == generic["q"], (host, generic)


def test_the_kernels_use_no_flag_that_changes_a_finite_result():
    # the flags are the whole contract; a regression to fastmath=True must fail here too,
    # on machines where both compilations happen to agree
    allowed = {"nnan", "ninf"}
    assert set(extra_trees._FAST) <= allowed
    for name in ("_grow", "_minmax4", "_left_sums4", "_left_sums4_unweighted"):
        fm = getattr(extra_trees, name).targetoptions.get("fastmath")
        flags = set(getattr(fm, "flags", fm) or ())
        assert flags <= allowed, (name, flags)


def test_same_seed_same_bits_in_one_process():
    rng = np.random.default_rng(0)
    X, y = rng.normal(size=(400, 3)), rng.normal(size=400)
    from sklearn.ensemble import ExtraTreesRegressor

    p = extra_trees.native_params(ExtraTreesRegressor(n_estimators=3, random_state=5, n_jobs=1), 400, 3)
    assert p is not None
    h = [hashlib.sha256(b"".join(np.asarray(g.threshold).tobytes() + np.asarray(g.value).tobytes()
                                 for g in extra_trees.grow_trees(X, y, None, p))).hexdigest() for _ in range(2)]
    assert h[0] == h[1]


@pytest.mark.parametrize("mode", ["auto", "refit"])
def test_the_fit_does_not_depend_on_the_number_of_threads(mode):
    import warnings

    from offline_adp.algorithms.fqi import FittedQIteration
    from offline_adp.simulate import simulate

    ds = simulate("car_on_hill", 10, 40, seed=4, horizon=50)
    obs = ds.arrays().obs
    q = []
    for jobs in (1, 2):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            f = FittedQIteration(gamma=0.95, n_iterations=6, random_state=1, mode=mode,
                                 regressor_params={"n_jobs": jobs, "n_estimators": 12}).fit(ds)
        q.append(f.q_function_.values(obs))
    np.testing.assert_array_equal(q[0], q[1])
