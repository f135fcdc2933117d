"""Small, serialisable feature maps for observations."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from sklearn.base import BaseEstimator, TransformerMixin


class SelectColumns(TransformerMixin, BaseEstimator):
    """Keep the observation columns ``columns`` (indices), in that order."""

    def __init__(self, columns: Sequence[int] = (0,)) -> None:
        self.columns = columns

    def fit(self, X: np.ndarray, y: object = None) -> SelectColumns:
        self.n_features_in_ = np.asarray(X).shape[1]
        return self

    def transform(self, X: np.ndarray) -> np.ndarray:
        return np.asarray(X, dtype=np.float64)[:, list(self.columns)]

    def __call__(self, X: np.ndarray) -> np.ndarray:
        return self.transform(X)


def drop_features(feature_names: Sequence[str], drop: Sequence[str]) -> SelectColumns:
    """A :class:`SelectColumns` keeping every feature not named in ``drop``."""
    unknown = sorted(set(drop) - set(feature_names))
    if unknown:
        from offline_adp.errors import SpecError

        raise SpecError(f"cannot drop unknown features {unknown}; features are {list(feature_names)}")
    return SelectColumns([i for i, n in enumerate(feature_names) if n not in set(drop)])
