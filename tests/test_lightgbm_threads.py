"""LightGBM's default thread count (issue #33: n_jobs=-1 spun OpenMP threads on a loaded machine)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("lightgbm")

from offline_adp.regressors import LIGHTGBM_DEFAULT_THREADS, make_regressor  # noqa: E402


def test_default_lightgbm_trains_on_one_thread_and_an_explicit_count_is_kept():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(400, 3))
    y = X @ np.array([1.0, -2.0, 0.5]) + 0.1 * rng.normal(size=400)
    default = make_regressor("lightgbm", n_estimators=5).fit(X, y)
    assert LIGHTGBM_DEFAULT_THREADS == 1
    assert default.booster_.params["num_threads"] == 1  # what the booster was trained with
    two = make_regressor("lightgbm", n_estimators=5, n_jobs=2).fit(X, y)
    assert two.booster_.params["num_threads"] == 2
    # the thread count does not change this fit's trees
    np.testing.assert_allclose(default.predict(X), two.predict(X), rtol=0, atol=1e-12)
