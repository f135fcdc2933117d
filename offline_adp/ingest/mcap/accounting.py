"""What became of each message read: the per-topic counts of an MCAP ingest.

Per topic, per file and per recording, the messages of a file are partitioned as

    messages_read = messages_used + messages_skipped + messages_unselected + messages_orphaned
                    + messages_stale + messages_dropped_late + messages_undecodable

``skipped``: a topic the spec does not read (never decoded). ``unselected``: decoded, but
for no key of the spec: each reads a field path with a selector (``transforms[child_frame_id=
base_link]``) that found no element in it (a /tf message of another frame pair). ``undecodable``: a message of
a spec topic that did not decode (``on_error = "quarantine"``; a damaged chunk's
messages are not read at all and are not counted here, see ``recovered``). Of the decoded
messages, ``orphaned`` ones were held for an epoch the clock never reached, ``stale``
ones were held after their stream's time jumped back more than ``restart``, a jump that
proved no restart (rule 5 of "Epochs" in docs/ingestion-spec.md), and ``dropped_late`` ones
came after their epoch was over; every other decoded message is
``used``: placed against the clock's steps of its epoch (a 100 Hz stream aligned to a
10 Hz clock gives values to a tenth of the steps' rows, yet all its messages are used in
this sense). A message that feeds several keys (the clock and a stream, two streams of one
topic) is used if any of them used it; set aside by all that took it (a key whose selector
found no element does not take it), it counts under the first of their reasons in
:data:`ASIDE`'s order.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np

#: The reasons a decoded message is set aside, unused (a message several keys set aside
#: counts under the first of their reasons in this order).
ASIDE = ("orphaned", "stale", "dropped_late")


class MessageAccounting:
    """Mixin of the streaming assembler: per-topic, per-file counts of decoded messages and
    of those set aside. Needs ``by_topic``, ``topic_of`` and ``stats`` of the assembler."""

    by_topic: dict[str, list[Any]]
    topic_of: dict[Any, str]
    stats: dict[str, int]
    reports: list[dict[str, Any]]

    def _init_accounting(self) -> None:
        self.decoded = {t: 0 for t in self.by_topic}  # per topic: messages decoded (the next message's id)
        self.aside: dict[str, Counter[tuple[int, str]]] = {w: Counter() for w in (*ASIDE, "unselected")}
        # per topic of several keys, once a message was not for all of them: how many keys took each message
        self.takers: dict[str, bytearray] = {}
        self.selector_values: dict[Any, set[str]] = {}  # per key: values its selectors saw where none matched
        self.partial: dict[tuple[str, int], tuple[int, str]] = {}  # a message some of its keys set aside
        self.report_files: list[int] = []  # the file index of each entry of ``reports``

    def _taken(self, topic: str, mid: int, file_index: int, n: int) -> None:
        """Message ``mid`` of ``topic`` is for ``n`` of the topic's keys (0: unselected)."""
        keys = len(self.by_topic[topic])
        if n == 0:
            self.aside["unselected"][(file_index, topic)] += 1
        if keys > 1 and (topic in self.takers or n != keys):
            took = self.takers.setdefault(topic, bytearray([min(keys, 255)]) * mid)
            took.append(min(n, 255))

    def _set_aside(self, k: Any, why: str, ids: Any, files: Any) -> None:
        """Messages ``ids`` (of key ``k``'s topic, read from files ``files``) are not used by ``k``."""
        topic = self.topic_of[k]
        n_keys = len(self.by_topic[topic])
        took = self.takers.get(topic)
        if n_keys == 1:  # the common case, counted per file without a loop over the messages
            fs, ns = np.unique(np.asarray(files, dtype=np.int64), return_counts=True)
            for f, n in zip(fs.tolist(), ns.tolist(), strict=True):
                self.aside[why][(f, topic)] += n
            if why == "orphaned":
                self.stats["orphan_messages"] += int(ns.sum())
            return
        for i, f in zip(np.asarray(ids).tolist(), np.asarray(files).tolist(), strict=True):
            w = why
            if n_keys > 1:
                seen, w0 = self.partial.pop((topic, i), (0, why))
                w = min(w0, why, key=ASIDE.index)
                if seen + 1 < (n_keys if took is None else took[i]):
                    self.partial[(topic, i)] = (seen + 1, w)
                    continue
            self.aside[w][(f, topic)] += 1
            if w == "orphaned":
                self.stats["orphan_messages"] += 1

    def _orphan(self, k: Any, b: Any) -> None:
        """Key ``k``'s buffer ``b`` (or None) holds messages of an epoch the clock never reached."""
        self._set_aside_buffer(k, b, "orphaned")

    def _set_aside_buffer(self, k: Any, b: Any, why: str) -> None:
        """Key ``k``'s buffer ``b`` (or None) is not used, for reason ``why`` (one of :data:`ASIDE`)."""
        if b is not None and len(b):
            a = b.arrays()
            self._set_aside(k, why, a["#id"], a["file"])

    def _per_topic(self, why: str, file_index: int | None = None) -> dict[str, int]:
        out: dict[str, int] = {}
        for (f, t), n in self.aside[why].items():
            if n and (file_index is None or f == file_index):
                out[t] = out.get(t, 0) + n
        return out

    def used_counts(self) -> dict[str, int]:
        """Per topic of the spec: messages decoded and placed against the clock's steps."""
        gone: Counter[str] = sum((Counter(self._per_topic(w)) for w in (*ASIDE, "unselected")), Counter())
        return {t: n - gone.get(t, 0) for t, n in self.decoded.items()}

    def _settle_file_counts(self) -> None:
        """Each file entry's counts, once nothing more can be set aside (orphans are known
        when the clock enters an epoch or the recording ends: after their file was read)."""
        for entry, fi in zip(self.reports, self.report_files, strict=True):
            decoded, rest = entry.pop("_decoded"), dict(entry)
            orphaned, late, stale, unsel = (self._per_topic(w, fi) for w in ("orphaned", "dropped_late", "stale",
                                                                              "unselected"))
            read = Counter(decoded) + Counter(entry["messages_skipped"]) + Counter(entry["messages_undecodable"])
            entry.clear()
            entry.update(path=rest.pop("path"), messages_read={t: read[t] for t in sorted(read)},
                         messages_used={t: n - orphaned.get(t, 0) - late.get(t, 0) - stale.get(t, 0)
                                        - unsel.get(t, 0) for t, n in decoded.items()},
                         messages_skipped=rest.pop("messages_skipped"), messages_unselected=unsel,
                         messages_orphaned=orphaned,
                         messages_stale=stale, messages_dropped_late=late,
                         messages_undecodable=rest.pop("messages_undecodable"), **rest)
