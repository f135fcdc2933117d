"""The supported-sup bootstrap (evaluation/shift.py) drawn and counted a block of
replicates at a time gives the numbers of one replicate at a time, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp.evaluation import shift


def _one_at_a_time(obs, w, *, k=20, n_boot=200, level=0.95, cover_ratio=20.0, seed=0):
    """supported_sup as it was written: one draw and two bincounts per replicate."""
    leaf = shift._leaves(obs, w, k, seed)
    _, inv = np.unique(leaf, return_inverse=True)
    inv = inv.reshape(-1)
    cnt = np.bincount(inv)
    mean = np.bincount(inv, weights=w) / cnt
    rng = np.random.default_rng(seed)
    sups = np.empty(n_boot)
    for b in range(n_boot):
        idx = rng.integers(0, len(w), len(w))
        c = np.bincount(inv[idx], minlength=len(cnt))
        s = np.bincount(inv[idx], weights=w[idx], minlength=len(cnt))
        sups[b] = np.max(np.where(c >= max(1, k // 2), s / np.maximum(c, 1), 0.0))
    poorly = mean[inv] > cover_ratio
    ucb = max(float(np.quantile(sups, level)), float(mean.max())) if n_boot else float(mean.max())
    return {"supported_sup": float(mean.max()), "sup_ucb": ucb,
            "poorly_covered_mass": float(np.sum(w[poorly]) / max(np.sum(w), 1e-300)), "n_regions": int(len(cnt))}


@pytest.mark.parametrize("n, k, n_boot", [(47, 20, 200), (301, 20, 200), (1000, 5, 37), (9, 20, 10), (2000, 20, 0)])
@pytest.mark.parametrize("block", [1 << 21, 1000])  # one block, and blocks of a few replicates
def test_blocked_resampling_is_bit_identical(monkeypatch, n, k, n_boot, block):
    monkeypatch.setattr(shift, "_RESAMPLE_BLOCK", block)
    rng = np.random.default_rng(n)
    obs = rng.normal(size=(n, 3))
    w = np.exp(2 * rng.normal(size=n))
    for seed in (0, 7):
        assert shift.supported_sup(obs, w, k=k, n_boot=n_boot, seed=seed) == \
            _one_at_a_time(obs, w, k=k, n_boot=n_boot, seed=seed)
