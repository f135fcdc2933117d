"""Parquet files written through a write buffer (``offline_adp.data.io.write_parquet``) are
``pq.write_table``'s bytes: held to the plain computation it replaces, byte for byte."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from offline_adp.data.io import write_parquet

_SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _table(seed: int, n: int) -> pa.Table:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=n)
    x[rng.random(n) < 0.05] = np.nan
    ids = np.char.add("ep-", (np.arange(n) // 7).astype(str))
    return pa.table({
        "episode": pa.array(ids),
        "step": pa.array(np.arange(n) % 7, pa.int32()),
        "x": pa.array(x, mask=rng.random(n) < 0.1),
        "flag": pa.array(rng.random(n) < 0.5),
        "label": pa.array(rng.choice(["a", "bb", "ccc"], n)),
        "big": pa.array(rng.integers(-(2**62), 2**62, n), pa.int64()),
        "f32": pa.array(rng.random(n).astype(np.float32)),
    })


@_SETTINGS
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 3000),
       options=st.sampled_from([
           {},
           {"compression": "lz4", "use_dictionary": ["episode", "label", "flag"],
            "column_encoding": {"x": "BYTE_STREAM_SPLIT", "f32": "BYTE_STREAM_SPLIT", "step": "PLAIN",
                                "big": "DELTA_BINARY_PACKED"},
            "write_statistics": ["step", "big"], "write_batch_size": 1 << 16},
           {"compression": "zstd", "data_page_size": 1 << 10},
       ]))
def test_write_parquet_writes_the_bytes_of_write_table(tmp_path: Path, seed: int, n: int, options: dict) -> None:
    t = _table(seed, n)
    pq.write_table(t, tmp_path / "plain.parquet", **options)
    write_parquet(t, tmp_path / "buffered.parquet", **options)
    assert (tmp_path / "plain.parquet").read_bytes() == (tmp_path / "buffered.parquet").read_bytes()
