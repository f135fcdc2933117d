"""A heading from a quaternion: ``{ yaw_of = "pose.pose.orientation" }`` in a stream's fields.

A ROS pose carries its orientation as a quaternion, and ``q`` and ``-q`` are one rotation:
recorded as four raw features, the same heading can come with all four signs flipped from
one message to the next. The derived field reads the heading (rad), the same for both.
Oracles: scipy's rotation (a second implementation: the first z-y'-x'' Euler angle), and
logs built here from known headings.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from offline_adp.errors import SpecError
from offline_adp.ingest.mcap import ingest_mcap, parse_mcap_spec
from offline_adp.ingest.mcap.decode import yaw_of
from tests.conftest import SHARED_DATA
from tests.test_ingest_mcap_streaming import write_log

MS = 1_000_000
angles = st.floats(-math.pi, math.pi, allow_nan=False)


@settings(max_examples=300)
@given(yaw=angles, pitch=st.floats(-1.5, 1.5), roll=angles, scale=st.floats(1e-3, 1e3), flip=st.booleans())
def test_yaw_of_is_the_first_euler_angle_of_the_rotation(yaw, pitch, roll, scale, flip):
    q = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat()  # x, y, z, w
    q = q * scale * (-1.0 if flip else 1.0)  # the same rotation: any scale, either sign
    got = yaw_of(dict(zip("xyzw", q.tolist(), strict=True)))
    want = Rotation.from_quat(q / np.linalg.norm(q)).as_euler("ZYX")[0]
    assert abs(math.remainder(got - want, 2 * math.pi)) < 1e-9
    assert abs(math.remainder(got - yaw, 2 * math.pi)) < 1e-9
    assert -math.pi <= got <= math.pi


def test_a_zero_or_broken_quaternion_is_a_missing_value():
    assert math.isnan(yaw_of({"x": 0.0, "y": 0.0, "z": 0.0, "w": 0.0}))
    assert math.isnan(yaw_of({"x": float("nan"), "y": 0.0, "z": 0.0, "w": 1.0}))


def _spec(field):
    return {
        "clock": {"topic": "/odom", "time": "header.stamp"},
        "streams": [{"topic": "/odom", "time": "header.stamp", "max_age": 0.001,
                     "fields": {"yaw": field, "v": "v"}}],
        "action": {"topic": "/odom", "field": "u", "time": "header.stamp", "max_age": 0.001, "type": "discrete",
                   "values": [0, 1]},
        "cost": {"terms": [{"field": "v", "op": "abs"}]},
    }


def test_a_heading_is_read_from_logged_quaternions_whatever_their_sign(tmp_path):
    rng = np.random.default_rng(3)
    headings = np.cumsum(rng.normal(0.0, 0.4, 300))
    msgs = []
    for k, h in enumerate(headings):
        t = 10_000 * MS + k * 50 * MS
        sign = -1.0 if rng.random() < 0.5 else 1.0  # either quaternion of the rotation, as logs hold them
        q = {"x": 0.0, "y": 0.0, "z": sign * math.sin(h / 2), "w": sign * math.cos(h / 2)}
        msgs.append(("/odom", t, {"header": {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9}},
                                  "pose": {"pose": {"orientation": q}}, "v": 1.0, "u": float(k % 2)}))
    f = write_log(tmp_path / "odom.mcap", msgs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds, _ = ingest_mcap([f], parse_mcap_spec(_spec({"yaw_of": "pose.pose.orientation"})))
    feat = {x.name: x for x in ds.info.features}
    assert feat["yaw"].unit == "rad"
    a = ds.arrays()
    got = a.obs[:, [x.name for x in ds.info.features].index("yaw")]
    want = np.array([math.remainder(h, 2 * math.pi) for h in headings[: len(got)]])
    np.testing.assert_allclose(got, want, atol=1e-12)


@pytest.mark.parametrize("bad", [{"yaw_of": 3}, {"heading_of": "pose.pose.orientation"},
                                 {"yaw_of": "a", "also": "b"}, {"yaw_of": "pose..orientation"}])
def test_a_derived_field_is_checked_when_the_spec_is_read(bad):
    with pytest.raises(SpecError, match=r"spec\.streams\[0\]\.fields\.yaw"):
        parse_mcap_spec(_spec(bad))


@pytest.mark.skipif(not (SHARED_DATA / "nav2_turtlebot.mcap").exists(), reason="../shared/data is not present")
def test_real_recording_heading_of_odometry_equals_that_of_its_transform():
    """Nav2: /odom's pose and /tf's odom -> base_link transform are one rotation, written
    as two messages: their headings agree at every step (exact alignment on the stamp)."""
    sel = "transforms[child_frame_id=base_link]"
    spec = _spec({"yaw_of": "pose.pose.orientation"})
    spec["streams"][0]["fields"] = {"yaw": {"yaw_of": "pose.pose.orientation"}, "v": "twist.twist.linear.x"}
    spec["streams"].append({"topic": "/tf", "time": f"{sel}.header.stamp", "max_age": 0.001,
                            "fields": {"tf_yaw": {"yaw_of": f"{sel}.transform.rotation"}}})
    spec["action"] = {"topic": "/odom", "field": "twist.twist.angular.z", "time": "header.stamp", "max_age": 0.001,
                      "type": "continuous", "n_bins": 3}
    spec["episodes"] = {"gap": 2.0}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds, _ = ingest_mcap([SHARED_DATA / "nav2_turtlebot.mcap"], parse_mcap_spec(spec))
    names = [x.name for x in ds.info.features]
    obs = ds.arrays().obs
    yaw, tf_yaw = obs[:, names.index("yaw")], obs[:, names.index("tf_yaw")]
    np.testing.assert_allclose(yaw, tf_yaw, atol=1e-9)
    assert np.all(np.abs(yaw) <= math.pi) and np.ptp(yaw) > 1.0  # the robot turned


def test_linear_alignment_of_a_heading_goes_the_short_way_round(tmp_path):
    """A robot turning at a constant rate through +-pi, its pose logged at 10 Hz, the steps
    at 7 Hz: linear alignment of the heading must give the heading at the step times (from
    3.0 to -3.0 rad it passes pi, not 0). Ground truth: the constant-rate heading."""
    rate, t0 = 0.9, 10_000 * MS  # rad/s, from 2.5 rad: crosses pi after about 0.7 s and again each 7 s
    msgs = []
    for k in range(120):
        t = t0 + k * 100 * MS
        h = 2.5 + rate * (t - t0) / 1e9
        q = {"x": 0.0, "y": 0.0, "z": math.sin(h / 2), "w": math.cos(h / 2)}
        msgs.append(("/odom", t, {"header": {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9}},
                                  "pose": {"pose": {"orientation": q}}}))
    for k in range(80):
        t = t0 + 50 * MS + k * 143 * MS
        msgs.append(("/clock", t, {"v": 1.0, "u": float(k % 2)}))
    msgs.sort(key=lambda m: m[1])
    spec = {
        "clock": {"topic": "/clock"},
        "streams": [{"topic": "/odom", "time": "header.stamp", "align": "linear", "max_age": 0.2,
                     "fields": {"yaw": {"yaw_of": "pose.pose.orientation"}}},
                    {"topic": "/clock", "max_age": 0.001, "fields": {"v": "v"}}],
        "action": {"topic": "/clock", "field": "u", "max_age": 0.001, "type": "discrete", "values": [0, 1]},
        "cost": {"terms": [{"field": "v", "op": "abs"}]},
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds, _ = ingest_mcap([write_log(tmp_path / "turn.mcap", msgs)], parse_mcap_spec(spec))
    a = ds.arrays()
    names = [x.name for x in ds.info.features]
    steps = t0 + 50 * MS + a.step.astype(np.int64) * 143 * MS
    want = np.array([math.remainder(2.5 + rate * (t - t0) / 1e9, 2 * math.pi) for t in steps])
    got = a.obs[:, names.index("yaw")]
    assert np.abs(np.remainder(got - want + math.pi, 2 * math.pi) - math.pi).max() < 1e-9
    assert np.all(np.abs(got) <= math.pi) and (np.abs(want) > 3.0).sum() >= 3  # steps near +-pi were checked


def test_a_heading_of_any_scale_or_with_a_null_part():
    h = 1.5
    for scale in (1e-160, 1e-13, 1.0, 1e160):
        q = {"x": 0.0, "y": 0.0, "z": scale * math.sin(h / 2), "w": scale * math.cos(h / 2)}
        assert abs(yaw_of(q) - h) < 1e-12
    assert math.isnan(yaw_of({"x": None, "y": 0.0, "z": 0.0, "w": 1.0}))  # a JSON null: missing, as a plain field


def test_a_headings_unit_is_rad_and_a_command_list_names_paths():
    spec = _spec({"yaw_of": "pose.pose.orientation"})
    spec["streams"][0]["units"] = {"yaw": "deg"}
    with pytest.raises(SpecError, match=r"units\.yaw: a heading .* is in rad, not 'deg'"):
        parse_mcap_spec(spec)
    spec = _spec("v")
    spec["action"] = {"topic": "/odom", "fields": [{"yaw_of": "q"}], "type": "continuous"}
    with pytest.raises(SpecError, match=r"action\.fields: a list names field paths"):
        parse_mcap_spec(spec)
