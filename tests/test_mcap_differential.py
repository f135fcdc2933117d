"""Streaming MCAP assembly == the in-memory reference (tests/mcap_reference.py), on
generated multi-stream logs: different rates and jitter, time restarts per epoch, streams
that start late, skip epochs, restart before or after the clock, records out of time
order (within the reorder window), split files; for ``reorder_window`` in
{0.01, 0.2, 2, 30} s and flush cadences from every message to never.

CI runs ``N_LOGS`` generated logs in memory (messages fed to the assembler directly) and
a few through real MCAP files; ``pytest --hypothesis-profile nightly`` runs many more."""

from __future__ import annotations

import json
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap import ingest_mcap, parse_mcap_spec
from offline_adp.ingest.mcap.build import assemble
from offline_adp.ingest.mcap.records import Message
from tests import mcap_reference as ref

NIGHTLY = settings().max_examples >= 1000  # `--hypothesis-profile nightly` is loaded before collection
N_LOGS = 5000 if NIGHTLY else 500
N_FILES = 200 if NIGHTLY else 20
WINDOWS = (0.01, 0.2, 2.0, 30.0)
RESTART = 0.25  # s: more than the spread of the epochs' start times below
S = 1_000_000_000


def _times(rng, start, stop, hz, jitter):
    n = max(int((stop - start) * hz), 0)
    t = start + np.arange(n) / hz + rng.uniform(-jitter, jitter, n) / hz
    return np.unique(np.round(t * S).astype(np.int64))  # distinct times within a stream


@st.composite
def logs(draw):
    """(messages in file order, split points, spec dict, flush cadence)."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    window = draw(st.sampled_from(WINDOWS))
    n_epochs = draw(st.integers(1, 4))
    n_streams = draw(st.integers(1, 3))
    use_rate = draw(st.booleans()) and draw(st.booleans())  # a quarter: rate_hz ticks
    clock_hz = draw(st.sampled_from([5.0, 10.0, 25.0, 40.0]))
    delay = min(window, RESTART) / 3  # how late in the file a record may come (s)
    durations = rng.uniform(0.6, 1.6, n_epochs) + 0.5 * (rng.random(n_epochs) < 0.3)
    offsets = rng.uniform(0.0, 0.04, n_epochs)  # each epoch's time restarts near 1 s
    streams = []
    for i in range(n_streams):
        hz = float(rng.choice([10.0, 30.0, 60.0] if i == 0 and use_rate else [3.0, 10.0, 30.0, 60.0]))
        present = rng.random(n_epochs) < 0.8
        if draw(st.booleans()):
            present[: rng.integers(0, n_epochs)] = False  # starts late: absent for the first epochs
        streams.append({"topic": f"/s{i}", "hz": hz,
                        "jitter": float(rng.uniform(0, 0.4)), "present": present,
                        "lead": float(rng.uniform(-0.05, 0.05)),  # starts before (-) or after the clock
                        "align": str(rng.choice(["nearest", "previous", "linear"])),
                        "max_age": round(float(rng.choice([0.3, 0.6, 1.5, 5.0])) / hz, 4),
                        "missing": str(rng.choice(["fill", "fill", "drop_step", "drop_step", "error"],
                                                  p=[.3, .2, .2, .2, .1])),
                        "role": "obs" if i == 0 else str(rng.choice(["obs", "aux"]))})
    ahz = float(rng.choice([5.0, 10.0, 20.0]))
    action = {"topic": "/cmd", "hz": ahz, "jitter": float(rng.uniform(0, 0.3)),
              "present": rng.random(n_epochs) < 0.85, "lead": float(rng.uniform(-0.05, 0.05)),
              "align": str(rng.choice(["nearest", "previous"])),
              "max_age": round(float(rng.choice([0.6, 1.5, 5.0])) / ahz, 4),
              "missing": str(rng.choice(["drop_step", "fill", "error"], p=[.6, .3, .1]))}
    if draw(st.booleans()):
        action["present"][: rng.integers(0, n_epochs + 1)] = False
    # the clock pauses longer than gap: two episodes in one epoch
    pauses = (rng.random(n_epochs) < 0.3) & (durations > 1.4)
    no_clock = (rng.random(n_epochs) < 0.1) & (np.arange(n_epochs) > 0)  # a whole epoch without the clock
    msgs = []  # (write time, topic, t_ns, payload)
    g = 0.0  # write time of the previous epoch's last message
    g_clock = None  # ... and of its last clock message
    for e in range(n_epochs):
        t0, t1 = 1.0 + offsets[e], 1.0 + offsets[e] + durations[e]
        epoch = []
        for topic, hz, jit, lead in [("/clock", clock_hz, 0.1, 0.0)] + [
                (s["topic"], s["hz"], s["jitter"], s["lead"]) for s in [*streams, action] if s["present"][e]]:
            if topic == "/clock" and (use_rate or no_clock[e]):
                continue
            ts = _times(rng, t0 + lead, t1 + lead, hz, jit)
            if topic == "/clock" and pauses[e]:
                mid = (t0 + t1) / 2
                ts = ts[(ts < mid * S) | (ts > (mid + 0.5) * S)]
            epoch += [(t / S + rng.uniform(0, delay), topic, t, {"v": float(np.round(rng.normal(), 6)), "k": e})
                      for t in ts.tolist()]
        if not epoch:
            continue
        # the epoch's records follow the previous epoch's; the two overlap in the file by at
        # most `delay` (late records of the previous epoch stay within the reorder window)
        shift = g - min(w for w, *_ in epoch) + rng.uniform(-delay, 0.05)
        clock_topic = "/s0" if use_rate else "/clock"
        new_clock = [w for w, topic, *_ in epoch if topic == clock_topic]
        if new_clock and g_clock is not None:  # the clock's own records keep their order across its restart
            shift = max(shift, g_clock - min(new_clock) + 1e-6)
        msgs += [(w + shift, *rest) for w, *rest in epoch]
        g = max(w for w, *_ in msgs)
        g_clock = max((w for w, topic, *_ in msgs if topic == clock_topic), default=None)
    msgs.sort(key=lambda m: m[0])
    messages = [Message(topic, t, t, data) for _, topic, t, data in msgs]
    n_parts = draw(st.integers(1, 3))
    cuts = sorted(rng.integers(0, len(messages) + 1, n_parts - 1).tolist())
    spec = {
        "clock": {"rate_hz": clock_hz, "reorder_window": window} if use_rate else
                 {"topic": "/clock", "reorder_window": window},
        "episodes": {"restart": RESTART, "gap": 0.45},
        "streams": [{"topic": s["topic"], "fields": {f"x{i}": "v", f"k{i}": "k"}, "align": s["align"],
                     "max_age": s["max_age"],
                     "missing": s["missing"], "role": s["role"], **({"fill": -7.0} if s["missing"] == "fill" else {})}
                    for i, s in enumerate(streams)],
        "action": {"topic": "/cmd", "field": "v", "align": action["align"], "max_age": action["max_age"],
                   "missing": action["missing"], "type": "continuous", "n_bins": 3,
                   **({"fill": 0.5} if action["missing"] == "fill" else {})},
        "cost": {"terms": [{"field": "x0", "op": "square"}]},
    }
    if use_rate:  # ticks over the first stream: it must be an observation stream that is always there
        spec["streams"][0].update(missing="fill", fill=-7.0)
    flush_every = draw(st.sampled_from([1, 2, 7, 50, 400, 10**9]))
    clock_topic = "/s0" if use_rate else "/clock"
    # with the clock in every epoch, the epoch rules place every message right (ground truth);
    # an epoch without the clock cannot be told apart from a stream running ahead in the file
    # and every stream sends enough in each epoch it is in for its restarts to show
    from collections import Counter

    counts = Counter((m.topic, m.data["k"]) for m in messages)
    truth = ({m.data["k"] for m in messages if m.topic == clock_topic} == set(range(n_epochs))
             and min(counts.values(), default=0) >= 4)
    return messages, cuts, spec, flush_every, truth


def _split(messages, cuts):
    bounds = [0, *cuts, len(messages)]
    return [messages[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def _restarts_jump_clear(messages, spec) -> bool:
    """Whether every topic's time, at each restart (episode k to k + 1 in the generator's
    truth), jumps back by more than ``restart`` plus the topic's largest step between two
    messages: then no restart can be read as a stale stamp (rule 5's guarantee in
    docs/ingestion-spec.md: coming back in step takes at most ``restart`` of the new
    timeline plus one step)."""
    seqs: dict[str, list[tuple[int, int]]] = {}
    for m in messages:
        seqs.setdefault(m.topic, []).append((m.data["k"], m.log_time))
    for seq in seqs.values():
        step = max((b[1] - a[1] for a, b in pairwise(seq) if a[0] == b[0] and b[1] > a[1]), default=0)
        tops: dict[int, int] = {}
        lows: dict[int, int] = {}
        for k, t in seq:
            tops[k], lows[k] = max(tops.get(k, t), t), min(lows.get(k, t), t)
        ks = sorted(tops)
        if any(tops[a] - lows[b] <= spec.restart * 1e9 + step for a, b in pairwise(ks)):
            return False
    return True


def _compare(got_eps, want_eps):
    assert [e.ep for e in got_eps] == [e.ep for e in want_eps]
    for g, w in zip(got_eps, want_eps, strict=True):
        np.testing.assert_array_equal(g.t, w.t, err_msg=g.ep)
        for f in ("obs", "next", "aux", "aux_next", "act"):
            np.testing.assert_array_equal(getattr(g, f), getattr(w, f), err_msg=f"{g.ep}: {f}")


@settings(max_examples=N_LOGS)
@given(logs())
def test_streaming_equals_the_reference(case):
    messages, cuts, d, flush_every, truth = case
    spec = parse_mcap_spec(d)
    try:
        want = ref.assemble(messages, spec, name="memory")
    except IngestError:
        with pytest.raises(IngestError):
            assemble(_split(messages, cuts), spec, flush_every=flush_every)
        return
    got = assemble(_split(messages, cuts), spec, flush_every=flush_every)
    _compare(got.episodes, want.episodes)
    assert got.stats["dropped_steps"] == want.dropped_steps
    assert got.stats["restarts"] == want.restarts
    assert got.stats["orphan_messages"] == want.orphans
    assert sum(got.late.values()) == want.late
    # per topic, what became of each message: used, orphaned or dropped late, as the reference says
    assert {t: n for t, n in got.used.items() if n} == want.used_by_topic
    assert got.orphaned == want.orphans_by_topic
    assert got.dropped_late == want.late_by_topic
    assert got.stale == want.stale_by_topic
    if _restarts_jump_clear(messages, spec):  # ground truth, not the reference's word: every stamp is genuine
        assert not got.stale


@settings(max_examples=N_LOGS // 5)
@given(logs(), st.sampled_from([1, 13, 10**9]))
def test_the_result_does_not_depend_on_flush_points_or_the_window(case, other_flush):
    """The same log with another flush cadence and the widest window: the same episodes
    (every record here is well inside the narrowest window it was generated for)."""
    messages, cuts, d, flush_every, truth = case
    if not truth:  # a skipped clock epoch: what counts as "ahead" depends on the window (documented)
        return
    spec = parse_mcap_spec(d)
    wide = parse_mcap_spec({**d, "clock": {**d["clock"], "reorder_window": 30.0}})
    try:
        a = assemble(_split(messages, cuts), spec, flush_every=flush_every)
    except IngestError:
        return
    b = assemble(_split(messages, cuts), wide, flush_every=other_flush)
    _compare(a.episodes, b.episodes)


@pytest.mark.xfail(strict=False, reason="open (issue 13 note): on some generated logs a sparse stream's restart is "
                                        "not visible and a value of a neighbouring epoch is paired; the streaming "
                                        "ingester and the reference agree (same rules)")
@settings(max_examples=N_LOGS // 5)
@given(logs())
def test_every_value_of_a_row_comes_from_one_epoch(case):
    """Ground truth, where the log allows it (the clock in every epoch, every stream with
    a few messages in each epoch it is in)."""
    messages, cuts, d, flush_every, truth = case
    spec = parse_mcap_spec(d)
    try:
        got = assemble(_split(messages, cuts), spec, flush_every=flush_every)
    except IngestError:
        return
    for e in got.episodes if truth else ():  # ground truth: every value of a row comes from one epoch of the log
        k = np.concatenate([e.obs, e.aux], axis=1)[:, [i for i, n in enumerate(spec.obs_names + spec.aux_names)
                                                       if n.startswith("k")]]
        seen = k != -7.0  # the fill value: no message
        hi = np.where(seen, k, -np.inf).max(axis=1)
        lo = np.where(seen, k, np.inf).min(axis=1)
        assert np.all((hi == lo) | ~seen.any(axis=1)), e.ep


def _write(path, messages):
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f, chunk_size=2048)
        w.start()
        sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        chans: dict[str, int] = {}
        for m in messages:
            if m.topic not in chans:
                chans[m.topic] = w.register_channel(topic=m.topic, message_encoding="json", schema_id=sid)
            w.add_message(chans[m.topic], log_time=m.log_time, publish_time=m.publish_time,
                          data=json.dumps(m.data).encode())
        w.finish()


@settings(max_examples=N_FILES)
@given(logs())
def test_through_mcap_files_split_recordings_included(tmp_path_factory, case):
    messages, cuts, d, _, _ = case
    spec = parse_mcap_spec(d)
    parts = _split(messages, cuts)
    d_ = tmp_path_factory.mktemp("logs")
    files = [d_ / "rec.mcap"] if len(parts) == 1 else [d_ / f"rec_{i}.mcap" for i in range(len(parts))]
    for f, p in zip(files, parts, strict=True):
        _write(f, p)
    try:
        want = ref.assemble(messages, spec, name="rec")
    except IngestError:
        with pytest.raises(IngestError):
            ingest_mcap(files, spec)
        return
    if not want.episodes:
        with pytest.raises(IngestError):
            ingest_mcap(files, spec)
        return
    ds, s = ingest_mcap(files, spec)
    a = ds.arrays()
    assert list(ds.episode_ids) == [e.ep for e in want.episodes]
    np.testing.assert_array_equal(a.obs, np.concatenate([e.obs for e in want.episodes]))
    np.testing.assert_array_equal(a.next_obs, np.concatenate([e.next for e in want.episodes]))
    np.testing.assert_array_equal(ds.table.column("t_ns").to_numpy(), np.concatenate([e.t for e in want.episodes]))
    assert s["dropped_steps"] == want.dropped_steps
