"""A deliberately simple in-memory REFERENCE of MCAP assembly (a test oracle, never used
by the package).

It implements the semantics of docs/ingestion-spec.md ("Epochs", "Alignment",
"Episodes") the obvious way: one pass over the messages in file order gives each message
its epoch; then, per epoch, every stream is sorted by time and aligned to the steps with
``pandas.merge_asof``; steps are cut into episodes at gaps. Nothing is streamed, nothing
is flushed or pruned: the streaming assembler must give exactly the same episodes, for any
``reorder_window`` and flush cadence, on every log whose messages are no later in the
file than the reorder window.

Covered: a clock topic or ``rate_hz`` ticks, ``restart`` epochs, streams and the action
with ``nearest`` / ``previous`` / ``linear`` alignment and ``missing`` =
``fill`` / ``drop_step`` / ``error``, gap episodes. Not covered (tested elsewhere by
construction): episode events, end/terminal conditions, damage.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap.decode import get_path, to_ns
from offline_adp.ingest.mcap.records import Message
from offline_adp.ingest.mcap.spec import McapSpec, StreamSpec


@dataclass
class RefEpisode:
    ep: str
    t: np.ndarray
    obs: np.ndarray
    next: np.ndarray
    aux: np.ndarray
    aux_next: np.ndarray
    act: np.ndarray
    terminated: bool = False


@dataclass
class RefResult:
    episodes: list[RefEpisode]
    dropped_steps: int = 0
    restarts: int = 0
    late: int = 0  # messages dropped late (their epoch was over)
    orphans: int = 0  # messages held for an epoch the clock never reached
    late_by_topic: dict[str, int] = field(default_factory=dict)
    orphans_by_topic: dict[str, int] = field(default_factory=dict)
    stale_by_topic: dict[str, int] = field(default_factory=dict)  # stamped more than `restart` behind, no restart
    used_by_topic: dict[str, int] = field(default_factory=dict)  # every other message of a spec topic
    stats: dict[str, Any] = field(default_factory=dict)


def _time(which: str, m: Message) -> int:
    if which == "log_time":
        return int(m.log_time)
    if which == "publish_time":
        return int(m.publish_time)
    return to_ns(get_path(m.data, which))


def assign_epochs(messages: list[Message], spec: McapSpec) -> tuple[list[tuple[Any, int, int, list[float]]], RefResult]:
    """(key, epoch, time, values) per key of every message, by the epoch rules of the spec."""
    r = int(spec.restart * 1e9)
    reorder = int(spec.reorder_window * 1e9)
    keys: dict[Any, StreamSpec] = {("s", i): s for i, s in enumerate(spec.streams)}
    keys["action"] = spec.action_stream
    clock = "clock" if spec.clock_topic else ("s", next(i for i, s in enumerate(spec.streams) if s.role == "obs"))
    epoch: dict[Any, int] = {}
    maxt: dict[Any, int] = {}
    clock_first: dict[int, int] = {}
    # gone ahead: (its epoch, its time before, its first time after, the clock's then, times held in step since)
    jumped: dict[Any, tuple[int, int, int, int, list[int]]] = {}
    suspect: dict[Any, int] = {}  # back in step: the epoch it held messages for (stale stamps among them?)
    seen: dict[Any, int | None] = {}  # the clock's latest time when each stream's latest time was read
    out: dict[Any, list[tuple[Any, int, int, list[float]]]] = {}  # per (key, epoch)
    ids: dict[Any, list[int]] = {}  # per (key, epoch): the index of each message of ``out``
    aside: dict[int, dict[Any, str]] = {}  # per message: the keys that did not use it, and why
    res = RefResult([])
    topics: dict[int, tuple[str, int]] = {}  # per message of a spec topic: its topic and number of keys

    def set_aside(key: Any, idx: list[int], why: str) -> None:
        for i in idx:
            aside.setdefault(i, {})[key] = why

    for i_m, m in enumerate(messages):
        todo = []
        if spec.clock_topic and m.topic == spec.clock_topic:
            todo.append(("clock", _time(spec.clock_time, m), []))
        for k, s in keys.items():
            if s.topic == m.topic:
                todo.append((k, _time(s.time, m), [float(get_path(m.data, p)) for p in s.fields.values()]))
        todo.sort(key=lambda x: x[0] != clock)  # the clock first: the others are placed against it
        if todo:
            topics[i_m] = (m.topic, len(todo))
        for k, t, vals in todo:
            ce, cm = epoch.get(clock, 0), maxt.get(clock)
            ek, mk = epoch.get(k, ce), maxt.get(k)
            own = mk is not None and r > 0 and t < mk - r
            if k != clock and mk is not None and ek == ce and cm is not None and seen.get(k) is not None and r > 0:
                own = t < mk + max(cm - seen[k], 0) - r  # behind its own pace with the clock
            late = False
            j = jumped.get(k)
            if j is not None and (j[0] != ek or ek != ce + 1 or mk is None or mk - j[2] >= r or own):
                del jumped[k]  # the clock followed, or the stream's time ran on there: a restart
            if k == clock:
                e = ek + own
                res.restarts += own
                if e not in clock_first:  # a stream ahead by more than the window held an epoch the clock skipped
                    for k2 in list(epoch):
                        if k2 != clock and epoch[k2] == e and maxt.get(k2) is not None and maxt[k2] > t + reorder + r:
                            out.pop((k2, e), None)
                            set_aside(k2, ids.pop((k2, e), []), "orphan")
                            del maxt[k2]
                    for k2 in epoch:  # streams there before the clock: their pace with it counts from here
                        if k2 != clock and epoch[k2] == e and maxt.get(k2) is not None and seen.get(k2) is None:
                            seen[k2] = t
                    for k2 in [k2 for k2, j2 in jumped.items() if j2[0] == e]:  # the clock followed: a restart
                        times = jumped.pop(k2)[4]
                        held = list(zip(out.get((k2, e), []), ids.get((k2, e), []), strict=True))
                        set_aside(k2, [i for x, i in held if x[2] in times], "late")  # late records of the one before
                        if (k2, e) in out:
                            out[(k2, e)] = [x for x, _ in held if x[2] not in times]
                            ids[(k2, e)] = [i for x, i in held if x[2] not in times]
                    for k2 in [k2 for k2, e2 in suspect.items() if e2 == e]:  # stale stamps: after t + window + r
                        del suspect[k2]
                        held = list(zip(out.get((k2, e), []), ids.get((k2, e), []), strict=True))
                        keep = [(x, i) for x, i in held if x[2] <= t + reorder + r]
                        set_aside(k2, [i for x, i in held if x[2] > t + reorder + r], "stale")
                        if (k2, e) in out:
                            out[(k2, e)], ids[(k2, e)] = [x for x, _ in keep], [i for _, i in keep]
                        if epoch.get(k2) == e:
                            if keep:
                                maxt[k2] = max(x[2] for x, _ in keep)
                            else:
                                maxt.pop(k2, None)
                    clock_first[e] = t
            elif ((j := jumped.get(k)) is not None and cm is not None and t >= max(cm - r, j[1])
                  and t <= max(cm, j[1]) + r and cm == j[3]):
                j[4].append(t)  # in step, but the clock has not moved since the jump: held (its state unchanged)
                out.setdefault((k, ek), []).append((k, ek, t, vals))
                ids.setdefault((k, ek), []).append(i_m)
                continue
            elif ((j := jumped.get(k)) is not None and cm is not None and t >= max(cm - r, j[1])
                  and t <= max(cm, j[1]) + r):
                # back in step with the clock before its time ran on for `restart`: what it held may be stale,
                # what it held in step meanwhile is this epoch's
                del jumped[k]
                held = list(zip(out.get((k, ek), []), ids.get((k, ek), []), strict=True))
                for x, i in held:
                    if x[2] in j[4]:
                        out.setdefault((k, ce), []).append((k, ce, x[2], x[3]))
                        ids.setdefault((k, ce), []).append(i)
                out[(k, ek)] = [x for x, _ in held if x[2] not in j[4]]
                ids[(k, ek)] = [i for x, i in held if x[2] not in j[4]]
                suspect[k], e = ek, ce
            elif mk is not None and (ek == ce + 1 or cm is None):
                e = ek
                if own:
                    out.pop((k, ek), None)
                    set_aside(k, ids.pop((k, ek), []), "orphan")
            elif mk is not None and ek == ce and not own:
                e = ce
            elif mk is not None and ek == ce - 1 and not own and cm is not None and r > 0 and t > cm + r:
                e = ek
                late = cm - clock_first.get(ce, cm) >= reorder
            else:
                e = ce + (cm is not None and r > 0 and clock_first.get(ce, cm) - r <= t < cm - r)
                if e == ce + 1 and ek == ce and mk is not None:  # went ahead of the clock from its epoch
                    jumped[k] = (e, mk, t, cm, [])
            if late:  # the epoch is over: the message is counted, not used
                set_aside(k, [i_m], "late")
                continue
            if e != ek or own or mk is None or t > mk:
                maxt[k] = t
                if k != clock:
                    seen[k] = maxt.get(clock) if e == epoch.get(clock, 0) else None
            epoch[k] = e
            out.setdefault((k, e), []).append((k, e, t, vals))
            ids.setdefault((k, e), []).append(i_m)
    # messages held for an epoch the clock never reached (a stream's time fell back more than `restart` once
    # while the clock's did not): never used, counted as orphans (stale where the stream came back in step and
    # stayed)
    for k, e in [ke for ke in out if ke[0] != clock and ke[1] not in clock_first]:
        out.pop((k, e))
        set_aside(k, ids.pop((k, e)), "stale" if suspect.get(k) == e and epoch.get(k, 0) < e else "orphan")
    # per message: used if any of its keys used it; else orphaned if any of them orphaned it, else stale if any
    # found it stale, else late
    for i_m, (topic, n_keys) in topics.items():
        why = aside.get(i_m, {})
        if len(why) < n_keys:
            res.used_by_topic[topic] = res.used_by_topic.get(topic, 0) + 1
        elif "orphan" in why.values():
            res.orphans += 1
            res.orphans_by_topic[topic] = res.orphans_by_topic.get(topic, 0) + 1
        elif "stale" in why.values():
            res.stale_by_topic[topic] = res.stale_by_topic.get(topic, 0) + 1
        else:
            res.late += 1
            res.late_by_topic[topic] = res.late_by_topic.get(topic, 0) + 1
    return [x for v in out.values() for x in v], res


def _align(ts: np.ndarray, vals: np.ndarray, at: np.ndarray, s: StreamSpec) -> tuple[np.ndarray, np.ndarray]:
    """merge_asof-style alignment (ties at equal distance go to the earlier message)."""
    max_age = int(s.max_age * 1e9)
    steps = pd.DataFrame({"at": at.astype(np.int64), "i": np.arange(len(at))})
    if len(ts) == 0:
        return np.full(len(at), np.nan), np.zeros(len(at), bool)
    right = pd.DataFrame({"ts": ts.astype(np.int64), "v": vals, "j": np.arange(len(ts))})
    back = pd.merge_asof(steps, right, left_on="at", right_on="ts", direction="backward")
    fwd = pd.merge_asof(steps, right, left_on="at", right_on="ts", direction="forward", allow_exact_matches=False)
    has_p, has_n = back["j"].notna().to_numpy(), fwd["j"].notna().to_numpy()
    tp = back["ts"].fillna(0).to_numpy(np.int64)
    tn = fwd["ts"].fillna(0).to_numpy(np.int64)
    vp, vn = back["v"].to_numpy(), fwd["v"].to_numpy()
    if s.align == "previous":
        return np.where(has_p, vp, vals[0]), has_p & (at - tp <= max_age)
    if s.align == "nearest":
        use_n = has_n & (~has_p | (np.abs(tn - at) < np.abs(at - tp)))
        v = np.where(use_n, vn, vp)
        d = np.where(use_n, np.abs(tn - at), np.abs(at - tp))
        return v, (has_p | has_n) & (d <= max_age)
    out = np.empty(len(at))
    ok = np.zeros(len(at), bool)
    for i in range(len(at)):  # a plain loop: this is the reference
        if not has_p[i]:
            out[i] = vn[i]
            continue
        if not has_n[i]:
            out[i] = vp[i] + 0.0 * (vp[i] - vp[i])
            ok[i] = tp[i] == at[i]
            continue
        span = float(tn[i] - tp[i])
        w = (at[i] - tp[i]) / span
        out[i] = vp[i] + min(max(w, 0.0), 1.0) * (vn[i] - vp[i])
        ok[i] = (at[i] - tp[i] <= max_age and tn[i] - at[i] <= max_age) or tp[i] == at[i]
    return out, ok


def assemble(messages: list[Message], spec: McapSpec, name: str = "mem") -> RefResult:
    """The episodes the spec makes of ``messages`` (one recording)."""
    placed, res = assign_epochs(messages, spec)
    keys: dict[Any, StreamSpec] = {("s", i): s for i, s in enumerate(spec.streams)}
    keys["action"] = spec.action_stream
    clock = "clock" if spec.clock_topic else ("s", next(i for i, s in enumerate(spec.streams) if s.role == "obs"))
    obs_names, aux_names = spec.obs_names, spec.aux_names
    counter = 0
    for e in sorted({x[1] for x in placed}):
        def stream(k: Any) -> tuple[np.ndarray, np.ndarray]:
            rows = [(t, v) for kk, ee, t, v in placed if kk == k and ee == e]  # noqa: B023
            order = sorted(range(len(rows)), key=lambda i: rows[i][0])  # stable: file order among equal times
            ts = np.array([rows[i][0] for i in order], dtype=np.int64)
            vals = np.array([rows[i][1] for i in order],
                            dtype=float).reshape(len(rows), len(keys[k].fields) if k in keys else 0)
            return ts, vals

        ct, _ = stream(clock)
        if spec.rate_hz is not None:
            period, gap = int(round(1e9 / spec.rate_hz)), int(spec.gap * 1e9)
            ticks: list[int] = []
            nxt = prev = None
            for ti in ct.tolist():
                if nxt is None or prev is None or ti - prev > gap:
                    nxt = ti
                while nxt <= ti:
                    ticks.append(nxt)
                    nxt += period
                prev = ti
            ct = np.array(ticks, dtype=np.int64)
        n = len(ct)
        if not n:
            continue
        obs, aux = np.empty((n, len(obs_names))), np.empty((n, len(aux_names)))
        keep = np.ones(n, bool)
        act, act_ok = np.zeros(n), np.ones(n, bool)
        for k, s in keys.items():
            ts, vals = stream(k)
            for j, nm in enumerate(s.fields):
                v, ok = _align(ts, vals[:, j] if len(ts) else np.zeros(0), ct, s)
                if s.missing == "fill":
                    v, ok = np.where(ok, v, s.fill), np.ones(n, bool)
                elif s.missing == "drop_step":
                    keep &= ok
                elif k != "action" and not ok.all():
                    raise IngestError(f"reference: step without {s.topic} ({nm})")
                if k == "action":
                    act, act_ok = v, ok
                elif nm in obs_names:
                    obs[:, obs_names.index(nm)] = v
                else:
                    aux[:, aux_names.index(nm)] = v
        res.dropped_steps += int((~keep).sum())
        idx = np.flatnonzero(keep)  # a dropped step between two kept ones splits the episode there
        t, obs, aux, act, act_ok = ct[keep], obs[keep], aux[keep], act[keep], act_ok[keep]
        if not len(t):
            continue
        starts = [0] + [i for i in range(1, len(t)) if t[i] - t[i - 1] > spec.gap * 1e9 or idx[i] - idx[i - 1] > 1]
        for a, b in zip(starts, [*starts[1:], len(t)], strict=True):
            ep_id = f"{name}-{counter:05d}"
            counter += 1
            m = b - a - 1
            if m < 1:
                continue
            if not act_ok[a:a + m].all():
                raise IngestError(f"reference: episode {ep_id} has a step without a command")
            res.episodes.append(RefEpisode(ep_id, t[a:a + m], obs[a:b - 1], obs[a + 1:b], aux[a:b - 1], aux[a + 1:b],
                                           act[a:a + m]))
    return res
