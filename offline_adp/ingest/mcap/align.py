"""Alignment of one stream's values to step times."""

from __future__ import annotations

import numpy as np

from offline_adp.ingest.mcap.spec import StreamSpec

#: Said when a stream's messages are held for a later epoch than the clock's (its time
#: jumped back more than ``[episodes] restart``: read as a restart, which the clock did not
#: follow). Typical of /tf, where ``transforms[0]`` is another frame pair from message to
#: message, some future-dated.
AHEAD_OF_CLOCK = ("; that stream's time jumped back more than [episodes] restart = {r} s, read as a restart the "
                  "clock did not follow, so its later messages wait for a new epoch: raise restart above the "
                  "jump (or take that stream's values from messages of one kind)")


def _align(ts: np.ndarray, vals: np.ndarray, at: np.ndarray, s: StreamSpec,
           angle: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Values of one field at times ``at``; returns (values, ok mask). ``angle``: the values
    are headings in rad, and ``linear`` goes the short way round (from 3.0 to -3.0 through
    pi, not through 0), the result in [-pi, pi]."""
    max_age = int(s.max_age * 1e9)
    n = len(ts)
    if n == 0:
        return np.full(len(at), np.nan), np.zeros(len(at), bool)
    i = np.searchsorted(ts, at, side="right")  # ts[i-1] <= at < ts[i]
    prev = np.clip(i - 1, 0, n - 1)
    nxt = np.clip(i, 0, n - 1)
    has_prev = i > 0
    if s.align == "previous":
        ok = has_prev & (at - ts[prev] <= max_age)
        return vals[prev], ok
    if s.align == "nearest":
        use_next = (np.abs(ts[nxt] - at) < np.abs(at - ts[prev])) | ~has_prev
        j = np.where(use_next, nxt, prev)
        return vals[j], np.abs(ts[j] - at) <= max_age
    span = (ts[nxt] - ts[prev]).astype(np.float64)
    w = np.where(span > 0, (at - ts[prev]) / np.where(span > 0, span, 1.0), 0.0)
    ok = has_prev & (i < n) & (at - ts[prev] <= max_age) & (ts[nxt] - at <= max_age) | (ts[prev] == at)
    step = vals[nxt] - vals[prev]
    if angle:
        step = np.remainder(step + np.pi, 2 * np.pi) - np.pi
        out = vals[prev] + np.clip(w, 0, 1) * step
        return np.where(np.abs(out) > np.pi, np.remainder(out + np.pi, 2 * np.pi) - np.pi, out), ok
    return vals[prev] + np.clip(w, 0, 1) * step, ok
