"""The same data written as a rosbag2 SQLite bag, a ROS 1 bag (both with the ``rosbags``
writers) and a rosbag2 MCAP bag: ingested with one spec, the datasets are equal."""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp.ingest.mcap import ingest_mcap, parse_mcap_spec

pytest.importorskip("rosbags")
MS = 1_000_000
T0 = 1_700_000_000 * 1_000_000_000
V = [0.0, 0.2, 0.4]
W = [-0.5, 0.0, 0.5]


def _messages(store, ros1=False):
    """A PointStamped state at 10 Hz (x = k) and a Twist command 3 ms later."""
    Point = store.types["geometry_msgs/msg/PointStamped"]
    P = store.types["geometry_msgs/msg/Point"]
    H = store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    Twist = store.types["geometry_msgs/msg/Twist"]
    V3 = store.types["geometry_msgs/msg/Vector3"]
    out = []
    for k in range(40):
        t = T0 + k * 100 * MS
        stamp = Time(sec=t // 10**9, nanosec=t % 10**9)
        header = H(seq=k, stamp=stamp, frame_id="map") if ros1 else H(stamp=stamp, frame_id="map")
        out.append(("/state", "geometry_msgs/msg/PointStamped", t,
                    Point(header=header, point=P(x=float(k), y=0.0, z=0.0))))
        out.append(("/cmd_vel", "geometry_msgs/msg/Twist", t + 3 * MS,
                    Twist(linear=V3(x=V[k % 3], y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=W[(k // 3) % 3]))))
    return out


def _write_rosbag2(path, storage):
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(path, version=9, storage_plugin=storage) as w:
        conns = {}
        for topic, typ, t, msg in _messages(store):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=store)
            w.write(conns[topic], t, store.serialize_cdr(msg, typ))
    return path


def _write_rosbag1(path):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    with Writer(path) as w:
        conns = {}
        for topic, typ, t, msg in _messages(store, ros1=True):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=store)
            w.write(conns[topic], t, store.serialize_ros1(msg, typ))
    return path


SPEC = parse_mcap_spec({
    "clock": {"topic": "/state", "time": "header.stamp"},
    "streams": [{"topic": "/state", "time": "header.stamp", "fields": {"x": "point.x"}, "max_age": 0.001}],
    "action": {"topic": "/cmd_vel", "fields": {"v": "linear.x", "w": "angular.z"}, "max_age": 0.01,
               "vectors": [[v, w] for v in V for w in W]},
    "cost": {"terms": [{"field": "action.v", "op": "square"}]},
})


def test_the_same_data_as_sqlite_ros1_and_mcap_bags_gives_the_same_dataset(tmp_path):
    from rosbags.rosbag2 import StoragePlugin

    sqlite = _write_rosbag2(tmp_path / "sqlite_bag", StoragePlugin.SQLITE3)
    mcap = _write_rosbag2(tmp_path / "mcap_bag", StoragePlugin.MCAP)
    ros1 = _write_rosbag1(tmp_path / "run.bag")
    results = {name: ingest_mcap([p], SPEC) for name, p in (("sqlite", sqlite), ("mcap", mcap), ("ros1", ros1))}
    ref, _ = results["mcap"]
    a = ref.arrays()
    k = np.round(a.obs[:, 0]).astype(int)
    assert len(ref) == 39 and list(k) == list(range(39))  # ground truth first
    np.testing.assert_array_equal(ref.info.action_table.values[a.action],
                                  np.column_stack([np.take(V, k % 3), np.take(W, (k // 3) % 3)]))
    for name in ("sqlite", "ros1"):
        ds, s = results[name]
        b = ds.arrays()
        for f in ("obs", "next_obs", "action", "cost", "terminated", "truncated", "step"):
            np.testing.assert_array_equal(getattr(b, f), getattr(a, f), err_msg=f"{name}: {f}")
        np.testing.assert_array_equal(ds.table.column("t_ns").to_numpy(), ref.table.column("t_ns").to_numpy())
        np.testing.assert_array_equal(ds.table.column("src_log_time").to_numpy(),
                                      ref.table.column("src_log_time").to_numpy())
        assert s["messages_used"] == {"/state": 40, "/cmd_vel": 40}
