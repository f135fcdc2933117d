"""`mcap-info` describes every readable file: rosbag2 service-event channels (a schema the
ROS 2 decoder cannot parse) are listed with the reason and the rest is described; a
corrupt chunk is shown as damage; protobuf fields by their real paths; rates as the median
period per epoch with restarts and gaps counted; 1-message and empty topics. Every file is
written here; expected values are known by construction."""

from __future__ import annotations

import json

import pytest

from offline_adp.cli import main
from offline_adp.ingest.mcap import mcap_info

MS = 1_000_000


def _ros2_bag_with_service_events(path):
    """What `ros2 bag record` writes for a topic and a service with introspection on:
    /odom (nav_msgs-like, CDR) and /add_two_ints/_service_event, whose schema is the
    service definition (request --- response), as rosbag2 stores it."""
    from mcap_ros2.writer import Writer as Ros2Writer

    with open(path, "wb") as f:
        w = Ros2Writer(f)
        odom = w.register_msgdef("my_msgs/msg/Odom", "float64 x\nfloat64 v\n")
        for k in range(50):
            w.write_message("/odom", odom, {"x": 0.1 * k, "v": 1.0}, log_time=k * 20 * MS, publish_time=k * 20 * MS)
        # a service-event channel: its schema text has '---' separators, which mcap_ros2 cannot parse
        mcap_w = w._writer  # the underlying mcap writer
        sid = mcap_w.register_schema("example_interfaces/srv/AddTwoInts_Event", "ros2msg",
                                     b"service_msgs/ServiceEventInfo info\nint64 a\nint64 b\n---\nint64 sum\n")
        cid = mcap_w.register_channel("/add_two_ints/_service_event", "cdr", sid)
        for k in range(3):
            mcap_w.add_message(cid, log_time=k * 300 * MS, data=b"\x00\x01\x00\x00" + bytes(24),
                               publish_time=k * 300 * MS)
        w.finish()
    return path


def test_a_rosbag2_bag_with_service_events_is_described(tmp_path, capsys):
    pytest.importorskip("mcap_ros2")
    f = _ros2_bag_with_service_events(tmp_path / "bag_0.mcap")
    info = mcap_info(f)
    odom = info["topics"]["/odom"]
    assert odom["messages"] == 50 and odom["rate_hz"] == pytest.approx(50.0) and odom["status"] == "ok"
    assert odom["fields"] == ["x", "v"] and odom["field_info"][0]["type"] == "float"
    svc = info["topics"]["/add_two_ints/_service_event"]
    assert svc["messages"] == 3 and svc["status"].startswith("not decodable")
    assert "/add_two_ints/_service_event" in svc["status"] and "AddTwoInts_Event" in svc["status"]
    assert main(["mcap-info", str(f)]) == 0
    out = capsys.readouterr().out
    assert "/odom" in out and "not decodable" in out


def test_a_file_with_one_corrupt_chunk_is_described_with_its_damage(tmp_path, capsys):
    from tests.test_mcap_damage import _chunk_episodes
    from tests.test_mcap_epochs import rl_log, write_log

    src = write_log(tmp_path / "rl.mcap", rl_log(n_episodes=4, k_absent=0, n_steps=300))
    data = bytearray(src.read_bytes())
    off, n, _ = _chunk_episodes(bytes(data))[3]
    data[off + 9 + n - 40] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    info = mcap_info(bad)
    assert "lost 1 corrupt chunk" in info["damage"] and str(off) in info["damage"]
    st = info["topics"]["/state"]
    assert 0 < st["messages"] < 4 * 300
    # 200 Hz, time restarting every episode: the median period per epoch, restarts counted
    assert st["rate_hz"] == pytest.approx(200.0) and st["restarts"] == 3
    assert main(["mcap-info", str(bad)]) == 0
    assert "DAMAGE" in capsys.readouterr().out


def _json_log(path, topics):
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        for topic, msgs in topics.items():
            cid = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
            for t, m in msgs:
                w.add_message(cid, log_time=t, publish_time=t, data=json.dumps(m).encode())
        w.finish()
    return path


def test_rates_with_gaps_single_messages_and_empty_topics(tmp_path):
    ten_hz = [(k * 100 * MS, {"a": {"b": [k, 2]}}) for k in range(20)]
    ten_hz += [(10_000 * MS + k * 100 * MS, {"a": {"b": [k, 2]}}) for k in range(20)]  # 8 s gap, then again
    f = _json_log(tmp_path / "g.mcap", {"/ten": ten_hz, "/once": [(5 * MS, {"s": "hello"})], "/never": []})
    info = mcap_info(f)
    ten = info["topics"]["/ten"]
    assert ten["rate_hz"] == pytest.approx(10.0) and ten["gaps"] == 1 and ten["restarts"] == 0
    assert ten["fields"] == ["a.b[0]"] and ten["field_info"][0]["sample"] == 0
    once = info["topics"]["/once"]
    assert once["messages"] == 1 and once["rate_hz"] is None and once["status"] == "1 message"
    assert once["field_info"] == [{"path": "s", "type": "string", "sample": "hello"}]
    never = info["topics"]["/never"]
    assert never["messages"] == 0 and never["status"] == "empty" and never["fields"] is None


def test_protobuf_fields_by_their_real_paths(tmp_path):
    pytest.importorskip("mcap_protobuf")
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap_protobuf.writer import Writer

    fd = descriptor_pb2.FileDescriptorProto(name="r.proto", package="r")
    v = fd.message_type.add(name="Vec")
    v.field.add(name="x", number=1, type=descriptor_pb2.FieldDescriptorProto.TYPE_DOUBLE)
    s = fd.message_type.add(name="State")
    s.field.add(name="pos", number=1, type=descriptor_pb2.FieldDescriptorProto.TYPE_MESSAGE, type_name=".r.Vec")
    s.field.add(name="u", number=2, type=descriptor_pb2.FieldDescriptorProto.TYPE_DOUBLE,
                label=descriptor_pb2.FieldDescriptorProto.LABEL_REPEATED)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fd)
    State = message_factory.GetMessageClass(pool.FindMessageTypeByName("r.State"))
    Vec = message_factory.GetMessageClass(pool.FindMessageTypeByName("r.Vec"))
    path = tmp_path / "pb.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        for k in range(5):
            w.write_message("/state", State(pos=Vec(x=0.5 * k), u=[1.0, 2.0]), log_time=k * 100 * MS,
                            publish_time=k * 100 * MS)
        w.finish()
    t = mcap_info(path)["topics"]["/state"]
    assert t["fields"] == ["pos.x", "u[0]"] and "DESCRIPTOR" not in str(t["fields"])
    assert t["field_info"][1]["sample"] == 1.0


def test_an_empty_file_says_empty(tmp_path):
    (tmp_path / "e.mcap").write_bytes(b"")
    info = mcap_info(tmp_path / "e.mcap")
    assert info["damage"] == "empty file (0 bytes)" and info["topics"] == {}
