"""Numba for the kernels that run alone (leaf lookups, sums over leaves), imported when one
first runs, not when its module is.

Importing numba and loading the first kernel from its on-disk cache costs about 0.6 CPU-s
(numba's import, then its typing registries, which import parts of scipy): most of what
loading a small saved policy cost. A process that loads a policy and acts on a few states
(:class:`~offline_adp.trees.loaded.LoadedEnsemble` then looks leaves up with numpy) never
pays it. :func:`kernel` wraps a plain function as one compiled on its first call; a
kernel called from another compiled kernel must be compiled eagerly instead (numba types
its callees), as the builder's are (:mod:`offline_adp.trees.builder_kernel`).
"""

from __future__ import annotations

import functools
import importlib.util
import sys
import threading
from collections.abc import Callable
from typing import Any

_LOCK = threading.Lock()


@functools.cache
def installed() -> bool:
    """Whether numba is installed (found, not imported): whether compiled lookups may be
    built at all."""
    return importlib.util.find_spec("numba") is not None


@functools.cache
def available() -> bool:
    """Whether numba imports here (it is imported by this call: call it where a compiled
    kernel is about to run). False where it is missing or its import fails (e.g. a numpy
    it does not support): then the numpy paths run."""
    if not installed():
        return False
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def warm() -> bool:
    """Whether numba is already imported in this process (a kernel compiled or loaded, or a
    module of compiled kernels imported): another compiled call then costs little more."""
    return "numba" in sys.modules


class LazyKernel:
    """``numba.njit(**options)(fn)``, made on the first call (threads wait for one copy)."""

    def __init__(self, fn: Callable[..., Any], options: dict[str, Any]) -> None:
        self.fn, self.options = fn, options
        self._compiled: Any = None
        functools.update_wrapper(self, fn)

    def __call__(self, *args: Any) -> Any:
        k = self._compiled
        if k is None:
            k = self.compiled()
        return k(*args)

    def __reduce__(self) -> tuple[Any, tuple[str, str]]:
        """Pickled by name, as a numba dispatcher of a module function is."""
        return _by_name, (self.fn.__module__, self.fn.__qualname__)

    def compiled(self) -> Any:
        """The numba dispatcher (imports numba on the first call)."""
        with _LOCK:
            if self._compiled is None:
                import numba

                self._compiled = numba.njit(**self.options)(self.fn)
        return self._compiled


def _by_name(module: str, name: str) -> Any:
    """The kernel ``name`` of ``module`` (unpickling a :class:`LazyKernel`)."""
    return getattr(importlib.import_module(module), name)


def kernel(fn: Callable[..., Any], **options: Any) -> Any:
    """``fn`` as a kernel compiled by numba on its first call (``options``: ``numba.njit``'s),
    or ``fn`` itself where numba is not installed. Callers check :func:`available` before
    choosing a path that calls it."""
    return LazyKernel(fn, options) if installed() else fn
