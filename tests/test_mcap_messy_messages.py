"""MCAP messages that are valid MCAP but not what the spec reads (an ingestion fuzz review,
2026-11-29): each is an error naming the topic, the message's log_time and the field, or a
counted, warned-of decision; never a silent change of the data."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap import ingest_mcap
from tests.test_ingest_mcap_streaming import MS, T0, episode_messages, spec, write_log

EV = {"topic": "/event", "id_field": "id", "event_field": "event", "terminated_field": "terminated"}


def _with_end_flag(flag, ep_id="a", drop_start_flag=False):
    msgs = episode_messages(8, with_events=True, ep_id=ep_id)
    if drop_start_flag:
        del next(m for m in msgs if m[0] == "/event")[2]["terminated"]
    msgs[-1][2]["terminated"] = flag
    return msgs


@pytest.mark.parametrize("flag, terminated", [(True, True), (False, False), (1, True), (0, False), (1.0, True),
                                              (0.0, False)])
def test_an_end_event_flag_is_read_as_a_flag_and_a_start_event_needs_none(tmp_path, flag, terminated):
    f = write_log(tmp_path / "ok.mcap", _with_end_flag(flag, drop_start_flag=True))
    ds, _ = ingest_mcap([f], spec(episodes=EV))
    assert ds.n_episodes == 1 and bool(ds.arrays().terminated[-1]) is terminated


@pytest.mark.parametrize("flag, said", [("false", "is 'false', not a flag"), (None, "is null"), (2, "is 2, not a flag"),
                                        (0.5, "is 0.5, not a flag"), ("1", "is '1', not a flag")])
def test_an_end_event_flag_that_is_no_flag_is_an_error_naming_the_message(tmp_path, flag, said):
    f = write_log(tmp_path / "bad.mcap", _with_end_flag(flag))
    end_t = T0 + 7 * 100 * MS + 2 * MS
    with pytest.raises(IngestError, match=rf"topic '/event', message at log_time {end_t}: .*'terminated'.* {said}"):
        ingest_mcap([f], spec(episodes=EV))
    msgs = _with_end_flag(True)
    del msgs[-1][2]["terminated"]  # an end event without the flag
    with pytest.raises(IngestError, match=rf"log_time {end_t}: the episode event has no field 'terminated'"):
        ingest_mcap([write_log(tmp_path / "none.mcap", msgs)], spec(episodes=EV))


def test_episode_ids_naming_two_episodes_are_an_error_and_generated_ids_stay_apart(tmp_path):
    for d in ("a", "b"):
        (tmp_path / d).mkdir()
        write_log(tmp_path / d / "run.mcap", episode_messages(6, with_events=True, ep_id="ep0"))
    files = [tmp_path / "a" / "run.mcap", tmp_path / "b" / "run.mcap"]
    with pytest.raises(IngestError, match=r"episode id 'ep0' names two episodes: in .*a/run.mcap \(log_time \d+\) "
                                          r"and in .*b/run.mcap"):
        ingest_mcap(files, spec(episodes=EV))
    twice = episode_messages(6, with_events=True, ep_id="ep0") + episode_messages(
        6, t0=T0 + 5000 * MS, with_events=True, ep_id="ep0")
    with pytest.raises(IngestError, match="episode id 'ep0' names two episodes"):  # one file, an id reused
        ingest_mcap([write_log(tmp_path / "twice.mcap", twice)], spec(episodes=EV))
    ds, _ = ingest_mcap(files, spec())  # ids numbered per recording, both recordings named "run"
    assert ds.n_episodes == 2 and len(set(ds.episode_ids)) == 2 and len(ds) == 10


def _broken_log(tmp_path, msgs, bad):
    import json

    from mcap.writer import Writer

    path = tmp_path / "broken.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        chans: dict[str, int] = {}
        for i, (topic, t, m) in enumerate(msgs):
            if topic not in chans:
                chans[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
            data = b"{u: 1" if i == bad else json.dumps(m).encode()
            w.add_message(chans[topic], log_time=t, publish_time=t, data=data)
        w.finish()
    return path


def test_a_message_that_does_not_decode_names_its_topic_and_log_time(tmp_path):
    msgs = episode_messages(6)
    bad = next(i for i, m in enumerate(msgs) if m[0] == "/cmd" and m[1] > T0)
    path = _broken_log(tmp_path, msgs, bad)
    with pytest.raises(IngestError, match=rf"broken.mcap: topic '/cmd', message at log_time {msgs[bad][1]}: cannot be "
                                          r"decoded as json \(JSONDecodeError"):
        ingest_mcap([path], spec())


def test_under_quarantine_a_message_that_does_not_decode_sets_its_episode_aside_not_the_file(tmp_path):
    """It skipped the whole recording; now it is lost as a damaged chunk's messages are: the
    episode around it goes to quarantine/ with the reason, the others are kept."""
    from offline_adp.data.io import read_quarantine

    msgs = [m for ep in range(3) for m in episode_messages(8, t0=T0 + ep * 5000 * MS, ep=ep, with_events=True,
                                                            ep_id=f"e{ep}")]
    bad = next(i for i, m in enumerate(msgs) if m[0] == "/cmd" and m[1] > T0 + 5000 * MS + 300 * MS)
    path = _broken_log(tmp_path, msgs, bad)
    with pytest.warns(UserWarning, match="1 message\\(s\\) that do not decode, their episodes set aside"):
        ds, s = ingest_mcap([path], spec(episodes=EV), tmp_path / "ds", on_error="quarantine")
    assert list(ds.episode_ids) == ["e0", "e2"] and s["episodes_lost_to_damage"] == 1
    q = read_quarantine(tmp_path / "ds")
    assert q.num_rows == 7 and set(q.column("episode_id").to_pylist()) == {"e1"}


def test_a_repeated_clock_time_is_one_step_counted_and_warned_of(tmp_path):
    msgs = episode_messages(8)
    clock = [m for m in msgs if m[0] == "/clock"]
    msgs.insert(msgs.index(clock[3]) + 1, ("/clock", clock[3][1], {"k": 3, "ep": 0}))  # published twice
    f = write_log(tmp_path / "dup.mcap", msgs)
    with pytest.warns(UserWarning, match="1 clock message repeats the time of the one before them"):
        ds, s = ingest_mcap([f], spec())
    assert len(ds) == 7 and s["duplicate_clock_times"] == 1  # 8 distinct times: 7 transitions, none of length 0
    np.testing.assert_allclose(np.diff(ds.arrays().obs[:, 0]), 0.1, atol=1e-9)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ingest_mcap([write_log(tmp_path / "ok.mcap", episode_messages(8))], spec())


@pytest.mark.parametrize("value, said", [(True, "True is a boolean"), (2**60 + 1, "beyond 2\\^53")])
def test_a_command_of_a_boolean_or_an_integer_float64_cannot_hold_is_an_error(tmp_path, value, said):
    msgs = episode_messages(6)
    cmd = next(i for i, m in enumerate(msgs) if m[0] == "/cmd" and m[1] > T0)
    msgs[cmd][2]["u"] = [value]
    act = {"topic": "/cmd", "field": "u[0]", "align": "previous", "max_age": 0.05, "type": "continuous"}
    with pytest.raises(IngestError, match=rf"topic '/cmd', message at log_time {msgs[cmd][1]}: field .* {said}"):
        ingest_mcap([write_log(tmp_path / "c.mcap", msgs)], spec(action=act))


def test_a_spec_of_the_other_kind_says_which_command_reads_it(tmp_path):
    from offline_adp.errors import SpecError
    from offline_adp.ingest.mcap import parse_mcap_spec
    from offline_adp.ingest.spec import parse_parquet_spec

    table = {"episode": {"id": "run"}, "observations": {"columns": ["x"]}, "action": {"column": "u"},
             "cost": {"column": "c"}}
    with pytest.raises(SpecError, match="a Parquet/CSV ingestion spec .*`offline-adp ingest parquet` reads it"):
        parse_mcap_spec(table)
    with pytest.raises(SpecError, match="an MCAP ingestion spec .*`offline-adp ingest mcap` reads it"):
        parse_parquet_spec(spec().raw)
    with pytest.raises(SpecError, match=r"unknown key\(s\) \['topik'\] \(did you mean 'topic'\?\)"):
        parse_mcap_spec({**spec().raw, "clock": {"topik": "/clock"}})


def test_a_misspelled_column_is_named_with_the_column_it_probably_meant(tmp_path):
    import pandas as pd

    from offline_adp.ingest.parquet import ingest_parquet
    from offline_adp.ingest.spec import parse_parquet_spec

    pd.DataFrame({"run": [0, 0], "k": [0, 1], "x": [0.0, 1.0], "command": [0, 1], "c": [1.0, 1.0]}).to_parquet(
        tmp_path / "t.parquet")
    sp = parse_parquet_spec({"kind": "steps", "episode": {"id": "run", "step": "k"}, "observations": {"columns": ["x"]},
                             "action": {"column": "comand"}, "cost": {"column": "c"}})
    with pytest.raises(IngestError, match=r"needs columns \['comand'\] that the file does not have \(did you mean "
                                          r"'command'\?\)"):
        ingest_parquet([tmp_path / "t.parquet"], sp, tmp_path / "ds")


def test_an_end_event_s_id_and_source_are_not_read_and_other_kinds_are_not_checked(tmp_path):
    """Only a start event's id and source name the episode: an end event's may be null, and
    an event of another kind (counted as unknown) holds nothing the ingest reads."""
    msgs = _with_end_flag(True)
    msgs[-1][2]["id"] = None
    msgs.append(("/event", msgs[-1][1] + MS, {"event": "pause", "id": None}))
    ds, _ = ingest_mcap([write_log(tmp_path / "e.mcap", msgs)], spec(episodes=EV))
    assert list(ds.episode_ids) == ["a"] and bool(ds.arrays().terminated[-1])


def test_a_discrete_command_may_be_a_flag_and_files_may_come_from_a_generator(tmp_path):
    msgs = episode_messages(6)
    for m in msgs:
        if m[0] == "/cmd":
            m[2]["u"] = [bool(int(m[1] // (100 * MS)) % 2)]  # a gripper flag, as JSON true/false
    f = write_log(tmp_path / "g.mcap", msgs)
    act = {"topic": "/cmd", "field": "u[0]", "align": "previous", "max_age": 0.05, "type": "discrete",
           "values": [0.0, 1.0]}
    ds, _ = ingest_mcap((p for p in [f]), spec(action=act), tmp_path / "ds")  # a one-shot iterable, read once
    assert len(ds) == 5 and set(ds.arrays().action.tolist()) == {0, 1}
