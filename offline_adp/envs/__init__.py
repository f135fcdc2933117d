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
    except TypeError as exc:
        raise UnknownNameError(f"problem {name!r}: bad options {sorted(kwargs)} ({exc})") from None


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
