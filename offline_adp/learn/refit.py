"""The naive LEARN step: clone and refit the regressor on every iteration (any regressor)."""

from __future__ import annotations

from typing import Any

import numpy as np
from sklearn.base import clone

from offline_adp.errors import InvalidArgumentError
from offline_adp.learn.base import Learner, LearnSpec, fit_model, seeded
from offline_adp.qfunctions import QFunction, RegressorQ, predict_model


class RefitLearner(Learner):
    """Clone and refit LEARN on every iteration (any scikit-learn regressor).

    Per iteration the loop needs ``Q_k`` at every next state for every action (the next
    targets); that is the one large prediction, as in any FQI. The diagnostics also read
    ``Q_k`` on the training pairs and at the start states, but logged transitions mostly
    continue each other (``x_i == x'_j`` for some j, usually ``j = i - 1``, in any row
    order), so those values are *read* from the next-state predictions wherever the
    regression input is bitwise the same, and only the remaining distinct inputs (episode
    starts, mostly) are predicted, for all actions at once: ~1-2% extra rows instead of
    +50% (one value per training pair). Predictions are cached per iteration.
    ``predict_jobs``: the fitted forests' ``n_jobs`` for prediction (None: as fitted);
    registry forests (``extra_trees``, ``random_forest``) fit on all cores but predict on
    one thread unless ``n_jobs`` was given
    (:func:`offline_adp.regressors.predict_n_jobs`).
    """

    _DERIVED = ("train", "start")  # query sets read from the next-state predictions where possible

    def __init__(self, spec: LearnSpec, predict_jobs: int | None = None) -> None:
        super().__init__(spec)
        self._cache: dict[str, np.ndarray] = {}
        self._support: dict[str, np.ndarray | None] = {}  # per query set, for the current Q
        self._predict_jobs = predict_jobs
        self._source: dict[str, np.ndarray] = {}  # query -> row of [next; extra] holding each row's input
        if "next" not in self.queries:
            return
        base = self.queries["next"][0]
        derived = [n for n in self._DERIVED if n in self.queries and self.queries[n][0].shape[1:] == base.shape[1:]]
        if not derived or self.encoder.continuous:  # a state's candidates need not hold its logged command
            return
        idx, extra = _row_sources(base, [self.queries[n][0] for n in derived])
        self._source = dict(zip(derived, idx, strict=True))
        self.queries["extra"] = (extra, None)  # distinct inputs not among the next states

    def fit(self, y: np.ndarray, k: int) -> None:
        seed = self.seed + k
        if self.encoder.per_action:
            models = []
            for a in range(self.encoder.n_actions):
                rows = self.actions == a
                m = seeded(clone(self.regressor), seed)
                if not rows.any():
                    raise InvalidArgumentError(f"action {a} never occurs in the data: a per-action model "
                                               "cannot be fitted")
                models.append(fit_model(m, self.phi[rows], y[rows],
                                        None if self.weights is None else self.weights[rows]))
        else:
            m = seeded(clone(self.regressor), seed)
            models = [fit_model(m, self.encoder.pairs(self.phi, self.actions), y, self.weights)]
        if self._predict_jobs is not None:
            for m in models:
                if hasattr(m, "estimators_") and hasattr(m, "n_jobs"):
                    m.n_jobs = self._predict_jobs
        self.q = RegressorQ(models, self.encoder)
        self._cache, self._support = {}, {}

    def predict(self, name: str) -> np.ndarray:
        if name not in self._cache:
            phi, actions = self.queries[name]
            if name in self._source:  # all actions of each row, read from [Q(next); Q(extra)]
                if "_table" not in self._cache:
                    self._cache["_table"] = np.concatenate([self.predict("next"), self.predict("extra")])
                self._cache[name] = self._select(self._cache["_table"][self._source[name]], actions)
            elif len(phi) == 0:
                self._cache[name] = np.zeros((0, self.encoder.n_actions)) if actions is None else np.zeros(0)
            elif actions is not None and not self.encoder.per_action:
                self._cache[name] = self._predict_pairs(self.encoder.pairs(phi, actions))
            else:
                self._cache[name] = self._select(self.q.values_phi(phi), actions)
        return self._cache[name]

    def _predict_pairs(self, X: np.ndarray) -> np.ndarray:
        """The joint model's predictions on joint inputs ``X``."""
        if isinstance(self.q, RegressorQ):
            return self.q.predict_model(0, X)
        return predict_model(self.q.models[0], X)  # a restored Q of another kind (its models[0])

    def support(self, name: str) -> np.ndarray | None:
        """The lookup tables' support on the query set ``name`` (an all-actions one), else None."""
        q = getattr(self, "q", None)
        support_phi = getattr(q, "support_phi", None)
        if support_phi is None or self.queries[name][1] is not None:
            return None
        if name not in self._support:
            self._support[name] = support_phi(self.queries[name][0])
        return self._support[name]

    def snapshot(self) -> QFunction:
        return self.q

    def restore(self, q: QFunction, iteration: int, rows: list[dict[str, Any]] | None = None) -> None:
        self.q, self._cache, self._support = q, {}, {}  # type: ignore[assignment]


def _row_sources(base: np.ndarray, sets: list[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """For each row of each array in ``sets``: its index in ``[base; extra]`` where that
    row is bitwise equal to the input there; ``extra`` holds the distinct rows found in
    no ``base`` row (one sort over all rows, once per fit)."""
    d = base.shape[1] if base.ndim == 2 else 1
    rows = np.ascontiguousarray(np.concatenate([base.reshape(len(base), d), *(s.reshape(len(s), d) for s in sets)]),
                                dtype=np.float64)
    keys = rows.view(np.dtype((np.void, 8 * d))).ravel()
    _, first, inv = np.unique(keys, return_index=True, return_inverse=True)
    n = len(base)
    in_base = first < n  # np.unique's first occurrence: a base row whenever the key is in base
    new = np.flatnonzero(~in_base)  # distinct keys found only in the other sets
    where = first.copy()
    where[new] = n + np.arange(len(new))
    extra = rows[first[new]]
    out, lo = [], n
    for s in sets:
        out.append(where[inv[lo:lo + len(s)]])
        lo += len(s)
    return out, extra.reshape((len(extra),) + base.shape[1:])
