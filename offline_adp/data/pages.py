"""Small memory pages for a burst of fresh allocations (the Parquet ingestion).

Arrow's default allocator (mimalloc) reserves its arena with ``madvise(MADV_HUGEPAGE)``, and
numpy advises the same on every array of 4 MiB or more, so on Linux with transparent huge
pages in ``madvise`` mode (a common default) every first touch of such memory faults in a
2 MiB page that the kernel zeroes in one go. Measured on the 2M-row ingestion
(``benchmarks/ingest_parquet.py``, a 2-core KVM guest whose freed 2 MiB blocks the host
reclaims): 208 huge-page faults, system time 0.15 to 1.4 s between identical runs (median
0.6 s); with the process's transparent huge pages off, 109k small-page faults and 0.22 to
0.40 s (median 0.29 s), user time unchanged within noise.

:func:`small_pages` turns transparent huge pages off for the process
(``prctl(PR_SET_THP_DISABLE)``) while an ingestion runs and restores the previous setting
afterwards (memory faulted in meanwhile stays in small pages). Nothing is changed outside
Linux, nor when the call is refused.
"""

from __future__ import annotations

import contextlib
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any

_PR_SET_THP_DISABLE = 41
_PR_GET_THP_DISABLE = 42
_GUARD = threading.Lock()
_state: dict[str, Any] = {"depth": 0, "previous": None}


def _prctl() -> Callable[..., int] | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_PRCTL = _prctl()


def thp_disabled() -> bool | None:
    """Whether transparent huge pages are off for this process (None: not known here)."""
    if _PRCTL is None:
        return None
    r = _PRCTL(_PR_GET_THP_DISABLE, 0, 0, 0, 0)
    return None if r < 0 else bool(r)


@contextlib.contextmanager
def small_pages() -> Iterator[None]:
    """Within the block, the process faults in small pages only (see the module docstring);
    re-entrant and thread-safe: the setting found by the outermost block is restored when the
    last block ends."""
    with _GUARD:
        if _state["depth"] == 0 and _PRCTL is not None:
            previous = thp_disabled()
            if previous is False and _PRCTL(_PR_SET_THP_DISABLE, 1, 0, 0, 0) == 0:
                _state["previous"] = previous
            else:
                _state["previous"] = None  # already off, unknown or refused: nothing to restore
        _state["depth"] += 1
    try:
        yield
    finally:
        with _GUARD:
            _state["depth"] -= 1
            if _state["depth"] == 0 and _state["previous"] is False and _PRCTL is not None:
                _PRCTL(_PR_SET_THP_DISABLE, 0, 0, 0, 0)
                _state["previous"] = None
