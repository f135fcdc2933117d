"""The policy interface (:mod:`offline_adp.policies` holds the policies themselves): the
abstract :class:`Policy` (``probabilities``, ``act_index`` and the user-facing ``act``) and
:class:`DeterministicPolicy`, the :class:`PolicySignature` a fitted policy carries (feature
names, units, action table), and :func:`observation_matrix`, which turns what a user
passes to ``act`` (dict, DataFrame, array) into the policy's checked float matrix.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from offline_adp.data.info import ActionTable
from offline_adp.errors import SchemaError

TimeArg = int | np.ndarray


@dataclass(frozen=True)
class PolicySignature:
    """What a policy reads and what it commands: the named observation vector (feature
    names in order, with units) and the action table (index -> value vector).

    Parameters
    ----------
    feature_names : tuple of str
        Observation features, in the order of the columns of ``obs`` arrays.
    feature_units : tuple of str
        Unit of each feature ("" when unknown).
    action_table : ActionTable
    """

    feature_names: tuple[str, ...]
    feature_units: tuple[str, ...]
    action_table: ActionTable

    @classmethod
    def from_info(cls, info: Any) -> PolicySignature:
        """From a :class:`~offline_adp.data.info.DatasetInfo` (or a reference problem:
        anything with ``features`` and ``action_table``)."""
        feats = tuple(info.features)
        return cls(tuple(f.name for f in feats), tuple(f.unit for f in feats), info.action_table)

    def to_dict(self) -> dict[str, Any]:
        return {"feature_names": list(self.feature_names), "feature_units": list(self.feature_units),
                "action_table": self.action_table.to_dict()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str = "signature") -> PolicySignature:
        """Read a signature written by :meth:`to_dict`, checked: ``feature_names`` a
        non-empty list of distinct strings, ``feature_units`` (optional) one string per
        name, ``action_table`` an action table; else a :class:`SchemaError` naming ``where``."""
        if not isinstance(d, Mapping):
            raise SchemaError(f"{where}: malformed policy signature (an object expected, found {type(d).__name__})")
        names, units = d.get("feature_names"), d.get("feature_units")
        if (not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names)
                or len(set(names)) != len(names)):
            raise SchemaError(f"{where}: feature_names must be a non-empty list of distinct strings, found "
                              f"{names!r:.120}")
        if units is None:
            units = [""] * len(names)
        if not isinstance(units, list) or len(units) != len(names) or not all(isinstance(u, str) for u in units):
            raise SchemaError(f"{where}: feature_units must be one string per feature ({len(names)}), found "
                              f"{units!r:.120}")
        try:
            return cls(tuple(names), tuple(units),
                       ActionTable.from_dict(d["action_table"], where=f"{where}.action_table"))
        except (KeyError, TypeError) as exc:
            raise SchemaError(f"{where}: malformed policy signature ({exc!r})") from exc


def observation_matrix(obs: Any, names: Sequence[str] | None, t: Any = None) -> tuple[np.ndarray, bool]:
    """``obs`` (dict, DataFrame, Series, array; one observation or a batch) as a float64
    ``(n, d)`` array in the order of ``names``, and whether it was a single observation.

    Raises :class:`SchemaError` on missing or unexpected names (naming them), on an array
    of the wrong width (listing the expected names), on a value that is not finite (NaN or
    infinite: no policy's action means anything there, and an exported graph would still
    return one), and on a time step ``t`` (when given) that is not a non-negative integer,
    one or one per row (a negative one would read the rules from the end).
    """
    X, single = _observation_matrix(obs, names)
    bad = ~np.isfinite(X)
    if bad.any():
        i, j = (int(v[0]) for v in np.nonzero(bad))
        what = repr(names[j]) if names is not None else f"column {j}"
        raise SchemaError(f"observation {i}: {what} is {float(X[i, j])}; a policy acts on finite values only "
                          "(check the sensor, or hold its last value)")
    if t is not None:
        check_time_steps(t, len(X))
    return X, single


def check_time_steps(t: Any, n: int) -> None:
    """``t`` is a time step: a non-negative integer, or one per row of ``n`` (a
    :class:`SchemaError` otherwise)."""
    tt = np.asarray(t)
    if tt.dtype == bool or tt.dtype.kind not in "iu" or tt.ndim > 1 or (tt.ndim == 1 and len(tt) != n):
        raise SchemaError(f"time step t must be a non-negative integer (int, not float: 3, not 3.0) or one per "
                          f"observation ({n}); got {tt.dtype} of shape {tt.shape}"
                          + (f": {tt.ravel()[:3].tolist()}" if tt.size else ""))
    if tt.size and int(tt.min()) < 0:
        raise SchemaError(f"time step t must be >= 0, got {int(tt.min())}")


def _observation_matrix(obs: Any, names: Sequence[str] | None) -> tuple[np.ndarray, bool]:
    """:func:`observation_matrix` before its checks of values and time steps."""
    import sys

    pd = sys.modules.get("pandas")  # a DataFrame can only exist if pandas is imported
    if pd is not None and isinstance(obs, pd.Series):
        obs = obs.to_dict()
    is_frame = pd is not None and isinstance(obs, pd.DataFrame)
    if isinstance(obs, Mapping) or is_frame:
        keys = [str(k) for k in (obs.columns if is_frame else obs.keys())]
        if names is None:
            raise SchemaError(f"this policy has no feature names (no signature), so it cannot match {keys} by name; "
                              "pass an array in the order it was fitted on, or attach a signature "
                              "(policy.signature = PolicySignature.from_info(dataset.info))")
        missing = [n for n in names if n not in keys]
        extra = [k for k in keys if k not in set(names)]
        if missing or extra:
            raise SchemaError(f"observation names do not match the policy's: missing {missing}, unexpected {extra}; "
                              f"expected exactly {list(names)}")
        if is_frame:
            return obs[list(names)].to_numpy(dtype=np.float64), False
        try:
            cols = [np.asarray(obs[n], dtype=np.float64) for n in names]
        except (TypeError, ValueError) as exc:
            raise SchemaError(f"observation values must be numbers ({exc})") from None
        if any(c.ndim > 1 for c in cols) or len({c.size for c in cols if c.ndim == 1}
                                                | ({1} if any(c.ndim == 0 for c in cols) else set())) > 1:
            raise SchemaError(f"observation values for {list(names)} must be all scalars or all 1-D of one length; "
                              f"got shapes {[c.shape for c in cols]}")
        return np.column_stack([np.atleast_1d(c) for c in cols]), all(c.ndim == 0 for c in cols)
    try:
        X = np.asarray(obs, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise SchemaError("observations must be numbers (a dict, DataFrame or array), got "
                          f"{type(obs).__name__} ({exc})") from None
    if X.ndim not in (1, 2):
        raise SchemaError(f"observations must be one vector (d,) or a batch (n, d); got an array of shape {X.shape}")
    single = X.ndim == 1
    X = X.reshape(1, -1) if single else X
    if names is not None and X.shape[1] != len(names):
        raise SchemaError(f"observations have {X.shape[1]} columns, the policy expects {len(names)}: {list(names)}")
    return X, single


class Policy(ABC):
    """A (possibly stochastic, possibly time-varying) policy over a finite action set."""

    n_actions: int
    #: Feature names/units and action table (attached by ``fit`` on a dataset, or by hand).
    signature: PolicySignature | None = None

    @abstractmethod
    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        """Action probabilities, shape (n, n_actions), rows summing to 1."""

    def act_index(self, obs: np.ndarray, t: TimeArg = 0, rng: np.random.Generator | None = None) -> np.ndarray:
        """One action index per row of a float ``(n, d)`` array (stochastic policies sample
        by inverse CDF, vectorised). The fast path for algorithms and rollouts."""
        rng = rng if rng is not None else np.random.default_rng()
        p = self.probabilities(obs, t)
        u = rng.random(p.shape[0])
        return np.minimum((u[:, None] >= np.cumsum(p, axis=1)).sum(axis=1), self.n_actions - 1).astype(np.int32)

    def act(self, obs: Any, t: TimeArg = 0, rng: np.random.Generator | None = None, *,
            return_index: bool = False) -> Any:
        """The action for each observation, checked against the policy's signature.

        Parameters
        ----------
        obs : dict, DataFrame, Series or array
            One observation (a dict of scalars, a Series, a 1-D array of width d) or a
            batch (a dict of equal-length columns, a DataFrame, an (n, d) array). Names
            are matched to ``signature.feature_names``; missing or unexpected names are an
            error, as is an array of the wrong width.
        t : int or array
            Time step (time-varying policies).
        rng : Generator, optional
            For stochastic policies.
        return_index : bool
            Return action indices instead of action values.

        Returns
        -------
        ndarray or scalar
            Action values, ``(n, n_dims)`` or ``(n,)`` for a one-dimensional action table;
            with ``return_index`` int32 indices ``(n,)``. A single observation drops the
            leading axis. Without a signature the action values are the indices.

        Raises
        ------
        SchemaError
            Observation names or width do not match the policy's.
        """
        sig = self.signature
        X, single = observation_matrix(obs, None if sig is None else sig.feature_names, t)
        idx = np.asarray(self.act_index(X, t, rng), dtype=np.int32)
        if return_index or sig is None:
            return int(idx[0]) if single else idx
        values = sig.action_table.values[idx]
        if values.shape[1] == 1:
            values = values[:, 0]
        return values[0] if single else values


class DeterministicPolicy(Policy):
    """A policy that picks one action per (obs, t); ``probabilities`` are one-hot."""

    @abstractmethod
    def actions(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        """The chosen action per row, shape (n,) int."""

    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        a = self.actions(obs, t)
        p = np.zeros((len(a), self.n_actions))
        p[np.arange(len(a)), a] = 1.0
        return p

    def act_index(self, obs: np.ndarray, t: TimeArg = 0, rng: np.random.Generator | None = None) -> np.ndarray:
        return np.asarray(self.actions(obs, t), dtype=np.int32)
