"""MCAP ingestion, part two: streaming assembly, time restarts, split recordings, episode
conditions, event-driven commands, binned continuous actions, protobuf, per-file sources,
parallel files. Every fixture is written here with the mcap writers; expected values are
known by construction (each field encodes its own time, step or episode)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap import ingest_mcap, parse_mcap_spec

MS = 1_000_000


def write_log(path, messages, schema_names=None):
    """messages: [(topic, t_ns, dict)] written in the given (file) order, JSON encoded."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f, chunk_size=4096)
        w.start()
        sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        chans: dict[str, int] = {}
        for topic, t, m in messages:
            if topic not in chans:
                chans[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
            w.add_message(chans[topic], log_time=t, publish_time=t, data=json.dumps(m).encode())
        w.finish()
    return path


T0 = 10_000 * MS  # log times start at 10 s


def episode_messages(n_steps, t0=T0, ep=0, cmd_every=1, with_events=False, ep_id=None, terminated=False):
    """Clock at 10 Hz carrying k, a 50 Hz stream with x = 10 * ep + time since t0 in s,
    commands u = k % 3 published 5 ms before the tick (every ``cmd_every`` ticks), time ordered."""
    msgs = []
    if with_events:
        msgs.append(("/event", t0 - 2 * MS, {"event": "start", "id": ep_id, "terminated": False}))
    for j in range(n_steps * 5):
        t = t0 + j * 20 * MS
        msgs.append(("/fast", t, {"pos": {"x": 10 * ep + j * 0.02}}))
        if j % 5 == 0:
            k = j // 5
            msgs.append(("/clock", t, {"k": k, "ep": ep}))
            if k % cmd_every == 0:
                msgs.append(("/cmd", t - 5 * MS, {"u": [float(k % 3)]}))
    msgs.sort(key=lambda m: m[1])
    if with_events:
        msgs.append(("/event", t0 + (n_steps - 1) * 100 * MS + 2 * MS, {"event": "end", "id": ep_id,
                                                                        "terminated": terminated}))
    return msgs


def spec(**over):
    d = {
        "clock": {"topic": "/clock", "reorder_window": 0.5},
        "episodes": {"gap": 1.0},
        "streams": [{"topic": "/fast", "fields": {"x": "pos.x"}, "align": "previous", "max_age": 0.05}],
        "action": {"topic": "/cmd", "field": "u[0]", "align": "previous", "max_age": 0.05, "type": "discrete",
                   "values": [0.0, 1.0, 2.0]},
        "cost": {"terms": [{"field": "x", "op": "square"}]},
    }
    for k, v in over.items():
        d[k] = v
    return parse_mcap_spec(d)


def test_a_long_log_streams_with_bounded_buffers(tmp_path):
    """600 s of one continuous episode: the buffers hold a few seconds of messages, not the file."""
    f = write_log(tmp_path / "long.mcap", episode_messages(6000))
    ds, s = ingest_mcap([f], spec())
    a = ds.arrays()
    assert len(ds) == 5999 and ds.n_episodes == 1
    np.testing.assert_allclose(a.obs[:, 0], a.step * 0.1, atol=1e-9)
    np.testing.assert_array_equal(ds.info.action_table.values[a.action, 0], a.step % 3)
    total = s["messages_used"]["/fast"] + s["messages_used"]["/clock"] + s["messages_used"]["/cmd"]
    assert total == 6000 * 7
    # flushes every 5000 messages; the window is 0.5 s + max_age: a few thousand messages at most
    assert s["max_buffered_messages"] < 6000 < total / 5


def test_log_time_restarting_per_episode_splits_episodes(tmp_path):
    """Concatenated episodes whose log_time restarts at 0: each restart starts an episode,
    and every value lands in its own episode (no mixing across the restarts)."""
    msgs = [m for ep in range(3) for m in episode_messages(12, ep=ep)]
    f = write_log(tmp_path / "restarts.mcap", msgs)
    ds, s = ingest_mcap([f], spec())
    assert ds.n_episodes == 3 and len(ds) == 3 * 11 and s["restarts"] == 2
    a = ds.arrays()
    ep_of_row = np.floor(a.obs[:, 0] / 10).astype(int)  # x = 10 * ep + time
    for e in np.unique(a.episode):
        assert len(set(ep_of_row[a.episode == e])) == 1
    np.testing.assert_allclose(a.obs[:, 0] % 10, a.step * 0.1, atol=1e-9)


def test_a_split_recording_forms_one_recording_in_part_order(tmp_path):
    msgs = episode_messages(40, with_events=True, ep_id="run-7")
    half = len(msgs) // 2
    write_log(tmp_path / "rec_0.mcap", msgs[:half])
    write_log(tmp_path / "rec_1.mcap", msgs[half:])
    ev = {"topic": "/event", "id_field": "id", "event_field": "event", "terminated_field": "terminated"}
    # parts given out of order, as a glob would not: the part number decides
    ds, s = ingest_mcap([tmp_path / "rec_1.mcap", tmp_path / "rec_0.mcap"], spec(episodes=ev))
    assert s["recordings"] == [[str(tmp_path / "rec_0.mcap"), str(tmp_path / "rec_1.mcap")]]
    assert list(ds.episode_ids) == ["run-7"] and len(ds) == 39
    np.testing.assert_allclose(ds.arrays().obs[:, 0], np.arange(39) * 0.1, atol=1e-9)
    # the dataset rows name the part file each step came from
    files = ds.table.column("src_file").to_pylist()
    assert files[0].endswith("rec_0.mcap") and files[-1].endswith("rec_1.mcap")
    # as separate recordings the episode is cut in two (a start without end, an end without
    # start) and nothing is left: said so, not an empty dataset
    with pytest.raises(IngestError, match="no episode with at least one transition"):
        ingest_mcap([tmp_path / "rec_0.mcap", tmp_path / "rec_1.mcap"],
                    parse_mcap_spec({**spec(episodes=ev).raw, "sources": {"split_recordings": False}}))


def test_event_driven_commands_hold_within_max_age(tmp_path):
    """Commands published only every 4th tick: held (previous) while younger than max_age."""
    f = write_log(tmp_path / "ev.mcap", episode_messages(20, cmd_every=4))
    held = {"topic": "/cmd", "field": "u[0]", "align": "previous", "max_age": 0.5, "type": "discrete",
            "values": [0.0, 1.0, 2.0]}
    ds, _ = ingest_mcap([f], spec(action=held))
    a = ds.arrays()
    np.testing.assert_array_equal(ds.info.action_table.values[a.action, 0], (a.step - a.step % 4) % 3)
    with pytest.raises(IngestError, match=r"no /cmd command within max_age = 0.15 s"):
        ingest_mcap([f], spec(action={**held, "max_age": 0.15}))
    ds, s = ingest_mcap([f], spec(action={**held, "max_age": 0.15, "missing": "drop_step"}))
    assert s["dropped_steps"] == 10  # ticks 2 and 3 of every 4 are more than 150 ms after their command
    # a dropped step splits its episode (no transition stitched across it): pairs of ticks 4j, 4j + 1
    assert len(ds) == 5 and ds.n_episodes == 5 and s["episode_splits"] == 4
    a = ds.arrays()
    np.testing.assert_allclose(a.next_obs[:, 0] - a.obs[:, 0], 0.1, atol=1e-9)  # every transition is one tick


def test_end_and_terminal_conditions_cut_episodes(tmp_path):
    """err != 0 ends an episode (truncated) and its steps belong to none; goal == 1 ends
    one as terminated; the next episode starts when the condition clears."""
    msgs = episode_messages(30)
    for k in range(30):
        t = T0 + k * 100 * MS + 1 * MS
        msgs.append(("/status", t, {"err": int(10 <= k <= 12), "goal": int(k == 20)}))
    msgs.sort(key=lambda m: m[1])
    f = write_log(tmp_path / "cond.mcap", msgs)
    status = {"topic": "/status", "role": "aux", "fields": {"err": "err", "goal": "goal"}, "align": "nearest",
              "max_age": 0.01}
    sp = spec(streams=[spec().raw["streams"][0], status],
              episodes={"gap": 1.0, "end_when": [{"field": "err", "op": "!=", "value": 0}],
                        "terminal_when": [{"field": "goal", "op": "==", "value": 1}]})
    ds, s = ingest_mcap([f], sp)
    lengths = np.bincount(ds.arrays().episode).tolist()
    assert ds.info.feature_names == ["x"]  # status fields are auxiliary, not features
    assert s["condition_steps"] == 2  # steps 11 and 12, while err still holds
    a = ds.arrays()
    starts = a.obs[a.step == 0, 0]
    np.testing.assert_allclose(sorted(starts), [0.0, 1.3, 2.1], atol=1e-9)
    np.testing.assert_allclose(a.next_obs[a.terminated, 0], [2.0], atol=1e-9)  # ends at the goal step
    assert a.terminated.sum() == 1 and a.truncated.sum() == 2
    assert sorted(lengths) == [7, 8, 10]


def test_continuous_commands_are_binned_with_their_bin_values(tmp_path):
    rng = np.random.default_rng(0)
    u = rng.uniform(-1, 1, 50)
    msgs = []
    for k in range(50):
        t = T0 + k * 100 * MS
        msgs += [("/clock", t, {"k": k}), ("/fast", t, {"pos": {"x": k * 0.1}}),
                 ("/cmd", t + 3 * MS, {"u": [float(u[k])]})]
    f = write_log(tmp_path / "cont.mcap", msgs)
    act = {"topic": "/cmd", "field": "u[0]", "align": "nearest", "max_age": 0.05, "type": "continuous",
           "edges": [-1.0, -0.5, 0.0, 0.5, 1.0]}
    ds, _ = ingest_mcap([f], spec(action=act))
    a = ds.arrays()
    expected = np.clip(np.digitize(u[:49], [-0.5, 0.0, 0.5]), 0, 3)
    np.testing.assert_array_equal(a.action, expected)
    table = ds.info.action_table
    assert table.kind == "binned" and len(table) == 4
    for b in range(4):  # each bin keeps the mean of its commands
        assert table.values[b, 0] == pytest.approx(u[:49][expected == b].mean())


def test_rate_hz_clock_ticks_over_the_first_stream(tmp_path):
    msgs = [m for m in episode_messages(10) if m[0] != "/clock"]
    f = write_log(tmp_path / "rate.mcap", msgs)
    d = spec().raw
    ds, _ = ingest_mcap([f], parse_mcap_spec({**d, "clock": {"rate_hz": 5.0}}))
    a = ds.arrays()
    np.testing.assert_allclose(a.obs[:, 0], a.step * 0.2, atol=1e-9)  # ticks every 200 ms from the first message
    assert len(ds) == 4  # ticks at 0..0.8 s within the 0.98 s of data


def test_protobuf_log(tmp_path):
    """A protobuf-encoded log (schema: a FileDescriptorSet, as mcap_protobuf writes it)."""
    pytest.importorskip("mcap_protobuf")
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap_protobuf.writer import Writer

    fd = descriptor_pb2.FileDescriptorProto(name="robot.proto", package="robot")
    m = fd.message_type.add(name="State")
    m.field.add(name="k", number=1, type=descriptor_pb2.FieldDescriptorProto.TYPE_INT64)
    m.field.add(name="x", number=2, type=descriptor_pb2.FieldDescriptorProto.TYPE_DOUBLE)
    c = fd.message_type.add(name="Cmd")
    c.field.add(name="u", number=1, type=descriptor_pb2.FieldDescriptorProto.TYPE_DOUBLE,
                label=descriptor_pb2.FieldDescriptorProto.LABEL_REPEATED)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fd)
    State = message_factory.GetMessageClass(pool.FindMessageTypeByName("robot.State"))
    Cmd = message_factory.GetMessageClass(pool.FindMessageTypeByName("robot.Cmd"))
    path = tmp_path / "pb.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        for k in range(20):
            t = T0 + k * 100 * MS
            w.write_message("/state", State(k=k, x=0.1 * k), log_time=t, publish_time=t)
            w.write_message("/cmd", Cmd(u=[float(k % 2)]), log_time=t + 4 * MS, publish_time=t + 4 * MS)
        w.finish()
    sp = parse_mcap_spec({
        "clock": {"topic": "/state"}, "streams": [{"topic": "/state", "fields": {"x": "x"}, "max_age": 0.001}],
        "action": {"topic": "/cmd", "field": "u[0]", "max_age": 0.01, "type": "discrete", "values": [0.0, 1.0]},
        "cost": {"terms": [{"field": "x", "op": "abs"}]},
    })
    ds, s = ingest_mcap([path], sp)
    a = ds.arrays()
    assert len(ds) == 19 and s["messages_used"] == {"/state": 20, "/cmd": 20}
    np.testing.assert_allclose(a.obs[:, 0], 0.1 * a.step, atol=1e-12)
    np.testing.assert_array_equal(a.action, a.step % 2)


def test_per_file_sources_globs_and_parallel_files_are_deterministic(tmp_path):
    d = tmp_path / "logs"
    d.mkdir()
    for name, ep in (("demo_a", 0), ("explore_b", 1), ("explore_c", 2)):
        msgs = episode_messages(8, ep=ep)
        msgs.insert(3, ("/camera", T0, {"blob": "unneeded"}))  # not in the spec: skipped undecoded, counted
        write_log(d / f"{name}.mcap", msgs)
    sp = parse_mcap_spec({**spec().raw, "source": {"value": "unknown", "by_file": {"demo_*": "demonstration",
                                                                                   "explore_*": "exploration"}}})
    one, s1 = ingest_mcap([str(d / "*.mcap")], sp)
    two, s2 = ingest_mcap([str(d / "*.mcap")], sp, jobs=2)
    assert one.fingerprint() == two.fingerprint() and list(one.episode_ids) == list(two.episode_ids)
    assert one.source_counts() == {"demonstration": 7, "exploration": 14}
    assert s1["messages_skipped"] == {"/camera": 3} and s1["files"][0]["messages_skipped"] == {"/camera": 1}
    assert [f["path"] for f in s1["files"]] == sorted(str(p) for p in d.glob("*.mcap"))
    with pytest.raises(IngestError, match="no file matches"):
        ingest_mcap([str(d / "nothing_*.mcap")], sp)


def test_a_topic_missing_from_one_file_of_many_follows_its_missing_rule(tmp_path):
    write_log(tmp_path / "a.mcap", [("/extra", T0 - MS, {"y": 1.0})] + episode_messages(6))
    write_log(tmp_path / "b.mcap", episode_messages(6, ep=1))  # no /extra here
    extra = {"topic": "/extra", "fields": {"y": "y"}, "align": "previous", "max_age": 100.0}
    files = [tmp_path / "a.mcap", tmp_path / "b.mcap"]
    with pytest.raises(IngestError, match=r"b.mcap: topic '/extra' of the spec is not in the file .*; step at "
                                          r"t = 10.000000 s \(log_time 10000000000\) has no value for 'y'"):
        ingest_mcap(files, spec(streams=[spec().raw["streams"][0], extra]))
    ds, _ = ingest_mcap(files, spec(streams=[spec().raw["streams"][0], {**extra, "missing": "fill", "fill": -1.0}]))
    y = ds.arrays().obs[:, 1]
    assert set(y[:5]) == {1.0} and set(y[5:]) == {-1.0}


def test_empty_file_and_undecodable_needed_channel(tmp_path):
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(IngestError, match=r"empty.mcap: empty file \(0 bytes\)"):
        ingest_mcap([tmp_path / "empty.mcap"], spec())


def test_a_bad_file_in_a_glob_is_named_and_under_quarantine_skipped_and_counted(tmp_path):
    d = tmp_path / "logs"
    d.mkdir()
    write_log(d / "a.mcap", episode_messages(8))
    (d / "b.mcap").write_bytes(b"not an mcap file at all")
    (d / "c.mcap").write_bytes(b"")
    write_log(d / "d.mcap", episode_messages(8, ep=1))
    with pytest.raises(IngestError, match=r"b.mcap: not an MCAP file"):
        ingest_mcap([str(d / "*.mcap")], spec())
    with pytest.warns(UserWarning, match="skipped"):
        ds, s = ingest_mcap([str(d / "*.mcap")], spec(), on_error="quarantine")
    assert ds.n_episodes == 2 and len(ds) == 14
    skipped = {Path(f["files"][0]).name: f["error"] for f in s["skipped_files"]}
    assert set(skipped) == {"b.mcap", "c.mcap"} and "empty" in skipped["c.mcap"]


def test_a_missing_command_topic_is_named(tmp_path):
    f = write_log(tmp_path / "nocmd.mcap", [m for m in episode_messages(8) if m[0] != "/cmd"])
    act = {**spec().raw["action"], "missing": "drop_step"}
    with pytest.raises(IngestError, match=r"topics without any message: \['/cmd'\]; 8 steps dropped"):
        ingest_mcap([f], spec(action=act))


def test_a_terminal_role_field_and_a_reward_field(tmp_path):
    """role = "terminal": non-zero ends the episode as terminated; role = "reward": cost = -reward."""
    msgs = episode_messages(10)
    msgs += [("/env", T0 + k * 100 * MS, {"done": int(k == 6), "r": float(k)}) for k in range(10)]
    msgs.sort(key=lambda m: m[1])
    f = write_log(tmp_path / "env.mcap", msgs)
    d = spec().raw
    env = {"topic": "/env", "role": "terminal", "fields": {"done": "done"}, "max_age": 0.001}
    rew = {"topic": "/env", "role": "reward", "fields": {"r": "r"}, "max_age": 0.001}
    ds, _ = ingest_mcap([f], parse_mcap_spec({**d, "streams": [d["streams"][0], env, rew], "cost": {}}))
    a = ds.arrays()
    assert a.terminated.tolist()[:6] == [False] * 5 + [True] and ds.n_episodes == 2  # steps 0..6, then 7..9
    np.testing.assert_allclose(a.cost, -np.round(a.obs[:, 0] * 10), atol=1e-9)  # r = k at the step


def test_a_rosbag2_bag_directory_is_one_recording_in_metadata_order(tmp_path):
    """What `ros2 bag record` writes: a directory with metadata.yaml and the split files."""
    bag = tmp_path / "rosbag2_2026_11_22"
    bag.mkdir()
    msgs = episode_messages(40, with_events=True, ep_id="run-1")
    third = len(msgs) // 3
    for i in range(3):  # the file names do not sort in recording order: metadata.yaml decides
        write_log(bag / f"part_{['b', 'c', 'a'][i]}.mcap", msgs[i * third:(i + 1) * third if i < 2 else None])
    (bag / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: mcap\n  relative_file_paths:\n"
        "    - part_b.mcap\n    - part_c.mcap\n    - part_a.mcap\n  duration:\n    nanoseconds: 4000000000\n")
    ev = {"topic": "/event", "id_field": "id", "event_field": "event", "terminated_field": "terminated"}
    ds, s = ingest_mcap([bag], spec(episodes=ev))
    assert list(ds.episode_ids) == ["run-1"] and len(ds) == 39
    assert [Path(p).name for p in s["recordings"][0]] == ["part_b.mcap", "part_c.mcap", "part_a.mcap"]
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  storage_identifier: other\n"
                                       "  relative_file_paths:\n    - x.other\n")
    with pytest.raises(IngestError, match="stored as 'other', not MCAP"):
        ingest_mcap([bag], spec(episodes=ev))
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  storage_identifier: sqlite3\n"
                                       "  relative_file_paths:\n    - x.db3\n")  # SQLite: read by rosbags, named
    with pytest.raises(IngestError,
                       match=r"rosbag2_2026_11_22/metadata.yaml: relative_file_paths\[0\] = 'x.db3'.*missing"):
        ingest_mcap([bag], spec(episodes=ev))
    with pytest.raises(IngestError, match="no file matches"):
        ingest_mcap([str(tmp_path / "nothing*")], spec())
