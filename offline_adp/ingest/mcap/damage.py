"""The streaming assembler's damage accounting (:mod:`offline_adp.ingest.mcap.assembler`): which
epochs and time ranges the chunks lost to damage may have held, which steps and episodes
they touch, and the episodes whose start event was lost with them (docs/ingestion-spec.md,
"Reading, damage and streaming"). A mixin of the assembler's recording, whose state it reads.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.ingest.mcap.records import EpisodeRows
from offline_adp.ingest.mcap.spec import McapSpec


class DamageAccounting:
    """Lost chunks (the scan's ``lost_chunks`` of every file read so far) against the
    assembler's epochs: the state below is the recording's (``assembler._Recording``)."""

    spec: McapSpec
    stats: dict[str, int]
    epoch: dict[Any, int]
    clock_key: Any
    clock_first: dict[int, int]
    reorder: int
    live_reports: list[dict[str, Any]]
    pending_losses: list[dict[str, Any]]
    n_lost_seen: int
    event_kinds: list[str | None]

    def _lost_ranges(self, e: int) -> list[tuple[float, float]]:
        """Time ranges (widened by the reorder window) of the chunks lost so far that may
        have held messages of epoch ``e``."""
        out: list[tuple[float, float]] = []
        for r in self.live_reports:
            for c in r.get("lost_chunks", []):
                out += [(a - self.reorder, b + self.reorder) for ep, a, b in c.get("_epochs", ()) if ep == e]
        return out

    def _damaged(self, e: int, t: np.ndarray) -> np.ndarray:
        out = np.zeros(len(t), bool)
        for a, b in self._lost_ranges(e):
            out |= (t >= a) & (t <= b)
        return out

    def _note_losses(self, report: dict[str, Any]) -> None:
        """Chunks lost since the last message: they held messages of the clock's current
        epoch and, if the clock restarted inside them, of the next ones (known at the next
        clock message; see ``_resolve_losses``)."""
        lost = report.get("lost_chunks", [])
        for c in lost[self.n_lost_seen:]:
            self._count_lost_events(report, c)
            ce = self.epoch[self.clock_key]
            c["_ce"] = ce
            a, b = float(c.get("start_ns", -np.inf)), float(c.get("end_ns", np.inf))
            c["_epochs"] = [(ce, a, b), (ce + 1, a, b)]  # until the next clock message says more
            self.pending_losses.append(c)
        self.n_lost_seen = len(lost)

    def _count_lost_events(self, report: dict[str, Any], c: dict[str, Any]) -> None:
        """Add the episode events a lost chunk held (from the message-index records that
        follow it, see ``scan._index_of_lost_chunk``) to :attr:`event_kinds` as unknown
        (None), in file order; a chunk without a usable index is counted as uncounted."""
        if not self.spec.episode_topic:
            return
        if c.get("message"):  # one message that did not decode: an event if on the episode topic
            self.event_kinds += [None] * (c.get("topic") == self.spec.episode_topic)
            return
        index = c.get("_index")
        chans = report.get("channels", {})
        ids = [i for i, ch in chans.items() if ch.topic == self.spec.episode_topic]
        if index is None or c.get("_index_damaged") or not ids and any(i not in chans for i in index):
            self.stats["lost_chunks_uncounted"] += 1  # episodes_lost_to_damage is then a lower bound
            return
        times = sorted(t for i in ids for t in index.get(i, ()))
        self.event_kinds += [None] * len(times)

    def _episodes_never_seen(self) -> int:
        """Episodes whose start event was lost to damage: no step of theirs was assembled
        (they are in no episode), so only the events can tell. A lost event's kind is read
        from the alternation of starts and ends (after a start, an end; else a start);
        without an event field every event is a start."""
        if "event_field" not in self.spec.episode_fields:
            return sum(k is None for k in self.event_kinds)
        n, prev = 0, None
        for k in self.event_kinds:  # one entry per episode event (the episodes' count, not the rows')
            if k is None:
                k = "end" if prev == "start" else "start"
                n += k == "start"
            if k in ("start", "end"):
                prev = k
        return n

    def _resolve_losses(self, ce_after: int) -> None:
        """The epochs a lost chunk may have held: every epoch from the one the clock was in
        when it was lost to the one of the next clock message; the first and the last only
        within the chunk's time range (the last only if the chunk reaches back to its start)."""
        for c in self.pending_losses:
            ce, a, b = c["_ce"], float(c.get("start_ns", -np.inf)), float(c.get("end_ns", np.inf))
            eps = [(ce, a, b)] + [(e, -np.inf, np.inf) for e in range(ce + 1, ce_after)]
            if ce_after > ce and a <= self.clock_first.get(ce_after, np.inf) + self.reorder:
                eps.append((ce_after, a, b))
            c["_epochs"] = eps
        self.pending_losses = []

    def _episode_damaged(self, ep: EpisodeRows) -> str:
        """The reason an episode is lost to damage ("" if it is not)."""
        for r in self.live_reports:
            for c in r.get("lost_chunks", []):
                for e, a, b in c.get("_epochs", ()):
                    if e == ep.epoch and ep.t[0] <= b + self.reorder and ep.t_end >= a - self.reorder:
                        return f"damage: lost chunk at offset {c['offset']} of {r.get('_path', 'the file')}"
        return ""
