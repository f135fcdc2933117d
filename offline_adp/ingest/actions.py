"""Logged commands -> action indices: discrete mapping or binning of continuous commands.

Shared by Parquet and MCAP ingestion. Unmatched discrete values map to index -1 so the
doctor reports them (with file and row) instead of dropping them.
"""

from __future__ import annotations

import numpy as np

from offline_adp.data.info import Action, ActionTable
from offline_adp.errors import IngestError
from offline_adp.ingest.spec import ActionSpec


def _is_numeric(values: np.ndarray) -> bool:
    return values.dtype.kind in "iufb"


def map_discrete(raw: np.ndarray, spec: ActionSpec, *, where: str = "action") -> tuple[np.ndarray, ActionTable]:
    """Map logged discrete labels to indices into the action table.

    The table is ``spec.values`` in the given order, or the sorted distinct values seen.
    Numbers match within 1e-9 (relative); strings match exactly. Rows whose label is
    not in the table get index -1.
    """
    raw = np.asarray(raw)
    numeric = _is_numeric(raw)
    if spec.values is not None:
        table_vals = np.asarray(spec.values)
        if numeric and not _is_numeric(table_vals):
            raise IngestError(f"{where}: column {spec.column!r} holds numbers but action.values are {list(spec.values)}")
    else:
        if not numeric:
            raw = raw.astype(str)
        table_vals = np.unique(raw[~_isnan(raw)] if numeric else raw)
    if numeric:
        tv = table_vals.astype(np.float64)
        x = raw.astype(np.float64, copy=False)
        tol = 1e-9 * np.maximum(1.0, np.abs(tv))
        if len(tv) <= 32:  # one vectorised comparison per action (the last match wins)
            idx = _match_each(x, tv, tol)
        else:  # nearest table value by binary search, then the tolerance check
            order = np.argsort(tv)
            pos = np.searchsorted(tv[order], x)
            lo = order[np.clip(pos - 1, 0, len(tv) - 1)]
            hi = order[np.clip(pos, 0, len(tv) - 1)]
            best = np.where(np.abs(tv[hi] - x) <= np.abs(tv[lo] - x), hi, lo)
            idx = np.where(np.abs(tv[best] - x) <= tol[best], best, -1)
        values = [(float(v),) for v in tv]
    else:
        lookup = {str(v): i for i, v in enumerate(table_vals)}
        uniq, inv = np.unique(raw.astype(str), return_inverse=True)
        codes = np.array([lookup.get(u, -1) for u in uniq], dtype=np.int64)  # per distinct label
        idx = codes[inv]
        values = [(float(i),) for i in range(len(table_vals))]
    dims: tuple[str, ...] = (spec.dim if numeric else f"{spec.dim}_label_index",)
    if spec.vectors is not None:  # explicit value vectors for labels or multi-dimensional commands
        values = [tuple(v) for v in spec.vectors]
        dims = spec.dims or tuple(f"{spec.dim}{i}" for i in range(len(values[0])))
    names = spec.names or [str(v) if not numeric else f"{spec.dim}={float(v):g}" for v in table_vals]
    if len(names) != len(values):
        raise IngestError(f"{where}: action.names has {len(names)} entries for {len(values)} actions")
    table = ActionTable(
        actions=tuple(Action(str(n), v) for n, v in zip(names, values, strict=True)),
        dims=dims,
        units=(spec.unit,) * len(dims) if spec.unit else (),
    )
    return idx.astype(np.int32, copy=False), table


_MATCH_BLOCK = 1 << 14  # values per block of _match_each: its buffers stay in cache


def _match_each(x: np.ndarray, tv: np.ndarray, tol: np.ndarray) -> np.ndarray:
    """Per value of ``x``, the last ``k`` with ``|x - tv[k]| <= tol[k]`` (else -1), int32:
    block by block in place, no temporary the size of ``x``."""
    idx = np.full(len(x), -1, np.int32)
    d = np.empty(min(len(x), _MATCH_BLOCK))
    hit = np.empty(len(d), bool)
    for lo in range(0, len(x), _MATCH_BLOCK):
        xb = x[lo:lo + _MATCH_BLOCK]
        n = len(xb)
        out, db, hb = idx[lo:lo + n], d[:n], hit[:n]
        for k in range(len(tv)):
            np.subtract(xb, tv[k], out=db)
            np.abs(db, out=db)
            np.less_equal(db, tol[k], out=hb)
            np.copyto(out, k, where=hb)
    return idx


def bin_continuous(raw: np.ndarray, spec: ActionSpec, *, where: str = "action") -> tuple[np.ndarray, ActionTable]:
    """Bin continuous commands by ``spec.edges`` or ``spec.n_bins`` quantiles.

    Commands outside the outermost edges go to the nearest end bin (edges may be
    ``-inf``/``inf``). Each bin's value is the mean of the commands in it (``bin_value
    = "mean"``; the centre for empty bins) or the centre of its finite edges.
    """
    x = np.asarray(raw, dtype=np.float64)
    finite = x[np.isfinite(x)]
    if spec.edges is not None:
        edges = np.asarray(spec.edges, dtype=np.float64)
    else:
        if not len(finite):
            raise IngestError(f"{where}: no finite values in {spec.column!r} to compute quantile bins")
        edges = np.unique(np.quantile(finite, np.linspace(0, 1, spec.n_bins + 1)))
        if len(edges) < 2:
            edges = np.array([finite.min() - 0.5, finite.max() + 0.5])
    n_bins = len(edges) - 1
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, n_bins - 1)
    idx = np.where(np.isfinite(x), idx, -1)
    lo = np.where(np.isfinite(edges[:-1]), edges[:-1], edges[1:])
    hi = np.where(np.isfinite(edges[1:]), edges[1:], edges[:-1])
    centre = (lo + hi) / 2
    if spec.bin_value == "mean" and len(finite):
        ok = idx >= 0
        sums = np.bincount(idx[ok], weights=x[ok], minlength=n_bins)
        counts = np.bincount(idx[ok], minlength=n_bins)
        vals = np.where(counts > 0, sums / np.maximum(counts, 1), centre)
    else:
        vals = centre
    names = spec.names or [f"{spec.dim}~{v:.4g}" for v in vals]
    if len(names) != n_bins:
        raise IngestError(f"{where}: action.names has {len(names)} entries for {n_bins} bins")
    table = ActionTable(
        actions=tuple(Action(str(n), (float(v),)) for n, v in zip(names, vals, strict=True)),
        dims=(spec.dim,),
        kind="binned",
        units=(spec.unit,) if spec.unit else (),
        bin_edges=tuple(float(e) for e in edges),
    )
    return idx.astype(np.int32), table


def _isnan(x: np.ndarray) -> np.ndarray:
    return np.isnan(x) if x.dtype.kind == "f" else np.zeros(len(x), bool)
