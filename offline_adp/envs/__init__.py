"""Reference problems: each a batched access model plus a ``gymnasium.Env`` via ``make_env``.

The registry maps a problem's name to its class by import path, so listing the names
(``PROBLEM_NAMES``, e.g. for the CLI's choices) imports nothing heavy; the class is
imported on first use. Problem-specific behaviour (scores, summary numbers, report
figures, units) lives on the :class:`ReferenceProblem` subclass, never as
``if name == ...`` in generic code.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from offline_adp.errors import UnknownNameError

#: problem name -> "module:Class"
_REGISTRY: dict[str, str] = {
    "car_on_hill": "offline_adp.envs.car_on_hill:CarOnHill",
    "gridworld": "offline_adp.envs.gridworld:Gridworld",
    "path_tracking": "offline_adp.envs.path_tracking:PathTracking",
    "tabular": "offline_adp.envs.tabular:TabularMDP",
    "two_state": "offline_adp.envs.two_state:TwoState",
}
PROBLEM_NAMES: tuple[str, ...] = tuple(sorted(_REGISTRY))


def problem_class(name: str) -> type:
    """The class of the reference problem ``name`` (``UnknownNameError`` lists the known ones)."""
    try:
        module, cls = _REGISTRY[name].split(":")
    except KeyError:
        raise UnknownNameError(f"unknown problem {name!r}; known problems: {list(PROBLEM_NAMES)}") from None
    return getattr(importlib.import_module(module), cls)


def make_problem(name: str, **kwargs: Any) -> ReferenceProblem:
    """Instantiate a reference problem by name (keyword arguments go to its constructor)."""
    cls = problem_class(name)
    try:
        return cls(**kwargs)
    except TypeError as exc:  # unknown keys
        raise UnknownNameError(f"problem {name!r}: bad options {sorted(kwargs)} ({exc})") from None
    except (ValueError, OverflowError) as exc:  # values the problem refuses (n_states = -3)
        from offline_adp.errors import InvalidArgumentError

        raise InvalidArgumentError(f"problem {name!r}: options {kwargs} rejected ({exc})") from None


def recorded_problem_options(info: Any) -> dict[str, Any] | None:
    """The constructor options a dataset's reference problem was made with, from its
    provenance (``provenance.problem_options``, written by ``simulate`` and
    :meth:`ReferenceProblem.dataset_info`; for a concatenation, ``provenance.parts``).

    Returns the options (``{}``: the defaults), or ``None`` when the dataset names no
    problem or its provenance does not record them (datasets written before the options
    were recorded). Raises :class:`~offline_adp.errors.ArtifactError` naming
    ``provenance.problem_options`` when they are recorded as unknown (options that are not
    JSON) or the concatenated parts disagree: no simulator can reproduce that system.
    """
    from offline_adp.errors import ArtifactError
    from offline_adp.errors import ArtifactError as _Bad

    prov = getattr(info, "provenance", None) or {}
    if not isinstance(prov, dict) or not isinstance(prov.get("parts", []) or [], list):
        raise _Bad("meta/info.json: provenance must be an object (with parts, if any, a list); "
                   f"found {type(prov).__name__}")
    prov = dict(prov)
    problem = getattr(info, "problem", None)
    if not problem:
        return None
    if "problem_options" in prov:
        found = [prov["problem_options"]]
    else:
        found = [p["problem_options"] for p in prov.get("parts",
                                                        []) or [] if isinstance(p, dict) and "problem_options" in p]
        if not found:
            return None
    for opts in found:
        if not isinstance(opts, dict):
            raise ArtifactError(
                f"dataset of problem {problem!r}: provenance.problem_options is {opts!r}, i.e. the options it was made "
                "with are unknown, so no simulator can roll out the same system; evaluate with --simulator none")
    if any(o != found[0] for o in found[1:]):
        raise ArtifactError(
            f"dataset of problem {problem!r}: its parts were made with different provenance.problem_options "
            f"({found}); no single simulator reproduces them; evaluate with --simulator none")
    return dict(found[0])


def problem_for_dataset(name: str, info: Any) -> ReferenceProblem:
    """The reference problem ``name`` as the dataset ``info`` recorded it.

    When ``name`` is the dataset's own problem (``info.problem``), it is constructed with
    the options the data was made with (:func:`recorded_problem_options`); otherwise (a
    different problem, or none recorded) with its defaults. Every simulator of
    ``evaluate``, ``compare`` and the pipeline is built here, so a dataset simulated with
    ``--problem-options '{"seed": 3}'`` is rolled out in seed 3's system.
    """
    if name != getattr(info, "problem", None):
        return make_problem(name)
    opts = recorded_problem_options(info)
    return make_problem(name, **(opts or {}))


_LAZY = {"ProblemEnv": "offline_adp.envs.base:ProblemEnv", "ReferenceProblem": "offline_adp.envs.base:ReferenceProblem",
         **{v.split(":")[1]: v for v in _REGISTRY.values()}}


def __getattr__(name: str) -> Any:
    if name == "PROBLEMS":  # name -> class, for callers that want the classes themselves
        return {n: problem_class(n) for n in PROBLEM_NAMES}
    if name in _LAZY:
        module, attr = _LAZY[name].split(":")
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'offline_adp.envs' has no attribute {name!r}")


if TYPE_CHECKING:
    from offline_adp.envs.base import ReferenceProblem

__all__ = ["PROBLEM_NAMES", "make_problem", "problem_class", "ProblemEnv", "ReferenceProblem", "CarOnHill", "Gridworld",
           "PathTracking", "TabularMDP", "TwoState"]
