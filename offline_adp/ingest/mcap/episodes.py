"""Episode segmentation of assembled steps: events, gaps, conditions."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap.records import EpisodeRows
from offline_adp.ingest.mcap.spec import McapSpec


def read_event(dec: Any, fields: dict[str, str], topic: str, log_time: int) -> list[Any]:
    """The episode fields of one event message, in ``fields``' order, read as the segmenter
    uses them: the kind; on a start event the id and source (an end event's are not read:
    None); on an ``end`` event ``terminated`` (a start event need not have it: None), a
    boolean or a number 0 or 1. A field the message lacks, a null, or a flag of another type
    (the string ``"false"`` would read as true) is an error naming the topic, the message's
    log_time and the field."""
    where = f"topic {topic!r}, message at log_time {int(log_time)}"
    kind = str(_field(dec, fields["event_field"], "event_field", where)) if "event_field" in fields else "start"
    out: list[Any] = []
    for key, path in fields.items():
        if key == "event_field" or (key == "terminated_field") != (kind == "end") or kind not in ("start", "end"):
            out.append(kind if key == "event_field" else None)  # start: id, source; end: the flag; other: nothing
            continue
        v = _field(dec, path, key, where)
        if v is None:
            raise IngestError(f"{where}: the episode event's field {path!r} ([episodes] {key}) is null")
        if key == "terminated_field":
            flag = v.item() if isinstance(v, np.generic) else v
            if isinstance(flag, bool) or (isinstance(flag, int | float) and flag in (0, 1)):
                v = bool(flag)
            else:
                raise IngestError(f"{where}: the episode event's field {path!r} ([episodes] terminated_field) is "
                                  f"{v!r}, not a flag (true/false, 0/1)")
        out.append(v)
    return out


def _field(dec: Any, path: str, key: str, where: str) -> Any:
    from offline_adp.ingest.mcap.decode import get_path

    try:
        return get_path(dec, path)
    except (KeyError, AttributeError, IndexError, TypeError, ValueError) as exc:
        raise IngestError(f"{where}: the episode event has no field {path!r} ([episodes] {key}; "
                          f"{type(exc).__name__}: {exc}); run `offline-adp mcap-info` to list the fields") from None


@dataclass
class _Episode:
    """The episode being assembled: its steps so far (arrays appended per flush)."""

    key: Any
    ep_id: str
    source: str
    parts: list[dict[str, np.ndarray]] = field(default_factory=list)
    epoch: int = 0

    def add(self, steps: dict[str, np.ndarray], sl: slice) -> None:
        if sl.stop > sl.start:
            self.parts.append({k: v[sl] for k, v in steps.items()})


class EpisodeSegmenter:
    """Cuts assembled steps into episodes (a mixin of the assembler, which owns the state:
    ``spec``, ``stats``, ``cur``, ``out``, the event buffers and column map)."""

    spec: McapSpec

    def _segment(self, e: int, st: dict[str, np.ndarray]) -> None:
        """Cut the steps into episodes: events (or gaps), episode fields, end/terminal conditions."""
        spec = self.spec
        t = st["t"]
        n = len(t)
        if not n:
            return
        if spec.episode_topic:
            key = self._event_membership(e, t)
        else:
            prev = np.r_[self.last_step_t if self.last_step_t is not None else t[0], t[:-1]]
            gap = (t - prev) > spec.gap * 1e9
            if gap.any():  # a pause in the log starts an episode: counted, the longest said (ingest summary)
                self.stats["gap_splits"] = self.stats.get("gap_splits", 0) + int(gap.sum())
                self.stats["longest_gap_s"] = max(self.stats.get("longest_gap_s", 0.0),
                                                  float((t - prev)[gap].max()) / 1e9)
            if self.last_step_t is None:
                gap[0] = True
            key = (self.seg + np.cumsum(gap)).astype(object)  # a new key at every gap
            self.seg = int(key[-1])
        brk = st["split"].copy() if "split" in st else np.zeros(n, bool)
        if self.episode_fields:
            vals = np.column_stack([st["aux"][:, self.col[f][1]] for f in self.episode_fields])
            prev_v = np.vstack([vals[:1] if self.last_episode_value is None else self.last_episode_value, vals[:-1]])
            brk |= (vals != prev_v).any(axis=1)
            self.last_episode_value = vals[-1:]
        term = np.zeros(n, bool)
        for c in spec.terminal_when:
            term |= c.holds(self._field(st, c.field))
        end = term.copy()
        for c in spec.end_when:
            end |= c.holds(self._field(st, c.field))
        self.last_step_t = int(t[-1])
        # walk the change points only (not every step): key changes, breaks, condition steps and the step after one
        pts = np.flatnonzero(brk | end | np.r_[True, key[1:] != key[:-1]] | np.r_[False, end[:-1]])
        for i, j in zip(pts.tolist(), [*pts[1:].tolist(), n], strict=True):
            self._run(st, key[i], bool(brk[i]), bool(end[i]), bool(term[i]), i, j)

    def _run(self, st: dict[str, np.ndarray], k: Any, brk: bool, end: bool, term: bool, i: int, j: int) -> None:
        """Steps i..j-1: one key, no break inside; an ``end`` run is a single step."""
        if k is None:
            self._close(None)
            self.waiting = None
            self.stats["outside_episode_steps"] += j - i
            return
        if self.cur is not None and (self.cur.key != k or brk):
            self._close(None)
        if self.waiting is not None and self.waiting != k:
            self.waiting = None
        if self.waiting is not None:
            if end:  # the condition still holds: this step belongs to no episode
                self.stats["condition_steps"] += j - i
                return
            self.waiting = None
        if self.cur is None:
            self._open(k, st, i)
        self.cur.add(st, slice(i, j))  # type: ignore[union-attr]
        if end:  # an end or terminal condition: the episode ends at this step
            self._close(term)
            self.waiting = k

    def _open(self, k: Any, st: dict[str, np.ndarray], i: int) -> None:
        if self.spec.episode_topic:
            ep_id, source, _ = self.event_info[k]
            n_before = self.splits.get(k, 0)
            self.splits[k] = n_before + 1
            if n_before:
                ep_id = f"{ep_id}/{n_before}"
        else:
            ep_id, source = f"{self.name}-{self.counter:05d}", None
            self.counter += 1
        if source is None:
            source = self._source_of(self.files[int(st["file"][i]) - self.file0])
        self.cur = _Episode(k, ep_id, source, epoch=self.active)

    def _source_of(self, path: Path) -> str:
        import fnmatch

        for pat, label in self.spec.source_by_file.items():
            if fnmatch.fnmatch(path.name, pat) or fnmatch.fnmatch(str(path), pat):
                return str(label)
        return self.spec.source_value

    def _field(self, st: dict[str, np.ndarray], name: str) -> np.ndarray:
        where, j = self.col[name]
        return st[where][:, j]

    def _event_membership(self, e: int, t: np.ndarray) -> np.ndarray:
        """Per step, the key of the event-delimited episode it belongs to (None: outside)."""
        b = self.bufs.get(("events", e))
        out = np.full(len(t), None, dtype=object)
        if b is None:
            return out
        a = b.arrays()
        names = list(self.spec.episode_fields)
        kind = np.asarray([str(x) for x in a["event_field"]]) if "event_field" in a else np.full(len(a["t"]), "start")
        et = a["t"]
        is_start = kind == "start"
        idx = np.searchsorted(et, t, side="right") - 1  # the last event at or before each step
        for j in np.unique(idx[idx >= 0]):
            steps = idx == j
            if is_start[j]:
                s = j
                end_t = end_i = None
                after = np.arange(len(kind)) > j
                later_end = np.flatnonzero(after & (kind == "end"))
                later_start = np.flatnonzero(after & is_start)
                if len(later_end) and (not len(later_start) or later_end[0] < later_start[0]):
                    end_i = int(later_end[0])
                    end_t = et[end_i]
            elif kind[j] == "end":
                steps &= t == et[j]  # a step exactly at the end event still belongs to the episode
                starts = np.flatnonzero(is_start[:j])
                if not len(starts):
                    continue
                s, end_t, end_i = starts[-1], et[j], j
            else:
                continue
            k = f"{e}:{int(et[s])}"  # a scalar key (numpy would unpack a tuple)
            if k not in self.event_info:
                ep_id = str(a["id_field"][s]) if "id_field" in names else f"{self.name}-{e}-{int(et[s])}"
                src = str(a["source_field"][s]) if "source_field" in names else None
                self.event_info[k] = (ep_id, src, None)
            if end_t is not None:
                terminated = bool(a["terminated_field"][end_i]) if "terminated_field" in names else False
                self.event_info[k] = (*self.event_info[k][:2], terminated)
            out[steps] = [k] * int(steps.sum())
        return out

    def _close(self, terminated: bool | None, cut: bool = False) -> None:
        """Close the episode being assembled. ``cut``: the recording ends inside it.

        Rejected episodes keep their rows with a ``reason`` (they go to ``quarantine/``):
        cut, no end event, a step without a command (under ``on_error = "fail"`` the last
        is an error)."""
        ep, self.cur = self.cur, None
        if ep is None or not ep.parts:
            return
        st = {k: np.concatenate([p[k] for p in ep.parts]) for k in ep.parts[0]}
        reason = ""
        if cut:
            reason = "cut: the recording ends inside this episode"
            self.stats["cut_episodes"] += 1
        if self.spec.episode_topic:
            info = self.event_info.get(ep.key)
            ended = info is not None and info[2] is not None
            if not ended and terminated is None:  # the log stops inside this episode (cut or crashed recording)
                if not reason:
                    reason = "incomplete: the log ends before this episode's end event"
                    self.stats["incomplete_episodes"] += 1
                terminated = False
            if terminated is None:
                terminated = bool(info[2])  # type: ignore[index]
        n = len(st["t"]) - 1
        hit = st["hit"] | np.r_[st["act_hit"][:n], False]  # the last step needs no command
        if hit.any() and not reason:
            k = int(np.flatnonzero(hit)[0])
            reason = (f"damage: step {k} (log_time {int(st['lt'][k])}) lacks messages lost to damage in "
                      f"{self.files[int(st['file'][k]) - self.file0]}")
            self.stats["episodes_lost_to_damage"] += 1
        n = len(st["t"]) - 1
        if n < 1:
            self.stats["short_episodes"] += 1
            return
        if not st["act_ok"][:n].all() and not reason:
            k = int(np.flatnonzero(~st["act_ok"][:n])[0])
            msg = (f"{self.files[int(st['file'][k]) - self.file0]}: episode {ep.ep_id}, step {k} (log_time "
                   f"{int(st['lt'][k])}): no {self.spec.action_stream.topic} command within max_age = "
                   f"{self.spec.action_stream.max_age} s")
            topic = self.spec.action_stream.topic
            if self.decoded.get(topic, 0) == 0:  # nothing on it: is it in the file at all? (names the topics there)
                self._check_topic_present(topic, msg)
            if self.on_error == "fail":
                raise IngestError(msg)
            reason = "no command: " + msg
            self.stats["episodes_without_command"] += 1
        self.out.append(EpisodeRows(
            ep=ep.ep_id, src=ep.source, t=st["t"][:n], file=st["file"][:n], obs=st["obs"][:-1], next=st["obs"][1:],
            aux=st["aux"][:-1], aux_next=st["aux"][1:], act=st["act"][:n], terminated=bool(terminated),
            t_end=int(st["t"][-1]), epoch=ep.epoch, log_time=st["lt"][:n], reason=reason))
