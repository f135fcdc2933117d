"""The one rule that decides the discount factor and the horizon of a fit or an evaluation.

Every algorithm and the evaluation resolve ``gamma`` and the finite horizon ``T`` here,
so a dataset is fitted and evaluated on the same quantity:

1. an explicit setting wins (``gamma=``, ``horizon=`` on the estimator, in a config file
   or on the command line);
2. otherwise the dataset's hints (``meta/info.json``: ``gamma``, ``horizon``);
3. otherwise the stated defaults: ``gamma = 1`` with a finite horizon,
   :data:`DEFAULT_GAMMA` without one.

The horizon (finite-horizon algorithms, one Q per step) is used when it is set
explicitly, or when the resolved ``gamma`` is 1, the dataset declares a horizon and its
episodes never terminate: undiscounted costs without absorbing states need a finite
horizon, so a dataset that declares ``gamma = 1`` and ``horizon = 10`` (``simulate
tabular``) means the 10-step problem. Undiscounted data whose episodes terminate is a
shortest-path problem (Boyan & Moore's gridworld) and stays infinite-horizon. A discounted
dataset's horizon hint is a time limit (episodes are truncated there and bootstrapped),
not a finite-horizon problem, so it is not used as ``T``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from offline_adp.errors import SpecError

#: gamma for a discounted problem when neither the user nor the dataset says.
DEFAULT_GAMMA = 0.95


@dataclass(frozen=True)
class Discount:
    """A resolved discount factor and horizon, with where each came from.

    Attributes
    ----------
    gamma : float
    horizon : int or None
        ``T`` for finite-horizon algorithms, ``None`` for the infinite-horizon ones.
    gamma_source, horizon_source : {"explicit", "dataset", "default"}
    """

    gamma: float
    horizon: int | None
    gamma_source: str
    horizon_source: str

    def describe(self) -> str:
        h = "infinite horizon" if self.horizon is None else f"horizon T = {self.horizon}"
        return f"gamma = {self.gamma:g} ({self.gamma_source}), {h} ({self.horizon_source})"


def resolve_discount(info: Any = None, gamma: float | None = None, horizon: int | None = None,
                     terminates: bool = False) -> Discount:
    """Apply the rule of this module.

    Parameters
    ----------
    info : DatasetInfo or None
        The dataset's metadata (its ``gamma`` and ``horizon`` hints), if any.
    gamma, horizon : optional
        Explicit settings.
    terminates : bool
        Whether the data's episodes reach absorbing states (a shortest-path problem).

    Raises
    ------
    SpecError
        ``gamma`` outside (0, 1] or a horizon that is not a positive integer.
    """
    hint_gamma = getattr(info, "gamma", None)
    hint_horizon = getattr(info, "horizon", None)
    if horizon is not None:
        if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon <= 0:
            raise SpecError(f"horizon must be a positive integer or None, got {horizon!r}")
        T, T_src = int(horizon), "explicit"
    else:
        T, T_src = None, "default"
    if gamma is not None:
        g, g_src = float(gamma), "explicit"
    elif hint_gamma is not None:
        g, g_src = float(hint_gamma), "dataset"
    else:
        g, g_src = (1.0 if T is not None else DEFAULT_GAMMA), "default"
    if not 0.0 < g <= 1.0:
        where = ("the dataset's meta/info.json, field 'gamma'" if g_src == "dataset"
                 else "the 'gamma' parameter" if g_src == "explicit" else "the default")
        fix = "; set another gamma in the fit's config or fix the dataset's info.json" if g_src == "dataset" else ""
        raise SpecError(f"gamma must be in (0, 1], got {g!r} (from {where}){fix}")
    if T is None and g >= 1.0 and hint_horizon is not None and not terminates:
        T, T_src = int(hint_horizon), "dataset"
    return Discount(g, T, g_src, T_src)
