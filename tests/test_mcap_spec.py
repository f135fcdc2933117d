"""MCAP spec features: vector actions from several fields (a Twist's linear.x and
angular.z), sec/nanosec and protobuf Timestamp time fields, units per feature, MCAP key
errors. Fixtures encode their own expected values."""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp.errors import SpecError
from offline_adp.ingest.mcap import ingest_mcap, parse_mcap_spec
from tests.test_ingest_mcap_streaming import MS, T0, write_log

V = [0.0, 0.2, 0.4]
W = [-0.5, 0.0, 0.5]


def _twist_log(tmp_path, n=60, jitter=0.0):
    """A state at 10 Hz with x = k; a Twist command (linear.x, angular.z) 3 ms later with
    v = V[k % 3] (+ jitter) and w = W[(k // 3) % 3]; stamps as {sec, nanosec}."""
    rng = np.random.default_rng(0)
    msgs = []
    for k in range(n):
        t = T0 + k * 100 * MS
        stamp = {"sec": t // 1_000_000_000, "nanosec": t % 1_000_000_000}
        msgs.append(("/state", t + 7 * MS, {"header": {"stamp": stamp}, "x": float(k)}))  # logged 7 ms late
        v, w = V[k % 3] + jitter * rng.uniform(-0.05, 0.05), W[(k // 3) % 3] + jitter * rng.uniform(-0.1, 0.1)
        msgs.append(("/cmd_vel", t + 3 * MS, {"linear": {"x": v, "y": 0.0}, "angular": {"z": w}}))
    return write_log(tmp_path / "twist.mcap", msgs)


def _spec(action, **stream):
    return parse_mcap_spec({
        "clock": {"topic": "/state", "time": "header.stamp"},
        "streams": [{"topic": "/state", "time": "header.stamp", "fields": {"x": "x"}, "max_age": 0.001, **stream}],
        "action": {"topic": "/cmd_vel", "max_age": 0.01, **action},
        "cost": {"terms": [{"field": "action.v", "op": "square"}, {"field": "x", "op": "abs", "weight": 0.0}]},
    })


def test_a_discrete_vector_action_from_two_fields(tmp_path):
    f = _twist_log(tmp_path)
    vectors = [[v, w] for v in V for w in W]
    ds, _ = ingest_mcap([f], _spec({"fields": {"v": "linear.x", "w": "angular.z"}, "vectors": vectors}))
    a = ds.arrays()
    k = np.round(a.obs[:, 0]).astype(int)  # the state's own time stamp, not its log_time, is the step time
    np.testing.assert_array_equal(ds.table.column("t_ns").to_numpy(), T0 + k * 100 * MS)
    table = ds.info.action_table
    assert table.dims == ("v", "w") and len(table) == 9
    np.testing.assert_allclose(table.values[a.action], np.column_stack([np.take(V, k % 3), np.take(W, (k // 3) % 3)]))
    np.testing.assert_allclose(a.cost, np.take(V, k % 3) ** 2)  # cost term on one component


def test_a_continuous_vector_action_is_binned_into_a_product_table(tmp_path):
    f = _twist_log(tmp_path, jitter=1.0)
    edges = {"v": [-1.0, 0.1, 0.3, 1.0], "w": [-1.0, -0.25, 0.25, 1.0]}
    ds, _ = ingest_mcap([f], _spec({"fields": {"v": "linear.x", "w": "angular.z"}, "type": "continuous",
                                    "edges": edges, "unit": "SI"}))
    a = ds.arrays()
    k = np.round(a.obs[:, 0]).astype(int)
    np.testing.assert_array_equal(a.action, (k % 3) * 3 + (k // 3) % 3)  # row-major over (v bin, w bin)
    table = ds.info.action_table
    assert table.kind == "binned" and len(table) == 9 and table.units == ("SI", "SI")
    for cell in range(9):  # each cell's value: the mean command in it, per component
        rows = a.action == cell
        assert abs(table.values[cell, 0] - V[cell // 3]) < 0.05 and abs(table.values[cell, 1] - W[cell % 3]) < 0.1
        assert rows.any()


def test_protobuf_timestamp_time_field_and_units(tmp_path):
    pytest.importorskip("mcap_protobuf")
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory, timestamp_pb2
    from mcap_protobuf.writer import Writer

    pool = descriptor_pool.DescriptorPool()
    ts_fd = descriptor_pb2.FileDescriptorProto()
    timestamp_pb2.DESCRIPTOR.CopyToProto(ts_fd)
    pool.Add(ts_fd)
    fd = descriptor_pb2.FileDescriptorProto(name="s.proto", package="s", dependency=["google/protobuf/timestamp.proto"])
    m = fd.message_type.add(name="State")
    m.field.add(name="stamp", number=1, type=descriptor_pb2.FieldDescriptorProto.TYPE_MESSAGE,
                type_name=".google.protobuf.Timestamp")
    m.field.add(name="x", number=2, type=descriptor_pb2.FieldDescriptorProto.TYPE_DOUBLE)
    m.field.add(name="u", number=3, type=descriptor_pb2.FieldDescriptorProto.TYPE_DOUBLE)
    pool.Add(fd)
    State = message_factory.GetMessageClass(pool.FindMessageTypeByName("s.State"))
    Ts = message_factory.GetMessageClass(pool.FindMessageTypeByName("google.protobuf.Timestamp"))
    path = tmp_path / "pb.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        for k in range(10):
            t = T0 + k * 100 * MS
            msg = State(stamp=Ts(seconds=t // 10**9, nanos=t % 10**9), x=0.5 * k, u=float(k % 2))
            w.write_message("/state", msg, log_time=t + 40 * MS, publish_time=t + 40 * MS)  # logged 40 ms late
        w.finish()
    sp = parse_mcap_spec({
        "clock": {"topic": "/state", "time": "stamp"},
        "streams": [{"topic": "/state", "time": "stamp", "fields": {"x": "x"}, "units": {"x": "m"}, "max_age": 0.001}],
        "action": {"topic": "/state", "time": "stamp", "field": "u", "max_age": 0.001, "type": "discrete",
                   "values": [0.0, 1.0]},
        "cost": {"terms": [{"field": "x", "op": "abs"}]},
    })
    ds, _ = ingest_mcap([path], sp)
    np.testing.assert_array_equal(ds.table.column("t_ns").to_numpy(), T0 + np.arange(9) * 100 * MS)
    assert ds.info.features[0].unit == "m"
    np.testing.assert_array_equal(ds.arrays().action, np.arange(9) % 2)


def test_key_errors_list_the_mcap_keys():
    with pytest.raises(SpecError, match=r"action: unknown key\(s\) \['column'\]; valid keys are .*'fields'.*'topic'"):
        _spec({"column": "u", "field": "linear.x", "type": "discrete", "values": [0.0]})
    with pytest.raises(SpecError, match="either 'field' .* or 'fields'"):
        _spec({"type": "discrete", "values": [0.0]})
    with pytest.raises(SpecError, match=r"vectors: a discrete vector action needs vectors"):
        _spec({"fields": {"v": "linear.x", "w": "angular.z"}})
    with pytest.raises(SpecError, match=r"units: \['y'\] are not fields of this stream"):
        _spec({"field": "linear.x", "values": [0.0]}, units={"y": "m"})
