"""Episodes logged twice (offline_adp.data.repeats) against a brute-force oracle, and the
ingests' warning and count."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest

from offline_adp.data.repeats import repeated_episodes
from offline_adp.errors import LogWarning
from offline_adp.simulate import simulate


def _oracle(ds):
    """Every episode equal (all its columns but the id, row for row) to an earlier one: pandas, pairwise."""
    df = ds.to_pandas()
    keep = [c for c in df.columns if c not in ("episode_id", "source", "truncated", "terminated")]
    eps = [(str(k), g[keep].reset_index(drop=True)) for k, g in df.groupby("episode_id", sort=False)]
    order = {str(e): i for i, e in enumerate(ds.episode_ids)}
    eps.sort(key=lambda kv: order[kv[0]])
    out = []
    for i, (k, g) in enumerate(eps):
        first = next((k2 for k2, g2 in eps[:i] if g2.shape == g.shape and g2.equals(g)
                      and not any(k2 == a for a, _ in out)), None)
        if first is not None:
            out.append((k, first))
    return out


@pytest.mark.parametrize("seed", range(4))
def test_repeats_are_what_a_pairwise_comparison_finds(seed):
    rng = np.random.default_rng(seed)
    ds = simulate("path_tracking", 8, 8, seed=seed, horizon=12)
    df = ds.to_pandas()
    ids = list(ds.episode_ids)
    parts = [df]
    for j, e in enumerate(rng.choice(ids, size=4, replace=True)):  # copies, some of the same episode
        c = df[df.episode_id == e].copy()
        c["episode_id"] = f"copy{j}"
        if j == 3:  # a near copy: one cost differs in the last digit
            c.iloc[-1, c.columns.get_loc("cost")] = np.nextafter(c["cost"].iloc[-1], np.inf)
        parts.append(c)
    both = type(ds).from_pandas(pd.concat(parts), ds.info)
    got = repeated_episodes(both)
    assert sorted(got) == sorted(_oracle(both))
    assert len(got) == 3 and not any(a == "copy3" for a, _ in got)
    assert repeated_episodes(ds) == _oracle(ds) == []


def test_the_ingests_warn_of_a_recording_ingested_twice_and_count_it(tmp_path):
    from offline_adp.ingest.parquet import ingest_parquet
    from offline_adp.simulate.raw import raw_table, write_raw

    ds = simulate("path_tracking", 4, 4, seed=5, horizon=10)
    raw, spec = write_raw(ds, tmp_path / "a.parquet")
    t, _ = raw_table(ds)
    dup = t.to_pandas()
    dup["episode"] = "again-" + dup["episode"].astype(str)
    dup.to_parquet(tmp_path / "b.parquet")
    with pytest.warns(LogWarning, match=r"8 of 16 episodes repeat an earlier episode row for row \('"):
        res = ingest_parquet([tmp_path / "a.parquet", tmp_path / "b.parquet"], spec, tmp_path / "ds")
    assert res.summary()["repeated_episodes"] == 8 and res.dataset.n_episodes == 16  # reported, nothing dropped
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogWarning)
        assert ingest_parquet([tmp_path / "a.parquet"], spec, tmp_path / "one").summary()["repeated_episodes"] == 0
