"""The per-topic message counts of an MCAP ingest partition the messages of the file:

    messages_read = messages_used + messages_skipped + messages_unselected + messages_orphaned
                    + messages_stale + messages_dropped_late + messages_undecodable

per topic, per file and in total. ``messages_used`` once counted every decoded message,
also those held for an epoch the clock never reached (orphans) and those dropped as late:
on a log with 500 orphaned /tf messages it said all 800 were used. Ground truth: the logs
are built here (a stale stamp at a known place; random logs counted topic by topic)."""

from __future__ import annotations

import json
import tempfile
import warnings
from collections import Counter
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap import ingest_mcap, parse_mcap_spec
from offline_adp.ingest.mcap.build import assemble
from tests import mcap_reference as ref
from tests.test_ingest_mcap_streaming import write_log
from tests.test_mcap_differential import _split, logs
from tests.test_mcap_stale_stream import _log, _spec

PARTS = ("messages_used", "messages_skipped", "messages_unselected", "messages_orphaned", "messages_stale",
         "messages_dropped_late", "messages_undecodable")


def _partition_holds(counts: dict, in_file: Counter) -> None:
    """Per topic: the parts add up to the messages in the file, and so does messages_read."""
    for topic, n in in_file.items():
        got = {p: counts.get(p, {}).get(topic, 0) for p in PARTS}
        assert sum(got.values()) == n, (topic, n, got)
        assert counts["messages_read"].get(topic, 0) == n, (topic, n, counts["messages_read"])
    assert set(counts["messages_read"]) <= set(in_file)


def test_orphaned_messages_are_not_counted_as_used(tmp_path):
    """/tf's messages from 300 on are stamped 1.5 s early (more than restart = 1 s): /tf's
    messages 300..799 are held for an epoch the clock never reaches, 500 orphans. Used: 300."""
    msgs = _log(behind=True) + [("/other", 5_000_000_000 + k, {"a": k}) for k in range(7)]
    f = write_log(tmp_path / "tf.mcap", msgs)
    with pytest.warns(UserWarning, match="set aside, unused"):
        ds, s = ingest_mcap([f], _spec("fill"), tmp_path / "ds")
    assert s["orphan_messages"] == 500
    assert s["messages_used"] == {"/state": 800, "/tf": 300}
    assert s["messages_orphaned"] == {"/tf": 500}
    assert s["messages_skipped"] == {"/other": 7}
    in_file = Counter(t for t, _, _ in msgs)
    _partition_holds(s, in_file)
    _partition_holds(s["files"][0], in_file)
    # what the dataset keeps says the same
    info = json.loads((tmp_path / "ds" / "meta" / "info.json").read_text())
    assert info["ingest"]["messages_used"] == {"/state": 800, "/tf": 300}
    assert info["ingest"]["messages_orphaned"] == {"/tf": 500}
    for entry in (info["ingest"]["files"][0], info["provenance"]["inputs"][0]):
        assert entry["messages_used"] == {"/state": 800, "/tf": 300}
        assert entry["messages_orphaned"] == {"/tf": 500}


def test_the_cli_prints_the_corrected_counts(tmp_path, capsys):
    from offline_adp.cli import main

    msgs = _log(behind=True)
    f = write_log(tmp_path / "tf.mcap", msgs)
    spec = tmp_path / "tf.spec.toml"  # _spec("fill") as a user writes it
    spec.write_text('[clock]\ntopic = "/state"\n[episodes]\nrestart = 1.0\ngap = 1.0\n'
                    '[[streams]]\ntopic = "/state"\nfields = { x = "x" }\nmax_age = 0.001\n'
                    '[[streams]]\ntopic = "/tf"\ntime = "stamp"\nfields = { tx = "tx" }\nmax_age = 0.01\n'
                    'missing = "fill"\nfill = 0.0\n'
                    '[action]\ntopic = "/state"\nfield = "x"\ntype = "continuous"\nmax_age = 0.001\n'
                    '[cost]\nfield = "x"\n')
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["ingest", "mcap", str(f), "--spec", str(spec), "--out", str(tmp_path / "ds")]) == 0
    out = capsys.readouterr().out
    assert "read: {'/state': 800, '/tf': 800}" in out
    assert "used (decoded and placed against the clock's steps): {'/state': 800, '/tf': 300}" in out
    assert "orphaned, unused (held for an epoch the clock never reached): {'/tf': 500}" in out
    assert " 1600  1100        0     500  -" in out  # the file's row: read, used, skipped, unused


def test_a_split_recording_counts_orphans_in_the_file_they_came_from(tmp_path):
    """The orphans are found after the last file is read: each file's counts still add up."""
    msgs = _log(behind=True)
    a = write_log(tmp_path / "rec_0.mcap", msgs[:700])
    b = write_log(tmp_path / "rec_1.mcap", msgs[700:])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, s = ingest_mcap([a, b], _spec("fill"))
    assert [Path(f["path"]).name for f in s["files"]] == [a.name, b.name]
    _partition_holds(s["files"][0], Counter(t for t, _, _ in msgs[:700]))
    _partition_holds(s["files"][1], Counter(t for t, _, _ in msgs[700:]))
    assert s["messages_orphaned"] == {"/tf": 500} and s["messages_used"]["/tf"] == 300


@st.composite
def perturbed_logs(draw):
    """The differential test's generated logs, with a topic the spec does not read, a
    second stream on the command topic (two keys of one message), and a few messages
    moved later in the file (late) or stamped back by more than restart (orphans)."""
    messages, cuts, d, flush_every, truth = draw(logs())
    messages = list(messages)
    for s in d["streams"]:  # every step kept or filled: the ingest succeeds more often
        s.update(missing="fill", fill=-7.0)
    if draw(st.booleans()):
        d["streams"].append({"topic": "/cmd", "role": "aux", "fields": {"cmd_k": "k"}, "max_age": 1.0,
                             "missing": "fill", "fill": -1.0})
    n_other = draw(st.integers(0, 5))
    for j in range(n_other):
        i = draw(st.integers(0, len(messages)))
        messages.insert(i, ref.Message("/other", 1_000_000_000 + j, 1_000_000_000 + j, {"v": 0.0}))
    moved = False
    for _ in range(draw(st.integers(0, 4))):
        if not messages:
            break
        i = draw(st.integers(0, len(messages) - 1))
        m = messages[i]
        if draw(st.booleans()):  # stamped back by 0.4 s (restart is 0.25 s)
            messages[i] = ref.Message(m.topic, m.log_time - 400_000_000, m.publish_time - 400_000_000, m.data)
        else:  # written later in the file
            moved = True
            messages.insert(min(i + draw(st.integers(1, 400)), len(messages)), messages.pop(i))
    return messages, cuts, d, flush_every, moved


def _counts_of(files: list[list]) -> list[Counter]:
    return [Counter(m.topic for m in part) for part in files]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(perturbed_logs())
def test_per_topic_counts_partition_the_messages_in_memory(case):
    """Assembled in memory: used + orphaned + dropped late = the messages of each spec topic;
    with every message in file order within the window, the counts are the reference's."""
    messages, cuts, d, flush_every, moved = case
    spec = parse_mcap_spec(d)
    topics = {s.topic for s in (*spec.streams, spec.action_stream)} | {spec.clock_topic} - {None}
    mine = [m for m in messages if m.topic in topics]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            got = assemble(_split(mine, cuts), spec, flush_every=flush_every)
        except IngestError:
            return
    want = Counter(m.topic for m in mine)
    for t in topics:
        total = got.used.get(t, 0) + got.orphaned.get(t, 0) + got.stale.get(t, 0) + got.dropped_late.get(t, 0)
        assert total == want.get(t, 0), (t, got.used, got.orphaned, got.dropped_late, want)
    assert sum(got.orphaned.values()) == got.stats["orphan_messages"]
    if not moved:
        want_ref = ref.assign_epochs(mine, spec)[1]
        assert {t: n for t, n in got.used.items() if n} == want_ref.used_by_topic
        assert got.orphaned == want_ref.orphans_by_topic and got.dropped_late == want_ref.late_by_topic
        assert got.stale == want_ref.stale_by_topic


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(perturbed_logs())
def test_per_topic_counts_partition_the_messages_of_real_files(case):
    """Written as MCAP files (a split recording), ingested: per file and in total, per
    topic, the parts add up to the messages in the file (and to messages_read)."""
    messages, cuts, d, _, _ = case
    with tempfile.TemporaryDirectory() as tmp:
        parts = _split(messages, cuts)
        paths = [write_log(Path(tmp) / f"rec_{i}.mcap", [(m.topic, m.log_time, m.data) for m in p])
                 for i, p in enumerate(parts)]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                _, s = ingest_mcap(paths, parse_mcap_spec(d))
            except IngestError:
                return
    per_file = _counts_of(parts)
    assert len(s["files"]) == len(parts)
    for entry, in_file in zip(s["files"], per_file, strict=True):
        _partition_holds(entry, in_file)
    _partition_holds(s, sum(per_file, Counter()))


def test_messages_dropped_late_are_not_counted_as_used(tmp_path):
    """The last 5 /cmd messages of episode 0 are written after the clock has run 0.3 s
    (more than reorder_window = 0.2 s) into episode 1: their epoch is over, they are
    dropped. /cmd feeds two keys (the action and an aux stream): each message counts once."""
    from tests.test_mcap_epochs import rl_log, rl_spec

    ep0, ep1 = rl_log(1, 0), [m for m in rl_log(2, 0) if m[2]["ep"] == 1]
    held = [m for m in ep0 if m[0] == "/cmd"][-5:]
    ep0 = [m for m in ep0 if m not in held]
    # 60 steps of episode 1 without commands (3 messages a step, /cmd left out), the held ones, the rest
    msgs = ep0 + [m for m in ep1[:180] if m[0] != "/cmd"] + held + ep1[180:]
    f = write_log(tmp_path / "late.mcap", msgs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, s = ingest_mcap([f], rl_spec(0.2))
    assert s["messages_dropped_late"] == {"/cmd": 5} and s["late_messages"] == {"/cmd": 5}
    assert s["messages_used"] == {"/state": 600, "/cmd": 535, "/reward": 600}
    in_file = Counter(t for t, _, _ in msgs)
    _partition_holds(s, in_file)
    _partition_holds(s["files"][0], in_file)
