"""The epoch rules of the streaming assembler: which epoch each message belongs to, from the
file order alone (docs/ingestion-spec.md, "Epochs"), and the stale stamps among what a
stream held for a later epoch (rule 5)."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from offline_adp.ingest.mcap.buffers import _Buffer


class Jump(NamedTuple):
    """A stream gone ahead of the clock from its epoch, maybe on stale stamps (rule 5)."""

    epoch: int  #: the epoch it went to (the clock's next)
    before: int  #: its latest time before the jump
    first: int  #: its first time after it
    clock: int  #: the clock's latest time then
    in_step: list[int]  #: times of its messages in step while the clock has not moved since (held)


class EpochRules:
    """Mixin of the streaming assembler: its epoch state (``epoch``, ``maxt``, ``clock_first``,
    ``clock_seen``, ``jumped``, ``suspect``) and the rules that move it. Uses ``_orphan`` and
    ``_set_aside`` of :class:`~offline_adp.ingest.mcap.accounting.MessageAccounting` and
    ``_resolve_losses`` of :class:`~offline_adp.ingest.mcap.damage.DamageAccounting`."""

    epoch: dict[Any, int]
    maxt: dict[Any, int | None]
    bufs: dict[tuple[Any, int], _Buffer]
    clock_first: dict[int, int]
    clock_seen: dict[Any, int | None]
    jumped: dict[Any, Jump]
    suspect: dict[Any, int]
    clock_key: Any
    restart: int
    reorder: int
    active: int
    stats: dict[str, int]
    late: dict[str, int]
    topic_of: dict[Any, str]
    pending_losses: list[dict[str, Any]]

    def _epoch_of(self, k: Any, t: int) -> int | None:
        """The epoch of a message of key ``k`` at time ``t``, from the file order alone
        (never from what has been flushed): see "Epochs" in docs/ingestion-spec.md.

        The clock's epoch advances when its time jumps back more than ``restart``. Any
        other stream is placed against the clock's current epoch ``ce``, its first time
        ``cf`` and latest time ``cm``: a time in ``[cf - restart, cm - restart)`` is the
        next epoch's (the stream restarted before the clock); a stream still in ``ce - 1`` whose time has not
        jumped back and lies more than ``restart`` above ``cm`` is a late message of
        ``ce - 1``; anything else is ``ce``'s. A stream ahead of the clock stays ahead
        until the clock follows (a second jump back while ahead replaces its buffer: the
        clock skipped that epoch), or comes back in step first: at or after ``max(cm -
        restart, its latest time before the jump)`` and at most ``restart`` after the later
        of the two (near the clock's time again), once the clock has moved on since the
        jump and before the stream's time ran on for ``restart`` there; the message is then
        ``ce``'s and what it held is told at the clock's entry (:meth:`_stale_in`). None: the
        message belongs to an epoch that is over.
        """
        r = self.restart
        m, ek = self.maxt[k], self.epoch[k]
        own_restart = m is not None and r > 0 and t < m - r
        ck = self.clock_key
        if k == ck:
            e = ek + 1 if own_restart else ek
            back = own_restart or (m is not None and t < m)  # back in time by less than a restart: counted, said
            self.stats["restarts" if own_restart else "clock_steps_back"] += int(back)
            if e not in self.clock_first:
                self.clock_first[e] = t
                for k2 in self.epoch:
                    m2 = self.maxt[k2]
                    if k2 == ck or self.epoch[k2] != e or m2 is None:
                        continue
                    if m2 > t + self.reorder + r:  # ahead by more than the window: an epoch the clock skipped
                        self._orphan(k2, self.bufs.pop((k2, e), None))
                        self.maxt[k2] = None
                    elif self.clock_seen.get(k2) is None:  # there before the clock: its pace counts from here (rule 3)
                        self.clock_seen[k2] = t
                self._stale_in(e, t)
            if self.pending_losses:
                self._resolve_losses(e)
        else:
            ce, cm = self.epoch[ck], self.maxt[ck]
            seen = self.clock_seen.get(k)
            if m is not None and ek == ce and cm is not None and seen is not None and r > 0:
                # a stream keeps pace with the clock: it restarted if its time fell more than
                # `restart` behind its last time plus what the clock ran since (a stream silent
                # for most of an episode resumes in the next one at a time above its last)
                own_restart = t < m + max(cm - seen, 0) - r
            # the time jumped back within what the clock has covered in this epoch (older than the epoch's
            # first clock message: stale data of this epoch, e.g. a late localization stamp)
            ahead = cm is not None and r > 0 and self.clock_first.get(ce, cm) - r <= t < cm - r
            if (j := self.jumped.get(k)) is not None and (j.epoch != ek or ek != ce + 1 or m is None
                                                        or m - j.first >= r or own_restart):
                del self.jumped[k]  # the clock followed, or the stream's time ran on there: a restart
            j = self.jumped.get(k)
            # in step again (rule 5): near the clock's time, at or after its own time before the jump (a record
            # of its old timeline written out of order below that stays ahead: a new timeline could reach there)
            if j is not None and cm is not None and max(cm - r, j.before) <= t <= max(cm, j.before) + r:
                if cm == j.clock:  # the clock has not moved since the jump (a clock that stopped?): held till it does
                    j.in_step.append(t)
                    return ek if ek >= self.active else None
                del self.jumped[k]
                self._come_back(k, ek, ce, j.in_step)
                self.suspect[k], e = ek, ce
            elif m is not None and (ek == ce + 1 or cm is None):  # ahead of the clock (or before its first message)
                e = ek
                if own_restart:  # a second restart before the clock's: the clock has no such epoch
                    self._orphan(k, self.bufs.pop((k, ek), None))
            elif ek == ce and m is not None and not own_restart:
                e = ce
            elif ek == ce - 1 and m is not None and not own_restart and cm is not None and r > 0 and t > cm + r:
                e = ek  # a late message of the epoch before the clock's restart
                if cm - self.clock_first.get(ce, cm) >= self.reorder:
                    return None
            else:
                e = ce + 1 if ahead else ce
                if ahead and ek == ce and m is not None:  # gone ahead of the clock from its epoch
                    self.jumped[k] = Jump(e, m, t, cm, [])
        if e != ek:
            self.epoch[k], m = e, None
        elif own_restart:
            m = None
        if m is None or t > m:
            self.maxt[k] = t
            if k != ck:  # the clock's time when this stream's latest time was read (same epoch only)
                self.clock_seen[k] = self.maxt[ck] if e == self.epoch[ck] else None
        if e < self.active:  # defensive: never happens for messages on time (see the rules above)
            return None
        return e

    def _come_back(self, k: Any, held: int, e: int, times: list[int]) -> None:
        """Key ``k``'s messages at ``times``, held for epoch ``held`` while the clock stood still
        though they were in step with it, are epoch ``e``'s."""
        if times and (b := self.bufs.get((k, held))) is not None:
            back = b.take(np.isin(b.arrays()["t"], times))
            dst = self.bufs.setdefault((k, e), _Buffer(b.names, b.dtype))
            for i in range(len(back["t"])):
                dst.add(int(back["t"][i]), int(back["file"][i]), [back[n][i] for n in b.names], int(back["lt"][i]),
                        int(back["#id"][i]))

    def _stale_in(self, e: int, t: int) -> None:
        """The clock entered epoch ``e`` at time ``t``: what a stream back in step held for ``e``
        and lies more than ``reorder_window + restart`` after ``t`` was stale stamps, and the
        messages in step with the epoch before that a stream ahead held meanwhile (the clock
        had not moved) are not ``e``'s: late, not used (rule 5)."""
        for k in [k for k, j in self.jumped.items() if j.epoch == e]:  # the clock followed: a restart after all
            # (first: what it held in step are late records, not stale stamps, if it came back once before)
            times = self.jumped.pop(k).in_step
            if times and (b := self.bufs.get((k, e))) is not None:  # late records of the epoch before
                gone = b.take(np.isin(b.arrays()["t"], times))
                self._set_aside(k, "dropped_late", gone["#id"], gone["file"])
                self.late[self.topic_of[k]] += len(gone["t"])
        for k in [k for k, e2 in self.suspect.items() if e2 == e]:
            del self.suspect[k]
            if (b := self.bufs.get((k, e))) is not None:
                gone = b.take(b.arrays()["t"] > t + self.reorder + self.restart)
                self._set_aside(k, "stale", gone["#id"], gone["file"])
                if self.epoch[k] == e:
                    self.maxt[k] = int(b.arrays()["t"][-1]) if len(b) else None

    def _new_epoch_everywhere(self) -> None:
        e = max(self.epoch.values()) + 1
        for k in self.epoch:
            self.epoch[k], self.maxt[k] = e, None
