"""The streaming assembler: epochs, watermark, buffers, steps."""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap.accounting import MessageAccounting
from offline_adp.ingest.mcap.align import AHEAD_OF_CLOCK, _align
from offline_adp.ingest.mcap.buffers import _Buffer
from offline_adp.ingest.mcap.damage import DamageAccounting
from offline_adp.ingest.mcap.decode import NoElement, _Decoders, _msg_time, numeric_fields
from offline_adp.ingest.mcap.episodes import EpisodeSegmenter, read_event
from offline_adp.ingest.mcap.epochs import EpochRules, Jump
from offline_adp.ingest.mcap.presence import check_topic_present
from offline_adp.ingest.mcap.records import EpisodeRows, Message, RecordingResult
from offline_adp.ingest.mcap.rosbags_source import is_rosbags_input, read_rosbags
from offline_adp.ingest.mcap.scan import damage_text, scan_records
from offline_adp.ingest.mcap.spec import McapSpec, StreamSpec


class _Recording(EpisodeSegmenter, DamageAccounting, MessageAccounting, EpochRules):
    """Streams one recording (one file, or the parts of a split recording) into episodes.

    Steps: the clock topic's messages (or ``rate_hz`` ticks over the first observation
    stream). A step is aligned once every stream has moved ``reorder_window`` plus its
    ``max_age`` past it; buffers are then pruned, so memory holds the episode being
    assembled and a few seconds of messages, whatever the file size.
    """

    def __init__(self, files: list[Path], spec: McapSpec, on_error: str, file_index: int,
                 flush_every: int = 5000) -> None:
        self.files, self.spec, self.on_error, self.file0 = files, spec, on_error, file_index
        self.flush_every = max(int(flush_every), 1)
        self.cut = False
        self.final = False
        self.pending_drop = False  # the last steps assembled were dropped: the next kept one starts an episode
        self.n_since = 0
        self.name = re.sub(r"_\d+$", "", files[0].stem) if len(files) > 1 else files[0].stem
        self.value_keys: dict[Any, StreamSpec] = {("s", i): s for i, s in enumerate(spec.streams)}
        self.value_keys["action"] = spec.action_stream
        self.clock_key: Any = "clock" if spec.clock_topic else ("s", next(i for i, s in enumerate(spec.streams)
                                                                          if s.role == "obs"))
        self.by_topic: dict[str, list[Any]] = {}
        for k, s in self.value_keys.items():
            self.by_topic.setdefault(s.topic, []).append(k)
        if spec.clock_topic:
            self.by_topic.setdefault(spec.clock_topic, []).append("clock")
        if spec.episode_topic:
            self.by_topic.setdefault(spec.episode_topic, []).append("events")
        self.topic_of = {k: t for t, ks in self.by_topic.items() for k in ks}
        for keys in self.by_topic.values():  # the clock first: the other keys of its message are placed against it
            keys.sort(key=lambda x: x != self.clock_key)
        self.names = {k: list(s.fields) for k, s in self.value_keys.items()}
        self.names["clock"] = []
        self.names["events"] = list(spec.episode_fields)
        self.epoch: dict[Any, int] = {k: 0 for ks in self.by_topic.values() for k in ks}
        self.maxt: dict[Any, int | None] = {k: None for k in self.epoch}
        self.bufs: dict[tuple[Any, int], _Buffer] = {}
        self.clock_first: dict[int, int] = {}
        self.clock_seen: dict[Any, int | None] = {}
        self.jumped: dict[Any, Jump] = {}  # streams gone ahead of the clock, maybe on stale stamps (rule 5)
        # back in step: the epoch a stream held messages for (stale stamps among them told when the clock gets there)
        self.suspect: dict[Any, int] = {}
        self.active = 0
        self.flushed_t: int | None = None  # time of the last step handed to the episodes
        self.lag = int((spec.reorder_window + max(s.max_age for s in self.value_keys.values())) * 1e9)
        self.reorder = int(spec.reorder_window * 1e9)
        self.restart = int(spec.restart * 1e9)
        self.next_tick: int | None = None
        self.last_step_t: int | None = None
        self.last_episode_value: np.ndarray | None = None
        self.waiting: Any = None  # key of an episode an end/terminal condition closed, while it still holds
        self.counter = 0
        self.seg = 0
        self.event_info: dict[Any, tuple[str, str | None, bool | None]] = {}
        self.splits: dict[Any, int] = {}
        self.cur: Any = None  # the episode being assembled (episodes._Episode)
        self.out: list[EpisodeRows] = []
        self.late = {t: 0 for t in self.by_topic}
        self.filled = {t: 0 for t in self.by_topic}  # steps given a stream's fill value (missing = "fill")
        self.stats = {"dropped_steps": 0, "outside_episode_steps": 0, "condition_steps": 0, "short_episodes": 0,
                      "incomplete_episodes": 0, "episodes_lost_to_damage": 0, "damaged_steps": 0, "restarts": 0,
                      "orphan_messages": 0, "cut_episodes": 0, "episodes_without_command": 0,
                      "episode_splits": 0, "lost_chunks_uncounted": 0, "clock_steps_back": 0,
                      "duplicate_clock_times": 0, "max_buffered_messages": 0}
        self.reports: list[dict[str, Any]] = []
        self._init_accounting()
        self.key_missed: Counter[Any] = Counter()  # per key: messages its selectors found no element in
        self.live_reports: list[dict[str, Any]] = []
        self.pending_losses: list[dict[str, Any]] = []  # lost chunks whose epochs are not known yet
        self.n_lost_seen = 0
        # episode events in file order: their kind ("start", "end"), None for one lost in a damaged chunk
        self.event_kinds: list[str | None] = []
        obs = spec.obs_names
        aux = spec.aux_names
        self.col = {n: ("obs", obs.index(n)) for n in obs} | {n: ("aux", aux.index(n)) for n in aux}
        self.episode_fields = [n for s in spec.streams if s.role == "episode" for n in s.fields]

    # ------------------------------------------------------------------ reading
    def run(self) -> RecordingResult:
        for fi, path in enumerate(self.files):
            if fi and self.spec.per_file:
                self._new_epoch_everywhere()
            self._read(path, self.file0 + fi)
        return self.finish(cut=bool(self.live_reports) and "lost_from_offset" in self.live_reports[-1])

    def feed(self, messages: Iterable[Message], file_index: int | None = None) -> None:
        """Add decoded messages in file order (flushing every ``flush_every`` messages)."""
        fi = self.file0 if file_index is None else file_index
        for m in messages:
            self._add(m, fi)
            self.n_since += 1
            if self.n_since >= self.flush_every:
                self.n_since = 0
                self._flush()

    def finish(self, cut: bool = False) -> RecordingResult:
        """Assemble what is left. Episodes damage touched, and with ``cut`` (the recording
        ends inside a record) the episode it ends in, are marked rejected (``reason``), counted.
        """
        if self.pending_losses:
            self._resolve_losses(self.epoch[self.clock_key])
        self.cut = cut
        self._flush(final=True)
        for ep in self.out:
            if not ep.reason and (lost := self._episode_damaged(ep)):
                ep.reason = lost
                self.stats["episodes_lost_to_damage"] += 1
        self.stats["episodes_lost_to_damage"] += self._episodes_never_seen()
        self._settle_file_counts()
        missing = [t for t, n in self.decoded.items() if n == 0 and t != self.spec.episode_topic]
        orphaned, late = self._per_topic("orphaned"), self._per_topic("dropped_late")
        return RecordingResult(self.out, self.stats, self.used_counts(), self.late, self.reports, missing, self.filled,
                               dict(self.decoded), orphaned, late, self._per_topic("stale"),
                               self._per_topic("unselected"), self._selector_misses())

    def _read(self, path: Path, file_index: int) -> None:
        report: dict[str, Any] = {"_path": str(path)}
        self.live_reports.append(report)  # lost chunks become known while reading
        before = dict(self.decoded)
        decoders = _Decoders()
        try:
            if is_rosbags_input(path):  # a ROS 1 .bag or a rosbag2 SQLite bag: the rosbags readers
                for m in read_rosbags(path, set(self.by_topic), report):
                    self.feed((m,), file_index)
            else:
                self._read_mcap(path, file_index, report, decoders)
        except IngestError as exc:
            if str(path) in str(exc):
                raise
            raise IngestError(f"{path}: {exc}") from None
        except (KeyError, AttributeError, IndexError, TypeError, ValueError) as exc:
            raise IngestError(f"{path}: a field path of the spec does not match the messages ({type(exc).__name__}: "
                              f"{exc}); run `offline-adp mcap-info` to list the fields") from exc
        except Exception as exc:  # noqa: BLE001 - any other library error becomes ours, naming the file
            raise IngestError(f"{path}: cannot read as MCAP ({type(exc).__name__}: {exc})") from exc
        self._note_losses(report)
        text = damage_text(path, report)
        entry = {"path": str(path), "_decoded": {t: n - before[t] for t, n in self.decoded.items()},
                 "messages_skipped": dict(Counter(report.get("skipped", {}))),
                 "messages_undecodable": dict(Counter(c["topic"] for c in report.get("lost_chunks", ())
                                                      if c.get("message"))),
                 **({"empty": True} if report.get("empty") else {})}
        if text:
            lost = [{k: v for k, v in c.items() if not k.startswith("_")} for c in report["lost_chunks"]]
            entry["recovered"] = {"messages": report["messages"], "lost_chunks": lost,
                                  **{k: report[k] for k in ("lost_from_offset", "damaged", "messages_lost")
                                     if k in report},
                                  "text": text}
            # a file merely cut short is kept (its last episode is not)
            if self.on_error == "fail" and report["lost_chunks"]:
                raise IngestError(text + "; re-run with --on-error quarantine to keep what was recovered")
            import warnings

            warnings.warn(text, stacklevel=4)
        self.reports.append(entry)
        self.report_files.append(file_index)

    def _read_mcap(self, path: Path, file_index: int, report: dict[str, Any], decoders: _Decoders) -> None:
        add, every = self._add_fields, self.flush_every
        lost = report.setdefault("lost_chunks", [])
        with open(path, "rb") as f:
            self.n_lost_seen = 0
            for sch, ch, msg in scan_records(f, set(self.by_topic), report):
                if len(lost) > self.n_lost_seen:
                    self._note_losses(report)
                dec = decoders(sch, ch)
                if dec is None:
                    raise IngestError(f"{path}: needed topic {ch.topic!r} has message encoding "
                                      f"{ch.message_encoding!r} (schema {getattr(sch, 'name', '')!r}, encoding "
                                      f"{getattr(sch, 'encoding', '')!r}) that no installed decoder reads")
                try:
                    value = dec(msg.data)
                except Exception as exc:  # noqa: BLE001 - each decoder library raises its own types
                    why = (f"topic {ch.topic!r}, message at log_time {msg.log_time}: cannot be decoded as "
                           f"{ch.message_encoding} ({type(exc).__name__}: {exc})")
                    if self.on_error == "fail":
                        raise IngestError(f"{path}: {why}") from None
                    # lost, as a damaged chunk's messages: the episode around it is set aside, not the file
                    lost.append({"offset": None, "message": True, "topic": ch.topic, "start_ns": int(msg.log_time),
                                 "end_ns": int(msg.log_time), "error": why})
                    continue
                add(ch.topic, msg.log_time, msg.publish_time, value, file_index)
                self.n_since += 1
                if self.n_since >= every:  # as feed(): one flush per flush_every messages
                    self.n_since = 0
                    self._flush()

    def _check_topic_present(self, topic: str, step: str) -> None:
        check_topic_present(self.files, topic, step)

    def _add(self, msg: Message, file_index: int) -> None:
        self._add_fields(msg.topic, msg.log_time, msg.publish_time, msg.data, file_index)

    def _add_fields(self, topic: str, log_time: int, publish_time: int, dec: Any, file_index: int) -> None:
        mid = self.decoded[topic]  # the message's id: its place among the topic's decoded messages
        self.decoded[topic] += 1
        late = False  # once per message, whichever of its keys finds it late
        times: dict[str, int] = {}  # one time per time field of this message
        taken = []  # (key, time, values) of each key the message is for (a selector [key=value] may say not)
        for k in self.by_topic[topic]:
            try:
                taken.append((k, *self._read_key(k, topic, log_time, publish_time, dec, times)))
            except NoElement as exc:  # e.g. a /tf message of another frame pair: not this stream's
                self.key_missed[k] += 1
                seen = self.selector_values.setdefault(k, set())
                seen.update(exc.seen[: max(0, 20 - len(seen))])
        self._taken(topic, mid, file_index, len(taken))
        for k, t, values in taken:
            if k == "events":
                fields = list(self.spec.episode_fields)
                self.event_kinds.append(str(values[fields.index("event_field")]) if "event_field" in fields
                                        else "start")
            e = self._epoch_of(k, t)
            if e is None:  # late for an epoch already over (by file order, not by flush points): not used
                late = True
                self._set_aside(k, "dropped_late", [mid], [file_index])
                continue
            if e == self.active and self.flushed_t is not None and t < self.flushed_t - self.lag:
                late = True  # steps before it were aligned without it
            b = self.bufs.get((k, e))
            if b is None:
                b = self.bufs[(k, e)] = _Buffer(self.names[k], object if k == "events" else np.float64)
            b.add(t, file_index, values, int(log_time), mid)
        self.late[topic] += late

    def _selector_note(self, k: Any) -> str:
        """Why key ``k`` may lack messages: its selectors found no element in some (what they saw)."""
        seen = self.selector_values.get(k)
        if not seen:
            return ""
        topic = self.topic_of[k]
        n = self.decoded[topic]
        return (f"; its field paths' selector [key=value] found no element in {self.key_missed[k]} of the {n} "
                f"{topic} messages so far (values seen: {sorted(seen)[:20]})")

    def _selector_misses(self) -> dict[str, list[str]]:
        """Keys whose selectors found their element in none of their topic's messages: the
        spec's place of each (``streams[1] (/tf)``) and the values its selectors saw instead."""
        out = {}
        for k, seen in self.selector_values.items():
            if self.key_missed[k] == self.decoded[self.topic_of[k]]:
                where = {"clock": "clock", "events": "episodes", "action": "action"}.get(k, f"streams[{k[1]}]")
                out[f"{where} ({self.topic_of[k]})"] = sorted(seen)
        return out

    def _read_key(self, k: Any, topic: str, log_time: int, publish_time: int, dec: Any,
                  times: dict[str, int]) -> tuple[int, list[Any]]:
        """Key ``k``'s time and values in a decoded message (NoElement: the message is not ``k``'s)."""
        if k == "events":
            return int(log_time), read_event(dec, self.spec.episode_fields, topic, log_time)
        which = self.spec.clock_time if k == "clock" else self.value_keys[k].time
        exact = k == "action" and self.spec.action.type == "continuous"  # a boolean is no such command
        values = [] if k == "clock" else numeric_fields(dec, self.value_keys[k].fields, topic, log_time,
                                                        command=exact)
        t = times.get(which)
        if t is None:
            try:
                t = times[which] = _msg_time(which, log_time, publish_time, dec)
            except (KeyError, AttributeError, IndexError, TypeError, ValueError, OverflowError) as exc:
                raise IngestError(f"topic {topic!r}, message at log_time {int(log_time)}: its time field {which!r} "
                                  f"cannot be read ({type(exc).__name__}: {exc}); run `offline-adp mcap-info` to "
                                  "list the fields") from None
        return t, values

    # ------------------------------------------------------------------ flushing
    def _watermark(self, e: int) -> float:
        """Steps of epoch ``e`` up to this time have all their data (inf: the epoch is over)."""
        ce = self.epoch[self.clock_key]
        if ce > e:
            now = self.maxt[self.clock_key] or 0
            if (ce > e + 1 or all(v > e for v in self.epoch.values())
                    or now - self.clock_first.get(ce, now) >= self.reorder):  # no message can still join e
                return np.inf
        latest = [self.maxt[k] for k in self.epoch if self.epoch[k] == e and self.maxt[k] is not None]
        if not latest:
            return -np.inf
        cm = self.maxt[self.clock_key]
        # the clock's time is the reference (a stream's time far ahead of it is anomalous
        # data and must not make the others look idle); without the clock in e, the latest
        top = cm if ce == e and cm is not None else max(latest)
        span = top - self.clock_first.get(e, top)
        w = np.inf
        for k in self.epoch:
            if k == "events":
                continue
            mk = self.maxt[k]
            if self.epoch[k] > e:
                if ce != e or (j := self.jumped.get(k)) is None or j.epoch != e + 1:
                    continue
                mk = j.before  # gone ahead from e on a stamp that may be stale: it may come back
            elif self.epoch[k] < e or mk is None:
                if span <= self.reorder:
                    return -np.inf  # this stream may still come (e.g. written topic by topic)
                continue
            if mk < top - self.reorder:
                continue  # an idle stream (event-driven commands): do not wait for it
            w = min(w, mk)
        return w - self.lag

    def _flush(self, final: bool = False) -> None:
        self.final = final
        held = sum(len(b) for b in self.bufs.values())
        self.stats["max_buffered_messages"] = max(self.stats["max_buffered_messages"], held)
        while True:
            e = self.active
            w = np.inf if final else self._watermark(e)
            if w == -np.inf:
                return
            self._emit_ready(e, w)
            if w != np.inf:
                return
            self._close(None, cut=final and self.cut and self.active == max(self.epoch.values()))
            # the epoch is over: so is its episode (in the last epoch of a cut recording: cut)
            for k in [k for k in self.bufs if k[1] == e]:  # an epoch the clock never reached: orphan messages
                b = self.bufs.pop(k)
                if e not in self.clock_first:  # back in step and stayed: stale stamps (rule 5)
                    back = self.suspect.get(k[0]) == e and self.epoch[k[0]] < e
                    self._set_aside_buffer(k[0], b, "stale" if back else "orphaned")
            self.last_step_t, self.last_episode_value, self.next_tick, self.waiting = None, None, None, None
            self.pending_drop = False
            self.flushed_t = None
            self.active += 1
            if self.active > max([*self.epoch.values(), *(e2 for _, e2 in self.bufs)]):  # held for later epochs too
                return

    def _ticks(self, e: int, w: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Step times, their files and the log_time of the message that made each step:
        clock messages, or rate_hz ticks over the reference stream."""
        none = np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0, np.int64)
        b = self.bufs.get((self.clock_key, e))
        if b is None:
            return none
        a = b.arrays()
        start = 0 if self.flushed_t is None else int(np.searchsorted(a["t"], self.flushed_t, side="right"))
        stop = len(a["t"]) if w == np.inf else int(np.searchsorted(a["t"], w, side="right"))
        t, f, lt = a["t"][start:stop], a["file"][start:stop], a["lt"][start:stop]
        if self.spec.rate_hz is None:
            same = t[1:] == t[:-1]  # a clock time repeated: one step, made by its last message
            self.stats["duplicate_clock_times"] += int(same.sum())
            return (t, f, lt) if not same.any() else tuple(v[np.r_[~same, True]] for v in (t, f, lt))  # type: ignore[return-value]
        period = int(round(1e9 / self.spec.rate_hz))
        gap = int(self.spec.gap * 1e9)
        out_t, out_f, out_lt = [], [], []
        prev = self.flushed_t
        # per reference message, not per row of data
        for ti, fi, li in zip(t.tolist(), f.tolist(), lt.tolist(), strict=True):
            if self.next_tick is None or prev is None or ti - prev > gap:
                self.next_tick = ti
            if self.next_tick <= ti:
                k = np.arange(self.next_tick, ti + 1, period, dtype=np.int64)
                out_t.append(k)
                out_f.append(np.full(len(k), fi, np.int32))
                out_lt.append(np.full(len(k), li, np.int64))
                self.next_tick = int(k[-1]) + period
            prev = ti
        if not out_t:
            return none
        return np.concatenate(out_t), np.concatenate(out_f), np.concatenate(out_lt)

    def _emit_ready(self, e: int, w: float) -> None:
        times, files, lts = self._ticks(e, w)
        if len(times):
            last_clock = self.bufs[(self.clock_key, e)].arrays()["t"]
            at = len(last_clock) if w == np.inf else np.searchsorted(last_clock, w, side="right")
            upto = int(last_clock[at - 1])
            self._steps(e, times, files, lts)
            self.flushed_t = upto
            for (k, ek), b in self.bufs.items():
                if ek == e and k != "events":
                    b.prune(upto - self.lag)

    def _steps(self, e: int, times: np.ndarray, files: np.ndarray, lts: np.ndarray) -> None:
        spec = self.spec
        n = len(times)
        obs = np.empty((n, len(spec.obs_names)))
        aux = np.empty((n, len(spec.aux_names)))
        keep = np.ones(n, bool)
        damaged = self._damaged(e, times)  # steps whose messages may be in a lost chunk: their episode is left out
        if self.cut and e == max(self.epoch.values()):  # steps whose data may have been written after the cut
            top = max((m for k, m in self.maxt.items() if m is not None and self.epoch[k] == e), default=None)
            if top is not None:
                damaged |= times >= top - self.lag
        missing_here = np.zeros(n, bool)
        act_cols: list[np.ndarray] = []
        act_ok = np.ones(n, bool)
        for k, s in self.value_keys.items():
            b = self.bufs.get((k, e))
            a = b.arrays() if b is not None else {"t": np.zeros(0, np.int64), **{nm: np.zeros(0) for nm in s.fields}}
            for name in s.fields:
                v, good = _align(a["t"], a[name], times, s, angle=isinstance(s.fields[name], dict))
                if s.missing == "fill":
                    self.filled[s.topic] += int((~good).sum()) if name == next(iter(s.fields)) else 0  # steps
                    v, good = np.where(good, v, s.fill), np.ones(n, bool)
                elif s.missing == "drop_step":
                    keep &= good
                elif k != "action":
                    if not (good | damaged).all():
                        j = int(np.flatnonzero(~(good | damaged))[0])
                        step = (f"step at t = {times[j] / 1e9:.6f} s (log_time {int(lts[j])}) has no value for "
                                f"{name!r} (use missing = 'fill' or 'drop_step')")
                        if self.decoded[s.topic] == 0:  # nothing on it so far: is it in the file at all?
                            self._check_topic_present(s.topic, step)
                        raise IngestError(f"{self.files[files[j] - self.file0]}: step at t = {times[j] / 1e9:.6f} s "
                                          f"(log_time {int(lts[j])}): no {s.topic} message within max_age = "
                                          f"{s.max_age} s for {name!r} (use missing = 'fill' or 'drop_step')"
                                          + (AHEAD_OF_CLOCK.format(r=self.restart / 1e9) if self.epoch[k] > e else "")
                                          + self._selector_note(k))
                    missing_here |= ~good
                if k == "action":
                    act_cols.append(v)
                    act_ok = act_ok & good
                else:
                    where, j = self.col[name]
                    (obs if where == "obs" else aux)[:, j] = v
        act = act_cols[0] if len(act_cols) == 1 else np.column_stack(act_cols)  # a vector action: one column each
        hit = damaged & (missing_here | ~keep)  # lacks data that damage may have taken: episode rejected
        self.stats["damaged_steps"] += int(hit.sum())
        self.stats["dropped_steps"] += int((~keep & ~hit).sum())
        keep |= hit
        # a dropped step inside an episode splits it (no transition is stitched across the gap)
        cum = np.cumsum(~keep)
        at = cum[keep]
        split = np.diff(np.r_[0, at]) > 0
        if len(split):
            split[0] |= self.pending_drop
            self.stats["episode_splits"] += int(split[1:].sum()) + int(split[0] and self.last_step_t is not None)
        self.pending_drop = bool((~keep[np.flatnonzero(keep)[-1] + 1:]).any()) if keep.any() else \
            self.pending_drop or bool((~keep).any())
        steps = {"t": times, "file": files, "lt": lts, "obs": obs, "aux": aux, "act": act, "act_ok": act_ok,
                 "hit": hit, "act_hit": damaged & ~act_ok}
        if not keep.all():
            steps = {k: v[keep] for k, v in steps.items()}
        steps["split"] = split
        self._segment(e, steps)

