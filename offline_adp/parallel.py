"""Where independent pieces of work run: here (the default) or on a Dask cluster.

A *task map* has the signature ``task_map(fn, items, shared=None, on_done=None) -> list``
and returns ``[fn(item, **shared) for item in items]`` in the order of ``items``. The
local one is a plain loop; :class:`offline_adp.engines.dask.DaskTaskMap` sends each item
to a worker with the ``shared`` objects broadcast once. Callers split their work into a
number of pieces that does not depend on the engine (with a seed per piece), so both
give the same result.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any, Protocol


class TaskMap(Protocol):
    def __call__(self, fn: Callable[..., Any], items: Sequence[Any], shared: dict[str, Any] | None = None,
                 on_done: Callable[[int], None] | None = None) -> list[Any]: ...


def local_map(fn: Callable[..., Any], items: Iterable[Any], shared: dict[str, Any] | None = None,
              on_done: Callable[[int], None] | None = None) -> list[Any]:
    """``[fn(item, **shared) for item in items]``; ``on_done(k)`` after the k-th item (0-based)."""
    out = []
    for k, item in enumerate(items):
        out.append(fn(item, **(shared or {})))
        if on_done is not None:
            on_done(k)
    return out
