"""Hyper-parameter checks of the chapter's estimators, scikit-learn's way.

Every estimator of :mod:`offline_adp.algorithms` declares its parameters' values once, as
scikit-learn's own estimators do: a ``_parameter_constraints`` class attribute in the
vocabulary of :mod:`sklearn.utils._param_validation` (``Interval``, ``StrOptions``,
``HasMethods``, ``"boolean"``, types, ``None``). Its ``fit`` starts with scikit-learn's
``BaseEstimator._validate_params()``, which checks them, and then calls the one hook this
module adds, :meth:`CheckedEstimator._check_param_combinations`, for what a constraint on
one parameter cannot say (one parameter against another, a list's elements, a regressor's
own parameters). The configuration layer (``AlgorithmEntry.check_params`` in
:mod:`offline_adp.algorithms.registry`) calls the same two on the estimator a TOML table
describes before anything runs or is written, so ``step_rule = "fast"`` is one line naming
the file and key. Both raise scikit-learn's ``InvalidParameterError`` (a ``ValueError`` and
a ``TypeError``) worded as scikit-learn words it: ``The 'key' parameter of Class must be
... Got ... instead.``

Checks that need the data (a horizon against the dataset's episodes, a model's access)
stay in ``fit``.
"""

from __future__ import annotations

import re
from numbers import Integral, Real
from typing import Any, ClassVar

import numpy as np
from sklearn.base import BaseEstimator
from sklearn.utils._param_validation import Interval, InvalidParameterError

from offline_adp.errors import IncompatibleError

__all__ = ["CheckedEstimator", "InvalidParameterError", "invalid_parameter", "check_learner",
           "POSITIVE_INT", "NON_NEGATIVE_INT", "SEED", "FRACTION", "NON_NEGATIVE", "GAMMA"]

#: common constraints
POSITIVE_INT = Interval(Integral, 1, None, closed="left")
NON_NEGATIVE_INT = Interval(Integral, 0, None, closed="left")
#: ``random_state`` is an int seed (``np.random.default_rng`` refuses a negative one; it is
#: also added to the iteration number), not scikit-learn's "random_state" (which takes a RandomState)
SEED = Interval(Integral, 0, None, closed="left")
FRACTION = Interval(Real, 0, 1, closed="both")
NON_NEGATIVE = Interval(Real, 0, None, closed="left")  # finite: an Interval refuses inf and NaN
#: a discount factor (:func:`offline_adp.data.discount.resolve_discount`'s rule)
GAMMA = Interval(Real, 0, 1, closed="right")


def invalid_parameter(est: Any, name: str, must: str, got: Any) -> InvalidParameterError:
    """The error scikit-learn raises for a bad ``name``, in its wording."""
    return InvalidParameterError(f"The {name!r} parameter of {type(est).__name__} must be {must}. Got {got!r} instead.")


class CheckedEstimator(BaseEstimator):
    """A scikit-learn estimator whose ``_parameter_constraints`` are checked by
    ``BaseEstimator._validate_params`` and then by :meth:`_check_param_combinations`."""

    _parameter_constraints: ClassVar[dict[str, list[Any]]] = {}

    def check_params(self) -> None:
        """Every parameter check, in order: scikit-learn's ``_validate_params()`` on
        ``_parameter_constraints``, then :meth:`_check_param_combinations` (the one call
        ``fit`` and the configuration layer make)."""
        self._validate_params()
        self._check_param_combinations()

    def _check_param_combinations(self) -> None:
        """The rules ``_parameter_constraints`` cannot express; called right after
        scikit-learn's ``_validate_params()`` (by ``fit`` and by the configuration layer).

        The base refuses a bool where a number is declared (scikit-learn's ``Interval``
        takes ``True`` as the integer 1). Subclasses extend it (calling ``super()``) and
        raise :func:`invalid_parameter` naming the parameter at fault.
        """
        for name, constraints in self._parameter_constraints.items():
            value = getattr(self, name, None)
            if (isinstance(value, bool | np.bool_) and "boolean" not in constraints
                    and any(isinstance(c, Interval) for c in constraints)):
                raise invalid_parameter(self, name, "a number, not a bool", value)


def check_learner(est: Any, name: str, params_name: str, make: Any, spec: Any, params: dict | None) -> None:
    """Build the learner ``make(spec, **params)`` (a regressor or classifier of
    :mod:`offline_adp.regressors`) and check its own parameters with its scikit-learn
    ``_validate_params`` when it declares constraints (LightGBM's do not); a failure is an
    :class:`InvalidParameterError`
    naming ``params_name`` (an unknown key or a bad value in it)."""
    from offline_adp.errors import UnknownNameError

    try:
        learner = make(spec, **(params or {}))
    except UnknownNameError as exc:
        raise invalid_parameter(est, params_name, f"parameters {name} takes ({exc.args[0].split(': ', 1)[-1]})",
                                params) from None
    except (TypeError, ValueError) as exc:  # a clone's set_params: an unknown parameter
        raise invalid_parameter(est, params_name, f"parameters {name} takes ({exc})", params) from None
    if hasattr(learner, "_parameter_constraints"):
        try:
            learner._validate_params()
        except InvalidParameterError as exc:
            inner = re.sub(r"^The ('\w+') parameter of (\w+) (.*)\. Got .*$", r"\2's \1 \3", " ".join(str(exc).split()))
            raise invalid_parameter(est, params_name, f"parameters {name} accepts ({inner})", params) from None


def refuse_continuous(name: str, ds: Any) -> None:
    """CPI and PSDP learn over the action table's entries (mixtures of policies, classifiers
    over actions): a dataset of continuous commands is refused rather than fitted on its
    bins behind the user's back."""
    at = getattr(getattr(ds, "info", None), "action_table", None)
    if at is not None and at.continuous:
        raise IncompatibleError(
            f"{name} learns over a finite action table and does not take continuous commands ({list(at.dims)} in this "
            "dataset); fit 'fqi' or 'api' (both learn over the exact commands), or ingest the commands with bins "
            "(type = 'continuous' with n_bins or edges) to run it over the bins")
