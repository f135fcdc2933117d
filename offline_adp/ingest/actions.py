"""Logged commands -> action indices: discrete mapping, binning of continuous commands, or
continuous commands kept as logged.

Shared by Parquet and MCAP ingestion. Unmatched discrete values map to index -1 so the
doctor reports them (with file and row) instead of dropping them. Continuous commands
(:func:`command_actions`) are always kept exactly by the caller in ``action_value.<dim>``
columns; the ``action`` index is then a bin of each command: the spec's bins (kind
``"binned"``), or, for commands kept as logged (kind ``"continuous"``), coarse quantile bins
per component (:func:`coarse_bins`) that only the discrete views use.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from offline_adp.data.info import ACTION_VALUE_PREFIX, Action, ActionTable
from offline_adp.data.levels import cell_means, level_edges
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
            raise IngestError(f"{where}: column {spec.column!r} holds numbers but action.values are "
                              f"{list(spec.values)}")
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
    block by block in place, no temporary the size of ``x``.

    When the table's tolerance intervals are far apart (finite, distinct values: at most one
    ``k`` can match), a value equal to ``tv[k]`` is that match: each block is first matched by
    equality (two in-cache passes per action instead of four, without masked copies), and
    only the values equal to none (NaN, rounding, labels outside the table) take the
    tolerance rule."""
    idx = np.full(len(x), -1, np.int32)
    d = np.empty(min(len(x), _MATCH_BLOCK))
    hit = np.empty(len(d), bool)
    exact = _far_apart(tv, tol)
    for lo in range(0, len(x), _MATCH_BLOCK):
        xb = x[lo:lo + _MATCH_BLOCK]
        n = len(xb)
        out, db, hb = idx[lo:lo + n], d[:n], hit[:n]
        if not exact:
            _match_tolerance(xb, tv, tol, out, db, hb)
            continue
        code = db.view(np.int64)[:n]  # k + 1 of the equal table value, 0 when none
        code[:] = 0
        for k in range(len(tv)):
            np.equal(xb, tv[k], out=hb)
            code += hb * np.int64(k + 1)
        np.subtract(code, 1, out=out, casting="unsafe")
        rest = np.flatnonzero(out < 0)
        if len(rest):
            sub = np.full(len(rest), -1, np.int32)
            _match_tolerance(xb[rest], tv, tol, sub, np.empty(len(rest)), np.empty(len(rest), bool))
            out[rest] = sub
    return idx


def _far_apart(tv: np.ndarray, tol: np.ndarray) -> bool:
    """Whether no number is within tolerance of two table values (finite values whose
    neighbours are more than twice their two tolerances apart: far beyond rounding)."""
    if not (np.isfinite(tv).all() and np.isfinite(tol).all()):
        return False
    order = np.argsort(tv, kind="stable")
    s, t = tv[order], tol[order]
    return bool((np.diff(s) > 2 * (t[:-1] + t[1:])).all())


def _match_tolerance(xb: np.ndarray, tv: np.ndarray, tol: np.ndarray, out: np.ndarray, db: np.ndarray,
                     hb: np.ndarray) -> None:
    """``out`` (-1 where nothing matches) set to the last ``k`` with ``|xb - tv[k]| <= tol[k]``."""
    for k in range(len(tv)):
        np.subtract(xb, tv[k], out=db)
        np.abs(db, out=db)
        np.less_equal(db, tol[k], out=hb)
        np.copyto(out, k, where=hb)


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
        edges = level_edges(finite, spec.n_bins)
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
        means, counts = cell_means(idx[ok], x[ok], n_bins)
        vals = np.where(counts > 0, means, centre)
    else:
        vals = centre
    names = spec.names or [f"{spec.dim}~{v:.4g}" for v in vals]
    if not spec.names and len(set(names)) != len(names):  # a level and the bin just above it print alike
        names = [f"{spec.dim}#{i}" for i in range(n_bins)]
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


#: Quantile bins per component of a command kept as logged (the product at most
#: :data:`MAX_COARSE_CELLS` cells): the coarse ``action`` index of the discrete views.
COARSE_BINS = 16
MAX_COARSE_CELLS = 4096


def command_units(spec: ActionSpec, k: int, *, where: str = "action") -> tuple[str, ...]:
    """Unit of each of the ``k`` components (``units``, or ``unit`` for every one; ``()``
    when none is given)."""
    if spec.units is not None:
        if len(spec.units) != k:
            raise IngestError(f"{where}.units: {len(spec.units)} entries for a command of {k} components")
        return tuple(spec.units)
    return (spec.unit,) * k if spec.unit else ()


def command_bounds(x: np.ndarray, spec: ActionSpec, dims: tuple[str, ...], *, infer: bool = True,
                   where: str = "action") -> tuple[tuple[float, ...] | None, tuple[float, ...] | None]:
    """``(low, high)`` of each component: the spec's ``low``/``high`` (one number applies to
    every component), else - with ``infer`` - the logged minimum/maximum of the finite
    commands (``None`` without ``infer``)."""
    k = len(dims)
    out: list[tuple[float, ...] | None] = []
    for key in ("low", "high"):
        v = getattr(spec, key)
        if v is not None:
            if len(v) == 1 and k > 1:
                v = v * k
            if len(v) != k:
                raise IngestError(f"{where}.{key}: {len(v)} entries for a command of {k} components {list(dims)}")
            out.append(tuple(float(b) for b in v))
            continue
        if not infer:
            out.append(None)
            continue
        finite = np.isfinite(x)
        empty = ~finite.any(axis=0)
        if empty.any():
            j = int(np.argmax(empty))
            raise IngestError(f"{where}: component {dims[j]!r}: no finite command to infer its bounds from; declare "
                              "low and high")
        red = np.min if key == "low" else np.max
        fill = np.inf if key == "low" else -np.inf
        out.append(tuple(float(b) for b in red(np.where(finite, x, fill), axis=0)))
    low, high = out
    if low is not None and high is not None and any(lo > hi for lo, hi in zip(low, high, strict=True)):
        # one bound declared, the other logged: the logged range lies beyond the declared bound
        if spec.low is None:
            low = tuple(min(lo, hi) for lo, hi in zip(low, high, strict=True))
        elif spec.high is None:
            high = tuple(max(lo, hi) for lo, hi in zip(low, high, strict=True))
    return low, high


def _coarse_edges(col: np.ndarray, nb: int, low: tuple[float, ...] | None, high: tuple[float, ...] | None,
                  j: int, levels: bool = True) -> np.ndarray:
    """One component's coarse bin edges (:func:`coarse_bins`): with ``levels``, a frequent
    level's own bin (:func:`~offline_adp.data.levels.level_edges`), else plain quantiles."""
    finite = col[np.isfinite(col)]
    if len(finite):
        edges = level_edges(finite, nb) if levels else np.unique(np.quantile(finite, np.linspace(0, 1, nb + 1)))
    elif low is not None and high is not None:
        edges = np.unique([low[j], high[j]])
    else:
        edges = np.zeros(1)
    if len(edges) < 2:
        edges = np.array([edges[0] - 0.5, edges[-1] + 0.5])
    return edges


def coarse_bins(x: np.ndarray, dims: tuple[str, ...], low: tuple[float, ...] | None = None,
                high: tuple[float, ...] | None = None) -> tuple[np.ndarray, ActionTable]:
    """Commands ``x`` (n, k) -> coarse bin index per row and a table of the bins.

    Each component is cut at quantiles of its finite values (at most :data:`COARSE_BINS`
    bins, the product at most :data:`MAX_COARSE_CELLS` cells); the index is row-major over
    the components; each cell's value is the mean command in it (its centre when empty).
    A non-finite component goes to an end bin (the index stays valid: the doctor reports
    the command itself). The table has kind ``"continuous"``."""
    n, k = x.shape
    nb = max(1, min(COARSE_BINS, int(np.floor(MAX_COARSE_CELLS ** (1.0 / k) + 1e-9))))
    all_edges = [_coarse_edges(x[:, j], nb, low, high, j) for j in range(k)]
    if int(np.prod([len(e) - 1 for e in all_edges], dtype=object)) > MAX_COARSE_CELLS:
        # a frequent level's own bin adds one per component: past the cap, plain quantile bins
        all_edges = [_coarse_edges(x[:, j], nb, low, high, j, levels=False) for j in range(k)]
    per = []
    for j, edges in enumerate(all_edges):
        col = x[:, j]
        m = len(edges) - 1
        per.append((np.clip(np.searchsorted(edges, col, side="right") - 1, 0, m - 1), (edges[:-1] + edges[1:]) / 2))
    shape = tuple(len(c) for _, c in per)
    idx = np.ravel_multi_index(tuple(i for i, _ in per), shape) if n else np.zeros(0, np.int64)
    cells = np.array(np.unravel_index(np.arange(int(np.prod(shape))), shape)).T
    values = np.column_stack([per[j][1][cells[:, j]] for j in range(k)])
    ok = np.isfinite(x).all(axis=1)
    for j in range(k):
        means, counts = cell_means(idx[ok], x[ok, j], len(cells))
        values[:, j] = np.where(counts > 0, means, values[:, j])
    names = [",".join(f"{d}#{i}" for d, i in zip(dims, c, strict=True)) for c in cells]
    table = ActionTable(
        actions=tuple(Action(nm, tuple(float(v) for v in row)) for nm, row in zip(names, values, strict=True)),
        dims=dims,
        kind="continuous",
        low=low,
        high=high,
    )
    return idx.astype(np.int32), table


def bin_product(x: np.ndarray, bins: Mapping[str, Mapping[str, Any]], dims: tuple[str, ...], *, bin_value: str = "mean",
                names: tuple[str, ...] | list[str] | None = None, units: tuple[str, ...] = (),
                where: str = "action") -> tuple[np.ndarray, ActionTable]:
    """A vector command ``x`` (n, k) binned per component (``bins[dim]``: ``{"edges": [...]}``
    or ``{"n_bins": m}``; beyond the outer edges into the end bins) into the cells of the
    product table (index row-major over the components; a row with a non-finite component
    gets -1, which the doctor reports). Each cell's value is the mean command in it
    (``bin_value = "mean"``; its centre when empty) or its centre. Kind ``"binned"``."""
    per_dim = []
    for j, d in enumerate(dims):
        b = bins[d]
        col = x[:, j]
        finite = col[np.isfinite(col)]
        if "edges" in b:
            edges = np.asarray(b["edges"], dtype=np.float64)
        else:
            if not len(finite):
                raise IngestError(f"{where}.{d}: no finite values to compute quantile bins")
            edges = level_edges(finite, int(b["n_bins"]))
            if len(edges) < 2:
                edges = np.array([finite.min() - 0.5, finite.max() + 0.5])
        nb = len(edges) - 1
        lo = np.where(np.isfinite(edges[:-1]), edges[:-1], edges[1:])
        hi = np.where(np.isfinite(edges[1:]), edges[1:], edges[:-1])
        per_dim.append((np.clip(np.searchsorted(edges, col, side="right") - 1, 0, nb - 1), (lo + hi) / 2, nb))
    shape = tuple(nb for _, _, nb in per_dim)
    ok = np.isfinite(x).all(axis=1)
    idx = np.where(ok, np.ravel_multi_index(tuple(i for i, _, _ in per_dim), shape), -1)
    cells = np.array(np.unravel_index(np.arange(int(np.prod(shape))), shape)).T
    centre = np.column_stack([per_dim[j][1][cells[:, j]] for j in range(len(dims))])
    vals = centre.copy()
    if bin_value == "mean":
        for j in range(len(dims)):
            means, counts = cell_means(idx[ok], x[ok, j], len(cells))
            vals[:, j] = np.where(counts > 0, means, centre[:, j])
    values = [tuple(float(v) for v in row) for row in vals]
    names = (
        list(names) if names else [",".join(f"{d}~{v:.4g}" for d, v in zip(dims, row, strict=True)) for row in values]
    )
    if len(set(names)) != len(names):  # equal representative values (e.g. empty cells): name by bin indices
        names = [",".join(f"{d}#{i}" for d, i in zip(dims, c, strict=True)) for c in cells]
    if len(names) != len(values):
        raise IngestError(f"{where}.names has {len(names)} entries for {len(values)} actions")
    table = ActionTable(actions=tuple(Action(str(n), v) for n, v in zip(names, values, strict=True)), dims=dims,
                        kind="binned", units=units)
    return idx.astype(np.int32), table


def command_actions(x: np.ndarray, spec: ActionSpec, dims: tuple[str, ...], *, vector: bool,
                    bins: Mapping[str, Mapping[str, Any]] | None = None, infer_binned_bounds: bool = True,
                    where: str = "action") -> tuple[np.ndarray, ActionTable]:
    """Continuous commands ``x`` (n, k), components ``dims`` -> (action index, action table).

    - kept as logged (no ``edges``/``n_bins``): kind ``"continuous"`` with bounds (declared
      or logged) and :func:`coarse_bins` as the index;
    - a scalar command (``vector`` false) with bins: :func:`bin_continuous`, exactly as
      before; bounds recorded only when declared (the table, hence the fingerprint, of an
      existing spec stays the same);
    - a vector command with bins: :func:`bin_product` (``bins`` per component, else the
      spec's ``edges``/``n_bins`` for every component); bounds declared, or logged when
      ``infer_binned_bounds``.

    The caller keeps ``x`` in the ``action_value.<dim>`` columns (:func:`command_columns`).
    """
    x = np.asarray(x, dtype=np.float64).reshape(len(x), -1)
    k = x.shape[1]
    if len(dims) != k:
        raise IngestError(f"{where}.names: {len(dims)} component names {list(dims)} for a command of {k} components")
    units = command_units(spec, k, where=where)
    if spec.exact and not bins:
        low, high = command_bounds(x, spec, dims, where=where)
        idx, table = coarse_bins(x, dims, low, high)
        return idx, dataclasses.replace(table, units=units)
    if not vector:
        idx, table = bin_continuous(x[:, 0], dataclasses.replace(spec, dim=dims[0]), where=where)
        low, high = command_bounds(x, spec, dims, infer=False, where=where)
        if low is not None or high is not None or units != table.units:
            table = dataclasses.replace(table, low=low, high=high, units=units)
        return idx, table
    if bins is None:
        one = {"edges": spec.edges} if spec.edges is not None else {"n_bins": spec.n_bins}
        bins = {d: one for d in dims}
    idx, table = bin_product(x, bins, dims, bin_value=spec.bin_value, names=spec.names, units=units, where=where)
    low, high = command_bounds(x, spec, dims, infer=infer_binned_bounds, where=where)
    if low is not None or high is not None:
        table = dataclasses.replace(table, low=low, high=high)
    return idx, table


def command_columns(x: np.ndarray, dims: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The exact commands as ``action_value.<dim>`` float64 columns."""
    x = np.asarray(x, dtype=np.float64).reshape(len(x), -1)
    return {ACTION_VALUE_PREFIX + d: np.ascontiguousarray(x[:, j]) for j, d in enumerate(dims)}
