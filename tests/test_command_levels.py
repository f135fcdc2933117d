"""Logged command levels stay apart (``data/levels.py``): a keyboard teleop's -0.2 / 0 / +0.2
came back from the quantile bins as -0.2 and 0.0504 (0 and 0.2 merged), and the policy sent
0.0504, a command nobody logged."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
from hypothesis import given, settings
from hypothesis import strategies as st

from offline_adp.algorithms.fqi_data import command_representatives
from offline_adp.data.levels import cell_means, level_edges
from offline_adp.ingest.actions import bin_continuous, bin_product, coarse_bins
from offline_adp.ingest.spec import ActionSpec


def _bins(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    return np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)


@settings(max_examples=60, deadline=None)
@given(levels=st.lists(st.sampled_from([-0.3, -0.2, 0.0, 0.1, 0.2, 1e-12, 7.0]), min_size=0, max_size=400),
       noise=st.integers(0, 300), n_bins=st.integers(1, 20), seed=st.integers(0, 10))
def test_level_edges_give_each_frequent_level_its_own_bin(levels, noise, n_bins, seed):
    x = np.r_[np.asarray(levels, float), np.random.default_rng(seed).normal(size=noise)]
    if not len(x):
        assert len(level_edges(x, n_bins)) == 0
        return
    e = level_edges(x, n_bins)
    assert np.all(np.diff(e) > 0) and e[0] <= x.min() and e[-1] >= x.max()
    if len(e) < 2:  # one distinct value, no level rule needed (a single row)
        assert len(np.unique(x)) == 1
        return
    b = _bins(x, e)
    assert np.bincount(b, minlength=len(e) - 1).min() > 0  # no empty bin
    vals, counts = np.unique(x, return_counts=True)
    frequent = vals[(counts >= 2) & (counts >= len(x) / n_bins)] if len(vals) > n_bins else vals
    for v in frequent:  # alone in its bin
        assert np.all(x[b == b[x == v][0]] == v), (v, e)


def test_level_edges_are_the_quantile_edges_without_repeated_values():
    x = np.random.default_rng(0).normal(size=5000)
    for B in (1, 4, 16, 100):
        np.testing.assert_array_equal(level_edges(x, B), np.unique(np.quantile(x, np.linspace(0, 1, B + 1))))


def test_cell_means_are_exact_on_constant_cells_and_the_plain_mean_elsewhere():
    rng = np.random.default_rng(1)
    cell = rng.integers(0, 5, 3000)
    x = np.where(cell == 2, 0.2, np.where(cell == 4, -1e-17, rng.normal(size=3000)))
    mean, counts = cell_means(cell, x, 7)
    assert mean[2] == 0.2 and mean[4] == -1e-17  # np.mean of 600 x 0.2 is not 0.2
    for k in (0, 1, 3):
        assert mean[k] == np.bincount(cell, weights=x, minlength=7)[k] / counts[k]
    assert np.isnan(mean[5:]).all() and (counts[5:] == 0).all()


def _keyboard(n: int = 3000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    steer = rng.choice([-0.2, 0.0, 0.2], n, p=[0.3, 0.5, 0.2])
    throttle = rng.choice([0.0, 0.5], n, p=[0.1, 0.9])
    return np.column_stack([steer, throttle])


def test_representatives_of_a_log_of_levels_are_its_levels():
    u = _keyboard()
    reps = command_representatives(u, 16)
    logged = {tuple(r) for r in u}
    assert {tuple(r) for r in reps} == logged  # every logged pair, exactly, and nothing else
    # levels beside continuous commands: the level comes back exactly, the rest are logged commands
    v = np.r_[np.zeros(400), np.random.default_rng(2).uniform(-1, 1, 600)][:, None]
    reps = command_representatives(v, 16)[:, 0]
    assert 0.0 in reps and len(reps) <= 16 + 2
    assert reps.min() >= v.min() and reps.max() <= v.max() and np.isin(reps, v[:, 0]).all()


def test_ingest_bins_keep_levels_apart():
    u = _keyboard()
    idx, table = coarse_bins(u, ("steer", "throttle"))
    got = {tuple(a.value) for a in table.actions if np.any(idx == table.actions.index(a))}
    assert got == {tuple(r) for r in u}
    np.testing.assert_array_equal(np.array([table.actions[i].value for i in idx]), u)  # each row's cell is its command
    idx, table = bin_continuous(u[:, 0], ActionSpec(column="steer", type="continuous", n_bins=8), where="t")
    assert sorted(a.value[0] for a in table.actions) == [-0.2, 0.0, 0.2]
    idx, table = bin_product(u, {"steer": {"n_bins": 8}, "throttle": {"n_bins": 8}}, ("steer", "throttle"))
    occupied = {table.actions[i].value for i in np.unique(idx)}
    assert occupied == {tuple(r) for r in u}
    assert isinstance(pa.array(idx), pa.Array)


def test_coarse_bins_keep_the_cell_cap_with_levels():
    from offline_adp.ingest.actions import MAX_COARSE_CELLS

    rng = np.random.default_rng(0)
    for k in (2, 3, 12):  # half of every component idle at 0: a level's own bin in each
        x = np.where(rng.random((5000, k)) < 0.5, 0.0, rng.normal(size=(5000, k)))
        idx, table = coarse_bins(x, tuple(f"d{i}" for i in range(k)))
        assert len(table.actions) <= MAX_COARSE_CELLS and idx.max() < len(table.actions)


def test_a_level_and_the_bin_above_it_never_share_a_name():
    rng = np.random.default_rng(0)
    x = np.r_[np.full(600, 0.2), rng.uniform(0.2, 0.20004, 200), rng.uniform(0.3, 1.0, 1200)]
    idx, table = bin_continuous(x, ActionSpec(column="u", type="continuous", n_bins=8), where="t")
    names = [a.name for a in table.actions]
    assert len(set(names)) == len(names)  # "a~0.2" twice refused the ingest
