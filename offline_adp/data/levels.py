"""Quantile bin edges that keep a command's logged levels apart.

``np.unique(np.quantile(x, linspace(0, 1, B + 1)))`` collapses repeated quantiles: a
value logged on many rows (a keyboard teleop's -0.2 / 0 / +0.2, a throttle mostly at 0)
becomes one edge, and with the usual ``searchsorted(..., side="right")`` it shares its bin
with the values just above it, so the bin's mean is a command nobody logged (0.05 from
levels 0 and 0.2). :func:`level_edges` adds, for every such level, the edges ``[v,
nextafter(v))``: the level is a bin of its own, and the values around it keep their
quantile bins.
"""

from __future__ import annotations

import numpy as np


def level_edges(values: np.ndarray, n_bins: int) -> np.ndarray:
    """Sorted bin edges (outer ones included) for the finite ``values``, about ``n_bins``
    bins: the quantile edges, plus a bin ``[v, nextafter(v, inf))`` for each level ``v``
    logged on at least ``len(values) / n_bins`` rows (and at least twice), or for every
    distinct value when there are at most ``n_bins`` of them. Each such level then falls
    alone in its bin under ``np.searchsorted(edges, x, side="right") - 1`` (the last edge
    is above the largest value when the largest is a level). No bin is left empty (an empty
    one is merged into its upper neighbour, the last into its lower). Empty ``values``: no
    edges."""
    x = np.asarray(values, dtype=np.float64)
    if not len(x):
        return np.zeros(0)
    B = max(1, int(n_bins))
    edges = np.quantile(x, np.linspace(0.0, 1.0, B + 1))
    levels, counts = np.unique(x, return_counts=True)
    if len(levels) > B:
        levels = levels[(counts >= 2) & (counts >= len(x) / B)]
    edges = np.unique(np.concatenate([edges, levels, np.nextafter(levels, np.inf)]))
    nb = len(edges) - 1
    if nb < 1:
        return edges
    counts = np.bincount(np.clip(np.searchsorted(edges, x, side="right") - 1, 0, nb - 1), minlength=nb)
    drop = np.zeros(len(edges), bool)
    drop[1:nb] = counts[:-1] == 0  # an empty bin loses its upper edge: it joins the bin above
    if counts[-1] == 0:
        drop[nb - 1] = True  # an empty last bin joins the one below
    return edges[~drop]


def cell_means(cell: np.ndarray, values: np.ndarray, n_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """The mean of ``values`` (n,) over the rows of each cell (``cell``: an index in
    ``[0, n_cells)`` per row) and each cell's row count; NaN for an empty cell. A cell whose
    rows all hold one value gets that value exactly (a sum of 300 x 0.2 over 300 is not
    0.2 in floating point, and a level must come back as logged)."""
    c = np.asarray(cell, dtype=np.int64)
    x = np.asarray(values, dtype=np.float64)
    counts = np.bincount(c, minlength=n_cells)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.bincount(c, weights=x, minlength=n_cells) / counts
    if len(c):
        first = np.full(n_cells, np.nan)
        first[c[::-1]] = x[::-1]  # the first row's value of each cell (the last write wins)
        constant = np.bincount(c, weights=(x != first[c]), minlength=n_cells) == 0
        mean = np.where(constant & (counts > 0), first, mean)
    return mean, counts
