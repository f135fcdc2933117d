"""MCAP ingestion (first part of issue 3): round trips, alignment, errors, a real log."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from offline_adp.errors import IngestError, SpecError
from offline_adp.ingest.mcap import StreamSpec, _align, ingest_mcap, mcap_info, parse_mcap_spec
from offline_adp.simulate import simulate
from offline_adp.simulate.mcap_writer import write_mcap
from tests.conftest import SHARED_DATA

SPEC = Path(__file__).resolve().parents[1] / "data" / "specs" / "path_tracking_mcap.toml"
FIELDS = ("obs", "next_obs", "cost", "action", "terminated", "truncated", "step", "episode")


@pytest.mark.parametrize("encoding", ["json", "ros2"])
def test_path_tracking_logs_ingest_back_to_the_direct_dataset(tmp_path, encoding):
    ds = simulate("path_tracking", 4, 4, seed=3, horizon=30)
    files = write_mcap(ds, tmp_path / "logs", encoding=encoding, seed=1)
    back, summary = ingest_mcap(files, SPEC, tmp_path / "ds")
    a, b = ds.arrays(), back.arrays()
    for f in FIELDS:  # multi-rate topics, latencies and jitter: exact up to round-off
        np.testing.assert_allclose(getattr(b, f), getattr(a, f), atol=1e-9, err_msg=f)
    assert list(back.episode_ids) == list(ds.episode_ids) and back.source_counts() == ds.source_counts()
    assert summary["doctor"]["ok"] and summary["dropped_steps"] == 0
    assert summary["files"][0]["messages_used"]["/vehicle/odometry"] > 0
    x = back.arrays(dtype=np.float32).obs  # FQI-ready arrays
    assert x.shape == (len(ds), 7) and x.dtype == np.float32


def _write_json_mcap(path, topics):
    """topics: {topic: [(t_ns, dict), ...]} written in the given order (file order)."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        chans = {t: w.register_channel(topic=t, message_encoding="json", schema_id=sid) for t in topics}
        for t, msgs in topics.items():
            for ts, m in msgs:
                w.add_message(chans[t], log_time=ts, publish_time=ts, data=json.dumps(m).encode())
        w.finish()


MS = 1_000_000


def _synthetic(tmp_path, with_bad_channel=False):
    clock = [(k * 100 * MS, {"k": k}) for k in range(10)]
    fast = [(k * 20 * MS, {"pos": {"x": k * 0.02}}) for k in range(50)]  # x = time in seconds, 50 Hz
    cmd = [(k * 100 * MS + 7 * MS, {"u": [0.5 * (k % 3)]}) for k in range(10)]
    topics = {"/clock": clock, "/fast": list(reversed(fast)), "/cmd": cmd}  # /fast out of time order in the file
    _write_json_mcap(tmp_path / "a.mcap", topics)
    if with_bad_channel:
        from mcap.writer import Writer

        with open(tmp_path / "b.mcap", "wb") as f:
            w = Writer(f)
            w.start()
            sid = w.register_schema(name="p", encoding="protobuf", data=b"\x00")
            ch = w.register_channel(topic="/weird", message_encoding="my-encoding", schema_id=sid)
            w.add_message(ch, log_time=1, publish_time=1, data=b"\x01")
            w.finish()
    return tmp_path / "a.mcap"


def _spec(align="previous", max_age=0.05, extra_stream=None):
    streams = [{"topic": "/clock", "fields": {"k": "k"}, "max_age": 0.001},
               {"topic": "/fast", "fields": {"x": "pos.x"}, "align": align, "max_age": max_age}]
    if extra_stream:
        streams.append(extra_stream)
    return parse_mcap_spec({
        "clock": {"topic": "/clock"}, "episodes": {"gap": 1.0}, "streams": streams,
        "action": {"topic": "/cmd", "field": "u[0]", "align": "nearest", "max_age": 0.05, "type": "discrete"},
        "cost": {"terms": [{"field": "x", "op": "square"}]},
    })


@pytest.mark.parametrize("align", ["previous", "nearest", "linear"])
def test_alignment_modes_on_a_multi_rate_log(tmp_path, align):
    f = _synthetic(tmp_path)
    ds, _ = ingest_mcap([f], _spec(align))
    a = ds.arrays()
    np.testing.assert_allclose(a.obs[:, 1], a.step * 0.1, atol=1e-12)  # 50 Hz samples land on every 100 ms tick
    np.testing.assert_allclose(a.cost, a.obs[:, 1] ** 2, atol=1e-12)  # cost = x^2 at the step
    np.testing.assert_array_equal(ds.info.action_table.values[a.action, 0], 0.5 * (a.step % 3))  # event commands, +7 ms
    assert len(ds) == 9 and a.truncated[-1]


def test_align_function_previous_nearest_linear_and_max_age():
    ts = np.array([0, 100, 200]) * MS
    vals = np.array([0.0, 1.0, 2.0])
    at = np.array([50, 149, 260, 400]) * MS
    v, ok = _align(ts, vals, at, StreamSpec("/t", {}, align="previous", max_age=0.07))
    np.testing.assert_array_equal(v, [0, 1, 2, 2])
    np.testing.assert_array_equal(ok, [True, True, True, False])  # 400 ms is 200 ms after the last sample
    v, ok = _align(ts, vals, at, StreamSpec("/t", {}, align="nearest", max_age=0.07))
    np.testing.assert_array_equal(v, [0, 1, 2, 2])
    np.testing.assert_array_equal(ok, [True, True, True, False])
    v, ok = _align(ts, vals, at[:2], StreamSpec("/t", {}, align="linear", max_age=0.1))
    np.testing.assert_allclose(v, [0.5, 1.49])
    np.testing.assert_array_equal(ok, [True, True])


def test_missing_values_error_fill_or_drop(tmp_path):
    import dataclasses

    f = _synthetic(tmp_path)
    base = _spec()
    stale = dataclasses.replace(base.streams[1], max_age=-1.0)  # no sample is ever fresh enough
    with pytest.raises(IngestError, match="no /fast message within max_age"):
        ingest_mcap([f], dataclasses.replace(base, streams=(base.streams[0], stale)))
    filled = dataclasses.replace(stale, missing="fill", fill=7.0)
    ds, _ = ingest_mcap([f], dataclasses.replace(base, streams=(base.streams[0], filled)))
    assert (ds.arrays().obs[:, 1] == 7.0).all()
    dropped = dataclasses.replace(base.streams[1], align="previous", max_age=0.0, missing="drop_step")
    ds, s = ingest_mcap([f], dataclasses.replace(base, streams=(base.streams[0], dropped)))
    assert s["dropped_steps"] == 0 and len(ds) == 9  # every tick has a sample exactly at its time


def test_undecodable_channels_unneeded_skipped_needed_named(tmp_path):
    from mcap.writer import Writer

    _synthetic(tmp_path, with_bad_channel=True)
    info = mcap_info(tmp_path / "b.mcap")
    assert info["topics"]["/weird"]["fields"] is None  # listed, not decodable
    # the good topics and an undecodable one in one file: unneeded, it is skipped (counted, never decoded)
    mixed = tmp_path / "mixed.mcap"
    with open(mixed, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        bad = w.register_schema(name="p", encoding="protobuf", data=b"\x00")
        weird = w.register_channel(topic="/weird", message_encoding="my-encoding", schema_id=bad)
        chans = {t: w.register_channel(topic=t, message_encoding="json",
                                       schema_id=sid) for t in ("/clock", "/fast", "/cmd")}
        for k in range(10):
            t = k * 100 * MS
            w.add_message(weird, log_time=t, publish_time=t, data=b"\x01\x02")
            w.add_message(chans["/clock"], log_time=t, publish_time=t, data=json.dumps({"k": k}).encode())
            for j in range(5):
                w.add_message(chans["/fast"], log_time=t + j * 20 * MS, publish_time=t,
                              data=json.dumps({"pos": {"x": (t + j * 20 * MS) / 1e9}}).encode())
            w.add_message(chans["/cmd"], log_time=t + 7 * MS, publish_time=t,
                          data=json.dumps({"u": [0.5 * (k % 3)]}).encode())
        w.finish()
    ds, s = ingest_mcap([mixed], _spec())
    assert len(ds) == 9 and s["messages_skipped"] == {"/weird": 10}
    spec = _spec(extra_stream={"topic": "/weird", "fields": {"w": "w"}})
    with pytest.raises(IngestError, match="needed topic '/weird' has message encoding 'my-encoding'"):
        ingest_mcap([mixed], spec)


def test_bad_field_path_and_spec_errors(tmp_path):
    f = _synthetic(tmp_path)
    spec = _spec(extra_stream={"topic": "/fast", "fields": {"z": "pos.zz"}})
    with pytest.raises(IngestError, match=r"a.mcap: topic '/fast', message at log_time \d+: field 'z' "
                                          r"\(path 'pos.zz'\) cannot be read as a number .* mcap-info"):
        ingest_mcap([f], spec)
    with pytest.raises(SpecError, match="valid keys"):
        parse_mcap_spec({"clock": {"topic": "/c", "rate": 10}})
    with pytest.raises(SpecError, match="no expressions"):
        parse_mcap_spec({"clock": {"topic": "/c"}, "streams": [{"topic": "/c", "fields": {"a": "a"}}],
                         "action": {"topic": "/c", "field": "a"}, "cost": {}})
    with pytest.raises(IngestError, match="cannot read as MCAP"):
        (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
        mcap_info(tmp_path / "junk.mcap")


@pytest.mark.skipif(not (SHARED_DATA / "nav2_turtlebot.mcap").exists(), reason="../shared/data is not present")
def test_real_rosbag2_recording():
    path = SHARED_DATA / "nav2_turtlebot.mcap"
    info = mcap_info(path)
    assert info["profile"] == "ros2" and info["topics"]["/odom"]["messages"] == 2639
    # no command topic in this log: the yaw rate from odometry stands in for the command, binned
    spec = parse_mcap_spec({
        "clock": {"topic": "/odom", "time": "header.stamp"}, "episodes": {"gap": 2.0},
        "streams": [{"topic": "/odom", "time": "header.stamp", "max_age": 0.001,
                     "fields": {"x": "pose.pose.position.x", "y": "pose.pose.position.y", "v": "twist.twist.linear.x"}},
                    {"topic": "/amcl_pose", "time": "header.stamp", "align": "previous", "max_age": 5.0,
                     "missing": "drop_step",
                     "fields": {"amcl_x": "pose.pose.position.x"}}],
        "action": {"topic": "/odom", "field": "twist.twist.angular.z", "time": "header.stamp", "max_age": 0.001,
                   "type": "continuous", "n_bins": 5},
        "cost": {"terms": [{"field": "v", "op": "abs", "weight": -1.0}]},
    })
    ds, summary = ingest_mcap([path], spec)
    assert summary["doctor"]["ok"]
    assert summary["files"][0]["messages_used"]["/odom"] == 2639
    assert len(ds) + ds.n_episodes + summary["dropped_steps"] == 2639  # every odom message is a step
    # the counts partition the file's messages, topic by topic as mcap-info counts them
    assert summary["messages_read"] == {t: v["messages"] for t, v in info["topics"].items()}
    assert summary["messages_used"] == {"/odom": 2639, "/amcl_pose": 135}
    assert summary["messages_skipped"] == {"/tf": 5422, "/tf_static": 1}
    assert len(ds.info.action_table) == 5 and ds.info.action_table.kind == "binned"


@pytest.mark.skipif(not (SHARED_DATA / "nav2_turtlebot.mcap").exists(), reason="../shared/data is not present")
def test_real_recording_tf_messages_set_aside_are_not_used():
    """/tf's transforms[0] is another frame pair from message to message: one stamp 1.68 s
    behind the others was read as a restart, and the 539 /tf messages after it were held for
    an epoch the clock never reached, 254 steps filled (2026-11-29 audit). That stamp is set
    aside as stale now, every step has its /tf value, and used + stale = the messages
    mcap-info counts."""
    import warnings

    path = SHARED_DATA / "nav2_turtlebot.mcap"
    spec = parse_mcap_spec({
        "clock": {"topic": "/odom", "time": "header.stamp"}, "episodes": {"gap": 2.0},
        "streams": [{"topic": "/odom", "time": "header.stamp", "max_age": 0.001,
                     "fields": {"v": "twist.twist.linear.x"}},
                    {"topic": "/tf", "time": "transforms[0].header.stamp", "max_age": 0.1, "missing": "fill",
                     "fill": 0.0, "role": "aux", "fields": {"tf_x": "transforms[0].transform.translation.x"}}],
        "action": {"topic": "/odom", "field": "twist.twist.angular.z", "time": "header.stamp", "max_age": 0.001,
                   "type": "continuous", "n_bins": 5},
        "cost": {"terms": [{"field": "v", "op": "abs", "weight": -1.0}]},
    })
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, s = ingest_mcap([path], spec)
    assert s["messages_read"] == {t: v["messages"] for t, v in mcap_info(path)["topics"].items()}
    assert s["messages_stale"] == {"/tf": 1} and s["messages_used"]["/tf"] == 5422 - 1
    assert s["messages_orphaned"] == {} and not s["filled_steps"]


@pytest.mark.skipif(not (SHARED_DATA / "nav2_turtlebot.mcap").exists(), reason="../shared/data is not present")
def test_real_recording_tf_frame_pair_selected_equals_odometry():
    """/tf mixes three frame pairs; the selector transforms[child_frame_id=base_link] reads
    odom -> base_link alone. Oracle: that transform is the odometry's pose, so at every step
    (both stamped alike, aligned exactly) its translation equals /odom's position. Nothing is
    stale or orphaned, every step has its value (missing = error), and the other pairs'
    messages are counted as unselected."""
    import warnings

    path = SHARED_DATA / "nav2_turtlebot.mcap"
    sel = "transforms[child_frame_id=base_link]"
    spec = parse_mcap_spec({
        "clock": {"topic": "/odom", "time": "header.stamp"}, "episodes": {"gap": 2.0},
        "streams": [{"topic": "/odom", "time": "header.stamp", "max_age": 0.001,
                     "fields": {"v": "twist.twist.linear.x", "px": "pose.pose.position.x"}},
                    {"topic": "/tf", "time": f"{sel}.header.stamp", "max_age": 0.001,
                     "fields": {"tf_x": f"{sel}.transform.translation.x"}}],
        "action": {"topic": "/odom", "field": "twist.twist.angular.z", "time": "header.stamp", "max_age": 0.001,
                   "type": "continuous", "n_bins": 5},
        "cost": {"terms": [{"field": "v", "op": "abs", "weight": -1.0}]},
    })
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds, s = ingest_mcap([path], spec)
    assert not [w for w in caught if "stale" in str(w.message) or "orphan" in str(w.message)]
    names = [f.name for f in ds.info.features]
    obs = ds.arrays().obs
    np.testing.assert_array_equal(obs[:, names.index("tf_x")], obs[:, names.index("px")])
    assert len(ds) == 2638 and not s["messages_stale"] and not s["messages_orphaned"]
    assert s["messages_used"]["/tf"] == 2639 and s["messages_unselected"] == {"/tf": 5422 - 2639}


def _chunks_and_episodes(path) -> tuple[list[tuple[int, int]], dict[int, set[str]]]:
    """Ground truth from an undamaged file: each chunk record's byte range [offset, end) and,
    per chunk, the episodes with a message in it (an episode spans its start..end events)."""
    import struct
    from io import BytesIO

    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk
    from mcap.stream_reader import breakup_chunk

    data = path.read_bytes()
    pos, chunks, times = 8, [], []
    while pos + 9 <= len(data):
        opcode, length = struct.unpack("<BQ", data[pos:pos + 9])
        if opcode == 0x06:  # a chunk
            chunk = Chunk.read(ReadDataStream(BytesIO(data[pos + 9:pos + 9 + length])))
            chunks.append((pos, pos + 9 + length))
            times.append([r.log_time for r in breakup_chunk(chunk) if type(r).__name__ == "Message"])
        if opcode == 0x0F:  # data end
            break
        pos += 9 + length
    with open(path, "rb") as fh:
        from mcap.reader import make_reader

        ev = [(m.log_time, json.loads(m.data)) for _, _, m in make_reader(fh).iter_messages(topics=["/episode/event"])]
    starts = {e["episode_id"]: t for t, e in ev if e["event"] == "start"}
    ends = {e["episode_id"]: t for t, e in ev if e["event"] == "end"}
    held = {i: {ep for ep in starts for t in ts if starts[ep] <= t <= ends[ep]} for i, ts in enumerate(times)}
    return chunks, held


@pytest.mark.parametrize("damage", ["truncate", "bitflip"])
def test_damaged_files_recover_complete_chunks_and_report(tmp_path, damage):
    """What the project promises of a damaged file, whatever the decompressor's or CRC
    check's own exception class: a cut file keeps every complete episode; one flipped byte
    loses exactly the chunk it hit, named by its offset, and the episodes with a message in
    that chunk, and nothing else."""
    from offline_adp.data.io import read_quarantine
    from offline_adp.ingest.mcap import scan_records

    ds = simulate("path_tracking", 6, 0, seed=5, horizon=40)
    (f,) = write_mcap(ds, tmp_path / "logs", encoding="json", chunk_size=32 * 1024)  # many chunks
    data = bytearray(f.read_bytes())
    if damage == "truncate":
        data = data[: len(data) * 2 // 3]  # a crash during recording, mid-chunk
        expected = r"recovered \d+ messages of file .*bad.mcap, cut at offset \d+ .*an unknown number of messages lost"
    else:
        chunks, held = _chunks_and_episodes(f)
        assert len(chunks) >= 3
        hit = len(chunks) // 2
        lo, hi = chunks[hit]
        data[(lo + hi) // 2] ^= 0xFF  # one flipped byte inside the middle chunk's compressed data
        expected = (rf"recovered \d+ messages of file .*bad.mcap, lost 1 corrupt chunk\(s\) at offset\(s\) {lo} "
                    r"\(\w+")  # any decoder's error class: zstd, CRC, ...
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    if damage == "truncate":  # a file cut short: every complete episode is kept in both modes
        with pytest.warns(UserWarning, match=expected):
            kept_fail, s_fail = ingest_mcap([bad], SPEC)
        assert s_fail["cut_episodes"] == 1 and s_fail["dropped_rows"] > 0  # the cut episode: reported, left out
    else:
        with pytest.raises(IngestError, match=expected):
            ingest_mcap([bad], SPEC)
    with pytest.warns(UserWarning, match="recovered"):
        part, summary = ingest_mcap([bad], SPEC, tmp_path / "q", on_error="quarantine")
    assert 0 < part.n_episodes < ds.n_episodes
    assert summary["files"][0]["recovered"]["messages"] > 0
    q = read_quarantine(tmp_path / "q")
    assert len(part) + q.num_rows == summary["transitions_assembled"]  # nothing silently lost
    assert set(q.column("reason").to_pylist()) <= {r["reason"] for r in summary["rejected_episodes"]}
    if damage == "truncate":
        assert list(kept_fail.episode_ids) == list(part.episode_ids)
        with open(bad, "rb") as fh:  # ground truth: the episodes whose end event survived the cut
            ended = [json.loads(m.data)["episode_id"] for _, ch, m in scan_records(fh, {"/episode/event"}, {})
                     if json.loads(m.data)["event"] == "end"]
        assert list(part.episode_ids) == ended
        assert summary["cut_episodes"] == 1 and all(r.startswith("cut") for r in q.column("reason").to_pylist())
        info = mcap_info(bad)  # mcap-info on a cut file: a record scan, saying what was lost
        assert info["scanned"] and "cut at offset" in info["damage"]
        n = info["topics"]["/vehicle/odometry"]["messages"]
        assert 0 < n < 6 * 40 * 5 and info["topics"]["/vehicle/odometry"]["fields"]
    full = ds.select_episodes(part.episode_ids)  # what was kept is exactly the original
    np.testing.assert_allclose(part.arrays().obs, full.arrays().obs, atol=1e-9)
    np.testing.assert_array_equal(part.arrays().action, full.arrays().action)
    if damage == "bitflip":  # exactly the hit chunk is lost, and exactly the episodes it held
        lost_chunks = summary["files"][0]["recovered"]["lost_chunks"]
        assert [c["offset"] for c in lost_chunks] == [lo]
        assert held[hit], "the damaged chunk holds no episode's messages: the test would prove nothing"
        assert set(ds.episode_ids) - set(part.episode_ids) == held[hit]


def test_unindexed_file_without_summary(tmp_path):
    from mcap.writer import IndexType, Writer

    ds = simulate("path_tracking", 2, 0, seed=6, horizon=10)
    (f,) = write_mcap(ds, tmp_path / "logs", encoding="json")
    from mcap.reader import make_reader

    out = tmp_path / "plain.mcap"
    with open(f, "rb") as src, open(out, "wb") as dst:
        w = Writer(dst, index_types=IndexType.NONE, use_summary_offsets=False, use_statistics=False, use_chunking=False)
        w.start()
        seen_s, seen_c = {}, {}
        for sch, ch, msg in make_reader(src).iter_messages(log_time_order=False):
            if sch.id not in seen_s:
                seen_s[sch.id] = w.register_schema(sch.name, sch.encoding, sch.data)
            if ch.id not in seen_c:
                seen_c[ch.id] = w.register_channel(ch.topic, ch.message_encoding, seen_s[sch.id])
            w.add_message(seen_c[ch.id], msg.log_time, msg.data, msg.publish_time)
        w.finish()
    back, _ = ingest_mcap([out], SPEC)
    np.testing.assert_allclose(back.arrays().obs, ds.arrays().obs, atol=1e-9)
