"""``small_pages`` (offline_adp.data.pages): transparent huge pages off for the process while
an ingestion runs, the previous setting restored afterwards, nested blocks included."""

from __future__ import annotations

import sys

import pytest

from offline_adp.data import pages


@pytest.mark.skipif(not sys.platform.startswith("linux") or pages.thp_disabled() is None,
                    reason="prctl(PR_GET_THP_DISABLE) is Linux only")
def test_small_pages_turns_huge_pages_off_and_restores_the_setting() -> None:
    assert pages.thp_disabled() is False
    with pages.small_pages():
        assert pages.thp_disabled() is True
        with pages.small_pages():
            assert pages.thp_disabled() is True
        assert pages.thp_disabled() is True  # the outer block still runs
    assert pages.thp_disabled() is False
    with pytest.raises(RuntimeError), pages.small_pages():  # restored on an error too
        raise RuntimeError
    assert pages.thp_disabled() is False


def test_small_pages_does_nothing_without_prctl(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pages, "_PRCTL", None)
    assert pages.thp_disabled() is None
    with pages.small_pages():
        assert pages.thp_disabled() is None


def test_ingestion_leaves_the_setting_as_it_found_it(tmp_path) -> None:
    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    from offline_adp.ingest.parquet import ingest_parquet

    before = pages.thp_disabled()
    n = 6
    pq.write_table(pa.table({"ep": ["a"] * n, "t": np.arange(n), "x": np.arange(n, dtype=float),
                             "nx": np.arange(1, n + 1, dtype=float), "u": np.zeros(n), "c": np.ones(n),
                             "done": [False] * (n - 1) + [True]}), tmp_path / "t.parquet")
    (tmp_path / "spec.toml").write_text(
        'kind = "transitions"\n[episode]\nid = "ep"\nstep = "t"\n[observations]\ncolumns = ["x"]\n'
        'next_columns = ["nx"]\n[action]\ncolumn = "u"\nvalues = [0.0]\n[cost]\ncolumn = "c"\n'
        '[end]\nterminated = "done"\n')
    res = ingest_parquet([tmp_path / "t.parquet"], tmp_path / "spec.toml", tmp_path / "ds")
    assert len(res.dataset) == n and res.report.ok
    assert pages.thp_disabled() == before
