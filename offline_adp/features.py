"""Small, serialisable feature maps for observations."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.utils.validation import validate_data

from offline_adp.errors import InvalidArgumentError


class SelectColumns(TransformerMixin, BaseEstimator):
    """Keep the observation columns ``columns`` (indices), in that order.

    Stateless: usable without ``fit`` (``requires_fit`` is False); ``fit`` records the
    input width, which ``transform`` then checks.
    """

    def __init__(self, columns: Sequence[int] = (0,)) -> None:
        self.columns = columns

    def fit(self, X: np.ndarray, y: object = None) -> SelectColumns:
        X = validate_data(self, X, dtype=np.float64)
        self._check_columns(X.shape[1])
        return self

    def transform(self, X: np.ndarray) -> np.ndarray:
        X = validate_data(self, X, dtype=np.float64, reset=False)
        self._check_columns(X.shape[1])
        return X[:, list(self.columns)]

    def _check_columns(self, width: int) -> None:
        """Every column an index ``0 <= c < width`` (no negative ones: counted from the end they
        would read another feature than the names say, and a saved map is untrusted input)."""
        bad = [c for c in self.columns
               if isinstance(c, bool) or not isinstance(c, int | np.integer) or not 0 <= int(c) < width]
        if bad:
            raise InvalidArgumentError(f"SelectColumns: columns {bad} are not indices 0..{width - 1} of an input of "
                                       f"{width} features")

    def __call__(self, X: np.ndarray) -> np.ndarray:
        return self.transform(X)

    def __sklearn_tags__(self) -> Any:
        tags = super().__sklearn_tags__()
        tags.requires_fit = False
        return tags


def drop_features(feature_names: Sequence[str], drop: Sequence[str]) -> SelectColumns:
    """A :class:`SelectColumns` keeping every feature not named in ``drop``."""
    unknown = sorted(set(drop) - set(feature_names))
    if unknown:
        from offline_adp.errors import SpecError

        raise SpecError(f"cannot drop unknown features {unknown}; features are {list(feature_names)}")
    return SelectColumns([i for i, n in enumerate(feature_names) if n not in set(drop)])
