"""The fitted-Q divergence monitor and the end-of-fit verdict.

What an *approximate* backup measured on samples can and cannot tell. The exact Bellman
operator is a sup-norm contraction over *all* states; a sampled ``sup_i |Q_k - Q_{k-1}|``
with a regressor in the loop may rise and fall (refit trees are redrawn every
iteration, a frozen structure is rebuilt) without anything diverging, so a rising change
is never by itself a reason to flag a fit. The monitor flags only what is unambiguous:

1. **Values beyond the bound.** From ``Q_0`` every exact iterate satisfies
   ``|Q_k| <= max|c| / (1 - gamma) + max|Q_0|`` (a finite horizon: ``max|c| sum_{j<T}
   gamma^j + max|Q_T|``); averagers (trees, k-NN, tables) stay inside it too. Flagged when
   ``max |Q_k|`` exceeds the bound by more than ``margin`` (a fraction of the bound).
2. **Sustained accelerating growth of max|Q|** (infinite horizon). With ``W = window``
   and ``M_k = max |Q_k|`` on the data: the growth over the last ``W`` iterations is at
   least ``1.5x`` the growth over the ``W`` before, both halves of the last window grow
   (the second at least as much as the first, and the first by at least a fifth of the
   total, so a single jump such as a restructured tree never qualifies), and the growth
   is at least 20% of ``M_k``, at 3 consecutive iterations. Iterates approaching a fixed point from ``Q_0`` decelerate
   (growth shrinks like ``gamma^k``), values growing linearly (undiscounted shortest
   paths) do not accelerate, and geometric divergence ``M_k ~ r^k`` with ``r^W >= 1.5``
   does.

The verdict at the end of every fit is one of ``converged`` (``sup|dQ| < tol``),
``still changing`` (last ``sup|dQ|`` and its trend over the last iterations),
``diverging`` (what the monitor saw) or ``completed`` (finite horizon: exact backward
recursion, nothing to converge).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class DivergenceMonitor:
    """Watches ``max_abs_q`` of the history rows (see the module docstring)."""

    bound: float
    bound_text: str
    q0_abs: float = 0.0
    margin: float = 0.1
    window: int = 10
    finite: bool = False

    def check(self, rows: list[dict[str, Any]]) -> str | None:
        """A message when ``rows`` (iterations 1..k) show divergence at iteration k, else None."""
        last = rows[-1]
        if np.isfinite(self.bound) and last["max_abs_q"] > self.bound * (1 + self.margin) + 1e-9:
            return (f"iteration {last['iteration']}: max |Q| = {last['max_abs_q']:.4g} exceeds the bound "
                    f"{self.bound_text} = {self.bound:.4g} by more than {self.margin:.0%}")
        if not np.isfinite(last["max_abs_q"]):
            return f"iteration {last['iteration']}: max |Q| is not finite"
        W = self.window
        if self.finite or len(rows) < 2 * W + 2:
            return None
        M = np.r_[self.q0_abs, [r["max_abs_q"] for r in rows]]  # M[k] = max |Q_k|
        k = len(M) - 1
        if all(self._accelerating(M, j) for j in range(k - 2, k + 1)):  # sustained: 3 checks in a row
            return (f"iteration {last['iteration']}: max |Q| is growing faster and faster: {M[k - 2 * W]:.4g} -> "
                    f"{M[k - W]:.4g} -> {M[k]:.4g} over the last {2 * W} iterations")
        return None

    def _accelerating(self, M: np.ndarray, k: int) -> bool:
        W, h = self.window, self.window // 2
        prev, d1, d2 = M[k - W] - M[k - 2 * W], M[k - W + h] - M[k - W], M[k] - M[k - W + h]
        total = d1 + d2
        return bool(total > 1.5 * max(prev, 0.0) and d2 >= d1 >= 0.2 * total > 0 and total >= 0.2 * M[k])


def trend(values: list[float]) -> str:
    """'decreasing', 'flat' or 'increasing': the least-squares slope of log values per
    iteration over the given window (|slope| < 1% per iteration: flat)."""
    v = np.log(np.maximum(np.asarray(values, dtype=np.float64), 1e-300))
    if len(v) < 3:
        return "flat"
    slope = np.polyfit(np.arange(len(v)), v, 1)[0]
    return "decreasing" if slope < -0.01 else ("increasing" if slope > 0.01 else "flat")


def verdict(rows: list[dict[str, Any]], *, tol: float | None, finite: bool, divergence: str | None,
            converged: bool, window: int = 10) -> tuple[str, str]:
    """``(verdict, message)`` for a finished fit (see the module docstring)."""
    if not rows:
        return "still changing", "no iterations ran"
    last = rows[-1]
    if divergence is not None:
        return "diverging", divergence
    if finite:
        return "completed", f"finite horizon: {len(rows)} backward steps (exact recursion, no fixed point to reach)"
    sd = last["sup_dq"]
    rel = sd / max(last["max_abs_q"], 1e-300)
    if converged:
        return "converged", f"sup|dQ| = {sd:.3g} < tol = {tol:g} at iteration {last['iteration']}"
    tr = trend([r["sup_dq"] for r in rows[-window:]])
    return "still changing", (f"after {last['iteration']} iterations sup|dQ| = {sd:.3g} ({rel:.2%} of max|Q| = "
                              f"{last['max_abs_q']:.4g}), {tr} over the last {min(window, len(rows))}")
