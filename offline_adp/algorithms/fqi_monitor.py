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
   does. Not for an averager (a frozen structure, the lookup table): its iterates cannot
   leave the bound of rule 1, and a structure rebuild's jumps can pass this test (three
   default fits in 300 small random ones did, an audit found, 2026-11-29).

The verdict at the end of every fit is one of ``converged``, ``still changing`` (how far
the values may still be from the fixed point, and the trend of ``sup|dQ|``), ``diverging``
(what the monitor saw) or ``completed`` (finite horizon: exact backward recursion, nothing
to converge).

**When a fit has converged** (a frozen tree structure: ``mode="frozen"``, the default's).
Between two builds the structure is fixed and one iteration is
``Q_k(z) = sum_i alpha_i(z) (c_i + gamma V_{k-1}(x'_i))`` with convex weights
``alpha_i(z)`` (leaf averages, then the average over trees) and ``V`` the minimum (FQI) or
the policy's expectation (FQE) over ``Q(x'_i, .)``: a sup-norm ``gamma``-contraction. With
``e_k = sup |Q_k - Q_{k-1}|`` over the data's pairs (training pairs and every next-state
pair), ``e_{k+1} <= gamma e_k``, so at *every* input ``z`` the last iterate is within

    ``gamma / (1 - gamma) * e_k``

of the fixed point of the final structure's averager (``|Q_k - Q*| <= gamma |Q_{k-1} - Q*|
<= gamma (e_k + |Q_k - Q*|)``): the bound needs only that ``Q_k`` is one backup of
``Q_{k-1}``, however ``Q_{k-1}`` was reached. A computed backup is exact only up to float64
rounding ``r`` (:func:`rounding_allowance`), so the bound stated is ``(gamma e_k + r) / (1 - gamma)``:
with large values and a tight tolerance the iterates can stop moving (``e_k = 0``) away from
the fixed point, and the verdict then says the tolerance is below what float64 resolves.
The fit has converged when that bound is at most ``tol`` (if given, else ``rtol *
max|Q_k|``), on an iteration that did not rebuild the structure nor run the settling solver
(whose Q is not one backup of the previous one: :mod:`offline_adp.learn.settle`), after the
last scheduled build. A structure rebuild starts a new contraction (``sup|dQ|`` jumps),
which is why the verdict never reads across one. The refit and warm-start modes change the
function class every iteration, so no such bound holds there (nor with ``gamma = 1`` or
target noise): they converge only by ``tol`` on ``e_k`` itself, and
otherwise say "still changing".

``n_iterations="auto"`` (:func:`auto_iterations`): ``K_b`` is the number of iterations after
which the contraction has damped the initial error (``max|c| / (1 - gamma) + max|Q_0|``)
to ``gamma^K_b <= 0.05`` of itself. A frozen fit builds its structures at geometrically
spaced iterations up to ``K_b / 4``
(:func:`~offline_adp.algorithms.fqi_modes.geometric_builds`; with ``n_structures`` set,
that many evenly over ``K_b``), then solves its final structure's fixed point
(:mod:`offline_adp.learn.settle`: accelerated backups within one iteration) and stops on
the next iteration, a plain backup, if the bound above holds there; it never runs more
than ``4 K_b`` iterations (nor the solver more than ``4 K_b`` backups; the verdict says
so when it stops at that cap). The other modes run ``K_b`` iterations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from offline_adp.learn.settle import backups

#: ``n_iterations="auto"``: the builds span the K_b iterations with ``gamma^K_b <= AUTO_FORGET``
AUTO_FORGET = 0.05
#: ... and a frozen fit may go on in its final structure up to ``AUTO_CAP * K_b`` iterations in all
AUTO_CAP = 4
#: K_b when ``gamma = 1`` (no contraction to count on), and the largest K_b
AUTO_UNDISCOUNTED, AUTO_MAX_BUILD = 100, 1000


def auto_iterations(gamma: float, settles: bool) -> tuple[int, int]:
    """``(K_b, K_max)`` for ``n_iterations="auto"`` (see the module docstring): ``K_b =
    ceil(log 0.05 / log gamma)`` (at most 1000; 100 for ``gamma = 1``), ``K_max = 4 K_b``
    when the fit can settle in a fixed structure (``settles``: the frozen mode), else ``K_b``."""
    g = float(gamma)
    K = AUTO_UNDISCOUNTED if g >= 1 else min(AUTO_MAX_BUILD, max(1, math.ceil(math.log(AUTO_FORGET) / math.log(g))))
    return K, (AUTO_CAP * K if settles else K)


def distance_bound(sup_dq: float, gamma: float, rounding: float = 0.0) -> float:
    """``(gamma * sup_dq + rounding) / (1 - gamma)``: how far a contraction's iterate can
    still be from its fixed point (``inf`` for ``gamma = 1`` unless nothing changed).

    ``rounding`` bounds what float64 arithmetic adds to one computed backup at any pair
    (:func:`rounding_allowance`): with ``|T~Q - TQ| <= r``, ``|Q_k - Q*| <= r + gamma
    (|Q_k - Q_{k-1}| + |Q_k - Q*|)``. Without it a fit whose iterates stopped moving in
    float64 would be stated "within 0" of a fixed point it may miss by ``r / (1 - gamma)``."""
    if gamma >= 1:
        return 0.0 if sup_dq == 0 and rounding == 0 else float("inf")
    return (float(gamma) * float(sup_dq) + float(rounding)) / (1.0 - float(gamma))


#: the trees (or other averaged members) :func:`rounding_allowance` allows for
ROUNDING_MEMBERS = 1024


def rounding_allowance(max_abs_q: float, max_abs_c: float, n_rows: int) -> float:
    """A bound on the float64 rounding of one backup at any pair: a leaf's (or cell's) mean
    of at most ``n_rows`` weighted targets, summed in sequence (``(2 n + 2) eps`` of the
    largest target), the mean over up to :data:`ROUNDING_MEMBERS` trees, and the target
    ``c + gamma min Q`` itself; targets are at most ``max|c| + max|Q|``."""
    eps = float(np.finfo(np.float64).eps)
    return (2.0 * n_rows + ROUNDING_MEMBERS + 8.0) * eps * (float(max_abs_c) + float(max_abs_q))


def bound_text(sd: float, gamma: float, rounding: float, bound: float) -> str:
    """How a stated distance was computed: ``gamma/(1-gamma) x sup|dQ|``, and the rounding
    term where it shows in the printed digits."""
    if gamma < 1 and rounding / (1.0 - gamma) > 1e-3 * bound:
        return (f"(gamma x sup|dQ| + r) / (1 - gamma), sup|dQ| = {sd:.3g}, r = {rounding:.3g} for float64 "
                "rounding")
    return f"gamma/(1-gamma) x sup|dQ|, sup|dQ| = {sd:.3g}"


def below_resolution(tolerance: float | None, gamma: float, rounding: float) -> str:
    """A note where ``tolerance`` is below what float64 rounding lets the bound resolve."""
    if tolerance is None or gamma >= 1 or rounding / (1.0 - gamma) <= tolerance:
        return ""
    return (f"; the tolerance is below what float64 resolves here (rounding alone allows "
            f"{rounding / (1.0 - gamma):.3g}): loosen tol or rtol")


@dataclass
class DivergenceMonitor:
    """Watches ``max_abs_q`` of the history rows (see the module docstring)."""

    bound: float
    bound_text: str
    q0_abs: float = 0.0
    margin: float = 0.1
    window: int = 10
    finite: bool = False
    averager: bool = False

    def check(self, rows: list[dict[str, Any]]) -> str | None:
        """A message when ``rows`` (iterations 1..k) show divergence at iteration k, else None."""
        last = rows[-1]
        if np.isfinite(self.bound) and last["max_abs_q"] > self.bound * (1 + self.margin + 1e-9):
            return (f"iteration {last['iteration']}: max |Q| = {last['max_abs_q']:.4g} exceeds the bound "
                    f"{self.bound_text} = {self.bound:.4g} by more than {self.margin:.0%}")
        if not np.isfinite(last["max_abs_q"]):
            return f"iteration {last['iteration']}: max |Q| is not finite"
        W = self.window
        if self.finite or self.averager or len(rows) < 2 * W + 2:
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


def convergence_verdict(rows: list[dict[str, Any]], *, finite: bool, divergence: str | None, converged: bool,
            gamma: float, tolerance: float | None, frozen: bool, capped: bool = False,
            window: int = 10, rounding: float = 0.0) -> tuple[str, str]:
    """``(verdict, message)`` for a finished fit (see the module docstring). ``tolerance``:
    what the distance bound (frozen) or ``sup|dQ|`` (other modes) had to reach (None: no
    criterion); ``capped``: the fit stopped at ``n_iterations="auto"``'s cap; ``rounding``:
    :func:`rounding_allowance` at the last iteration."""
    if not rows:
        return "still changing", "no iterations ran"
    last = rows[-1]
    if divergence is not None:
        return "diverging", divergence
    if finite:
        return "completed", f"finite horizon: {len(rows)} backward steps (exact recursion, no fixed point to reach)"
    sd, k = last["sup_dq"], last["iteration"]
    if frozen:
        bound = distance_bound(sd, gamma, rounding)
        how = bound_text(sd, gamma, rounding, bound)
        where = (f"within {bound:.3g} of the final tree structure's fixed point ({how}; "
                 f"max|Q| = {last['max_abs_q']:.4g})")
        inner = sum(backups(r) for r in rows)
        after = f"after {k} iterations" + (f" (and {inner} backups in the final structure's solver)" if inner else "")
        if converged:
            return "converged", f"{after} the values are {where} <= tolerance {tolerance:.3g}"
        tr = trend([r["sup_dq"] for r in rows[-window:]])
        why = ("stopped at n_iterations='auto''s cap; " if capped else "")
        note = below_resolution(tolerance, gamma, rounding)
        need = (f" > tolerance {tolerance:.3g}" if tolerance is not None else "") + note
        if note and sd == 0:  # the fit stopped: a backup changed nothing
            return "still changing", (f"{after} the values are only known to be {where}{need}; the last backup "
                                      "changed nothing in float64, so more iterations cannot settle it")
        return "still changing", (f"{why}{after} the values are only known to be {where}{need}; "
                                  f"sup|dQ| {tr} over the last {min(window, len(rows))} (more iterations "
                                  f"{'cannot settle it' if note else 'would settle it'})")
    rel = sd / max(last["max_abs_q"], 1e-300)
    if converged:
        return "converged", f"sup|dQ| = {sd:.3g} < tol = {tolerance:g} at iteration {k}"
    tr = trend([r["sup_dq"] for r in rows[-window:]])
    return "still changing", (f"after {k} iterations sup|dQ| = {sd:.3g} ({rel:.2%} of max|Q| = "
                              f"{last['max_abs_q']:.4g}), {tr} over the last {min(window, len(rows))} (no contraction "
                              "bound here: the function class changes every iteration (refit, warm start), "
                              "or gamma = 1, or target noise; set tol to stop on sup|dQ|)")


def structure_builds(history: pd.DataFrame) -> list[dict[str, Any]]:
    """The structure builds of a frozen fit's ``history_``: ``{"iteration", "trees", "screen",
    "constant", "builder"}`` per build, in order (``screen``: the build's screen value, None
    when not screened; ``constant``: a build on constant targets, one-leaf trees; ``builder``:
    ``"compiled"`` or ``"scikit-learn"``, None for a constant build; ``trees`` and ``builder``
    None in rows written before they were recorded); an empty list for the other modes."""
    if not len(history) or "structure_trees" not in history:
        return []
    built = history["structure"].diff().fillna(1).to_numpy() != 0
    cols = ["iteration", "structure_trees", "structure_screen", "structure_on_constant", "structure_builder"]
    rows = history.loc[built, [c for c in cols if c in history]].to_dict("records")
    # None: a run from before
    return [{"iteration": int(r["iteration"]),
             "trees": None if is_missing(r.get("structure_trees")) else int(r["structure_trees"]),
             "screen": None if is_missing(r.get("structure_screen")) else float(r["structure_screen"]),
             "constant": not is_missing(r.get("structure_on_constant")) and bool(r["structure_on_constant"]),
             "builder": r["structure_builder"] if isinstance(r.get("structure_builder"), str) else None} for r in rows]


def is_missing(v: Any) -> bool:
    """None or NaN (a history cell a row did not record)."""
    return v is None or (isinstance(v, float) and np.isnan(v))
