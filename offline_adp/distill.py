"""A compact, smooth deployable form of a continuous greedy policy: distillation.

The greedy policy over continuous commands
(:class:`~offline_adp.policies.GreedyCommandPolicy`) minimises ``Q(x, u)`` over the
commands logged at the nearest logged states: it carries the whole log (a k-d tree) and
jumps between logged commands as ``x`` moves. :func:`distill_policy` fits a tree
ensemble (extra trees, one multi-output forest: one split structure, one set of leaf
values per command component) from the state to the greedy command at the logged
states, and returns a :class:`DistilledCommandPolicy`: the forest's average, clipped to
the action table's bounds, with an optional per-step rate limit. It is saved as tree
arrays (artifact kind ``distilled_command``) and exported to ONNX
(:mod:`offline_adp.onnx_export`): the ``act`` of the saved policy and the ONNX model are
the same function.

This module sits in its own layer just above :mod:`offline_adp.policies` (it derives
from :class:`~offline_adp.policies.CommandPolicy`; artifacts and the exporter import it).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.errors import InvalidArgumentError, SchemaError
from offline_adp.policies import CommandPolicy, TimeArg, attach_signature, observation_matrix
from offline_adp.progress import get_logger

log = get_logger(__name__)

__all__ = ["DistilledCommandPolicy", "distill_policy", "advantage_weights"]


class DistilledCommandPolicy(CommandPolicy):
    """``u(x) = clip(mean over trees of leaf values, low, high)``, one tree ensemble per
    command component (they may share one split structure), then, when the caller passes
    the previous command, the rate limit.

    Parameters
    ----------
    models : list
        One regressor per component (:class:`~offline_adp.trees.ensemble.TreeEnsemble`
        or a scikit-learn forest), each ``predict((n, d)) -> (n,)``.
    low, high : ndarray (m,)
        Bounds per component (the action table's; ``-inf``/``inf`` where undeclared).
    max_rate : ndarray (m,), optional
        Largest ``|u_t - u_{t-1}|`` per component per step, in command units. Applied by
        :meth:`commands` / :meth:`act` only when the caller gives ``previous`` (the
        command sent at the previous step): the policy itself keeps no state, as the
        ONNX model keeps none (there it is metadata, ``max_rate``).
    n_features : int, optional
        The observation width (checked on input when known).
    report : dict, optional
        How the distillation fitted (:func:`distill_policy`).
    """

    time_varying = False

    def __init__(self, models: list[Any], low: np.ndarray, high: np.ndarray, max_rate: np.ndarray | None = None,
                 n_features: int | None = None, report: dict[str, Any] | None = None) -> None:
        self.models = list(models)
        self.low = np.asarray(low, np.float64).reshape(-1)
        self.high = np.asarray(high, np.float64).reshape(-1)
        m = len(self.models)
        if m == 0 or self.low.shape != (m,) or self.high.shape != (m,) or np.isnan(self.low).any() \
                or np.isnan(self.high).any() or (self.low > self.high).any():
            raise SchemaError(f"a distilled policy needs one model per command component and bounds low <= high of "
                              f"that length; got {m} models, low {self.low.tolist()}, high {self.high.tolist()}")
        self.max_rate = None if max_rate is None else _rates(max_rate, m)
        self.n_features, self.report = n_features, dict(report or {})

    @property
    def n_dims(self) -> int:
        return len(self.models)

    def raw_commands(self, obs: np.ndarray) -> np.ndarray:
        """The clipped forest output ``(n, m)`` (no rate limit)."""
        X = np.asarray(obs, np.float64)
        if X.ndim != 2 or (self.n_features is not None and X.shape[1] != self.n_features):
            raise SchemaError(f"observations of shape {X.shape}; the distilled policy reads {self.n_features} columns")
        u = np.column_stack([np.asarray(m.predict(X), np.float64).reshape(len(X)) for m in self.models])
        return np.minimum(np.maximum(u, self.low), self.high)

    def commands(self, obs: np.ndarray, t: TimeArg = 0, previous: Any = None) -> np.ndarray:
        """The command per row ``(n, m)``; with ``previous`` (``(n, m)``, ``(m,)`` or a
        scalar for one component; NaN rows: no previous command yet) and a ``max_rate``,
        each component moves at most ``max_rate`` from ``previous`` (then the bounds)."""
        u = self.raw_commands(obs)
        if previous is None or self.max_rate is None:
            return u
        prev = _previous(previous, u.shape)
        limited = np.clip(u, prev - self.max_rate, prev + self.max_rate)
        u = np.where(np.isnan(prev), u, limited)
        return np.minimum(np.maximum(u, self.low), self.high)

    def act(self, obs: Any, t: TimeArg = 0, rng: np.random.Generator | None = None, *, return_index: bool = False,
            previous: Any = None) -> Any:
        """The command for each observation (:meth:`CommandPolicy.act`); ``previous``: the
        command(s) sent at the previous step, to apply the rate limit (see :meth:`commands`).
        Without ``previous`` (or without a ``max_rate``) no rate limit is applied."""
        sig = self.signature
        X, single = observation_matrix(obs, None if sig is None else sig.feature_names, t)
        if return_index:
            idx = self.actions(X, t)
            return int(idx[0]) if single else idx
        u = self.commands(X, t, previous)
        if u.shape[1] == 1:
            u = u[:, 0]
        return u[0] if single else u


def _rates(max_rate: Any, m: int) -> np.ndarray:
    r = np.asarray(max_rate, np.float64).reshape(-1)
    r = np.full(m, r[0]) if r.shape == (1,) else r
    if r.shape != (m,) or not np.all(np.isfinite(r)) or (r <= 0).any():
        raise SchemaError(f"max_rate: one positive finite value, or one per command component ({m}); got {r.tolist()}")
    return r


def advantage_weights(q_values: np.ndarray) -> np.ndarray:
    """Distillation weight per state from its candidate Q-values ``(n, k)`` (costs).

    ``g = mean_j Q(x, c_j) - min_j Q(x, c_j)`` is how much picking the greedy command
    matters at ``x`` (0 where every candidate costs the same); the weight is
    ``0.1 + 0.9 * g / mean(g)`` (mean 1, at least 0.1, so no state is ignored), uniform
    when every ``g`` is 0."""
    q = np.asarray(q_values, np.float64)
    g = q.mean(axis=1) - q.min(axis=1)
    mg = float(g.mean()) if len(g) else 0.0
    return np.ones(len(g)) if not mg > 0 else 0.1 + 0.9 * g / mg


def _q_at(q: Any, obs: np.ndarray, u: np.ndarray) -> np.ndarray | None:
    """``Q(x, u)`` for arbitrary commands (joint regressor or booster-sum Q), else None."""
    from offline_adp.qfunctions import predict_model

    enc = getattr(q, "encoder", None)
    if enc is None or enc.per_action:
        return None
    X = enc.pairs(enc.phi(obs), u)
    if hasattr(q, "boosters"):
        return np.asarray(sum(b.predict(X, raw_score=True) for b in q.boosters), np.float64)
    models = getattr(q, "models", None)
    return None if not models else predict_model(models[0], X)


def distill_policy(policy: Any, dataset: Any, *, n_estimators: int = 50, min_samples_leaf: int = 5,
                   max_rate: Any = None, max_rows: int = 200_000, holdout: float = 0.2,
                   random_state: int = 0) -> DistilledCommandPolicy:
    """Fit a :class:`DistilledCommandPolicy` to a continuous greedy policy on a dataset's
    logged states.

    The targets are the greedy commands ``pi(x)`` at the logged states (at most
    ``max_rows`` of them, a seeded sample); the regressor is one multi-output extra-trees
    forest (``n_estimators`` trees, ``min_samples_leaf``, all features at each split),
    rows weighted by :func:`advantage_weights` (states where the greedy choice matters
    more count more). The result is clipped to the action table's bounds.

    ``policy.report`` (also logged) holds the fit on the logged states:
    ``mean_abs_diff`` (mean ``|distilled - greedy|`` per component; in sample, so with
    ``min_samples_leaf=1`` it is 0), ``max_abs_diff``, ``heldout_mean_abs_diff`` (the
    same for a forest fitted on the other rows, at a seeded ``holdout`` fraction of the
    rows; the final forest is fitted on all of them; ``holdout=0``: not measured),
    ``mean_step_change`` (mean ``|u(x') - u(x)|`` over logged transitions, greedy and
    distilled: the smoothness), ``q_increase`` (mean ``Q(x, distilled) - Q(x, greedy)``
    as the fitted Q sees it, when it can be evaluated at any command).

    Raises
    ------
    SchemaError
        ``policy`` is not a stationary continuous greedy policy (a ``q`` over candidate
        commands), or its commands do not match the dataset's action table.
    """
    from sklearn.ensemble import ExtraTreesRegressor

    from offline_adp.qfunctions import command_encoder
    from offline_adp.trees import TreeEnsemble

    q = getattr(policy, "q", None)
    enc = None if q is None else command_encoder(q)
    if enc is None or not getattr(policy, "continuous", False):
        raise SchemaError(f"distill_policy needs a greedy policy over continuous commands, got {type(policy).__name__}")
    if getattr(policy, "time_varying", False):
        raise SchemaError("distilling a time-varying (finite-horizon) greedy policy is not supported; fit a "
                          "stationary one")
    info = getattr(dataset, "info", None)
    table = getattr(info, "action_table", None)
    if table is None:
        raise SchemaError("distill_policy needs a dataset (its logged states and action table)")
    if policy.signature is None:
        attach_signature(policy, dataset)
    arr = dataset.arrays()
    obs, nxt = arr.obs, arr.next_obs
    n = len(obs)
    if n == 0:
        raise SchemaError("distill_policy: the dataset has no rows")
    if n > max_rows:
        rows = np.sort(np.random.default_rng(random_state).choice(n, max_rows, replace=False))
        obs, nxt = obs[rows], nxt[rows]
        n = max_rows
    low, high = table.bounds()
    cand = enc.commands(enc.phi(obs))
    qv = np.asarray(q.values(obs), np.float64)
    greedy = policy.clip(cand[np.arange(n), np.argmin(qv, axis=1)])
    if greedy.shape[1] != len(low):
        raise SchemaError(f"the policy commands {greedy.shape[1]} components, the action table has {len(low)}")
    w = advantage_weights(qv)

    def fit(rows: np.ndarray) -> Any:
        f = ExtraTreesRegressor(n_estimators=n_estimators, min_samples_leaf=min_samples_leaf, max_features=1.0,
                                random_state=random_state, n_jobs=1)
        y = greedy[rows]
        return f.fit(obs[rows], y if y.shape[1] > 1 else y[:, 0], sample_weight=w[rows])

    heldout = None
    if holdout > 0 and n >= 10:  # the fit's agreement on states it did not see (the in-sample one flatters it)
        test = np.random.default_rng(random_state).random(n) < holdout
        if test.any() and (~test).any():
            pred = fit(np.flatnonzero(~test)).predict(obs[test]).reshape(int(test.sum()), -1)
            heldout = np.abs(np.clip(pred, low, high) - greedy[test]).mean(axis=0)
    forest = fit(np.arange(n))
    base = TreeEnsemble.from_sklearn(forest)
    models = [base] + [base.with_values(np.concatenate([e.tree_.value[:, c, 0] for e in forest.estimators_]))
                       for c in range(1, greedy.shape[1])]
    out = DistilledCommandPolicy(models, low, high, max_rate, n_features=obs.shape[1])
    out.signature = policy.signature
    u = out.commands(obs)
    diff = np.abs(u - greedy)
    step_greedy = np.abs(policy.commands(nxt) - greedy).mean(axis=0)
    step_distilled = np.abs(out.commands(nxt) - u).mean(axis=0)
    qd, qg = _q_at(q, obs, u), _q_at(q, obs, greedy)
    out.report = {
        "rows": int(n), "n_estimators": int(n_estimators), "min_samples_leaf": int(min_samples_leaf),
        "random_state": int(random_state), "components": list(table.dims),
        "weights": "0.1 + 0.9 * g / mean(g), g = mean - min of Q over the candidate commands",
        "mean_abs_diff": diff.mean(axis=0).tolist(), "max_abs_diff": diff.max(axis=0).tolist(),
        "heldout_fraction": float(holdout) if heldout is not None else None,
        "heldout_mean_abs_diff": None if heldout is None else heldout.tolist(),
        "mean_step_change": {"greedy": step_greedy.tolist(), "distilled": step_distilled.tolist()},
        "q_increase": None if qd is None or qg is None else float(np.mean(qd - qg)),
        "max_rate": None if out.max_rate is None else out.max_rate.tolist(),
    }
    log.info("distilled the greedy policy into %d trees on %d logged states: mean |distilled - greedy| %s "
             "(max %s; on held-out states %s); mean step change greedy %s, distilled %s; mean Q increase %s",
             n_estimators, n, _fmt(out.report["mean_abs_diff"]), _fmt(out.report["max_abs_diff"]),
             "n/a" if heldout is None else _fmt(heldout), _fmt(step_greedy), _fmt(step_distilled),
             "n/a" if out.report["q_increase"] is None else f"{out.report['q_increase']:.4g}")
    return out


def _fmt(v: Any) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in np.asarray(v).reshape(-1)) + "]"


def _previous(previous: Any, shape: tuple[int, int]) -> np.ndarray:
    """``previous`` as an ``(n, m)`` array for commands of ``shape``: ``(n, m)``, ``(m,)`` (the
    same for every row), ``(n,)`` or a scalar for a one-component command. A scalar for a
    command of several components is refused: which component would it be?"""
    n, m = shape
    p = np.asarray(previous, dtype=np.float64)
    if p.ndim == 0 and m != 1:
        raise InvalidArgumentError(f"previous={float(p)!r} is one number for a command of {m} components; give "
                                   f"one per component, shape ({m},) or ({n}, {m})")
    if p.ndim == 0 or (p.ndim == 1 and m == 1 and len(p) in (1, n)):
        return np.broadcast_to(p.reshape(-1, 1), shape)
    if p.shape in ((m,), (1, m), (n, m)):
        return np.broadcast_to(p.reshape(-1, m), shape)
    raise InvalidArgumentError(f"previous has shape {p.shape}; for {n} observation(s) of a command of {m} "
                               f"component(s) give shape ({m},) or ({n}, {m})")
