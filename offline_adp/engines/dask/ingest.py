"""Distributed ingestion: one task per input file on the workers, one dataset written
(atomically, in the given file order) by the client."""

from __future__ import annotations

from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd


def _ingest_file(path: str | list[str], spec: Any, fmt: str, on_error: str | None) -> tuple[Any, Any, Any]:
    """One file (MCAP: one recording, i.e. a file or the parts of a split recording) ->
    (dataset, doctor findings, quarantined rows or None) on a worker; nothing is written there."""
    if fmt == "parquet":
        from offline_adp.ingest.parquet import ingest_tables

        res = ingest_tables([path], spec, on_error=on_error)
        return res.dataset, res.report.findings.assign(file=str(path)), res.quarantine
    from offline_adp.ingest.mcap.build import ingest_mcap_tables

    parts = path if isinstance(path, list) else [path]
    ds, quarantine, summary = ingest_mcap_tables(parts, spec, on_error=on_error)
    return (ds, pd.DataFrame([{**{k: v for k, v in summary.items() if np.isscalar(v)}, "file": ", ".join(parts)}]),
            quarantine)


def ingest_distributed(client: Any, files: list[str | PathLike[str]], spec: Any, out: str | PathLike[str], *,
                       fmt: str = "parquet", on_error: str | None = None,
                       overwrite: bool = False) -> tuple[Any, pd.DataFrame]:
    """Ingest many files in parallel on the workers (one task per file, the doctor run per
    file), then concatenate in the given file order and write one dataset (atomically).

    Returns the dataset and the merged per-file reports. ``spec`` is a parsed spec
    (:class:`~offline_adp.ingest.spec.ParquetSpec` or ``McapSpec``) or a spec file path.
    """
    from offline_adp.data.dataset import TransitionDataset
    from offline_adp.data.io import write_dataset

    if isinstance(spec, str | Path):
        if fmt == "parquet":
            from offline_adp.ingest.spec import load_parquet_spec

            spec = load_parquet_spec(spec)
        else:
            from offline_adp.ingest.mcap import load_mcap_spec

            spec = load_mcap_spec(spec)
    paths: list[Any] = [str(Path(f).resolve()) for f in files]
    if fmt == "mcap":  # the parts of a split recording stay together
        from offline_adp.ingest.mcap import resolve_sources

        paths = [[str(p) for p in rec] for rec in resolve_sources(paths, spec)]
    from offline_adp.data.io import check_dataset_output

    check_dataset_output(out, [p for rec in paths for p in ([rec] if isinstance(rec, str) else rec)])
    futures = client.map(_ingest_file, paths, spec=spec, fmt=fmt, on_error=on_error, pure=False)
    results = client.gather(futures)  # in file order: deterministic part order
    ds = TransitionDataset.concat([r[0] for r in results])
    from offline_adp.data.repeats import warn_repeated

    warn_repeated(ds, f"{len(paths)} files ingested on the cluster")  # across files too (a file copied)
    quarantined = [r[2] for r in results if r[2] is not None and r[2].num_rows]
    import pyarrow as pa

    write_dataset(ds, out, overwrite=overwrite,
                  quarantine=pa.concat_tables(quarantined, promote_options="default") if quarantined else None)
    return ds, pd.concat([r[1] for r in results], ignore_index=True)

