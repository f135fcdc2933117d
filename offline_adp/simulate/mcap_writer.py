"""Simulated logs as MCAP files, the way a vehicle or robot would record them.

Two layouts:

- ``generic`` (any problem, JSON): ``/observation`` (one field per feature, at each
  step including the final state), ``/action`` (index, name and value, 5 ms after the
  observation), ``/cost`` (at the next step's time) and ``/episode`` events
  (``start``/``end`` with ``terminated`` and ``source``).
- ``vehicle`` (``path_tracking``, JSON or ROS 2 CDR with embedded ``.msg``
  definitions): ``/vehicle/odometry`` at 50 Hz (pose, speed, steering angle, from the
  simulator's sub-steps), ``/planning/tracking_state`` at 10 Hz (progress, cross-track
  and heading error, curvature here and ahead), ``/control/steering_cmd`` at 10 Hz
  (published 8 +/- 2 ms after the tracking state, the controller's latency) and
  ``/episode/event``. Header stamps are simulation time; ``log_time`` adds 1-3 ms of
  transport delay; each episode is separated from the previous one by a 5 s gap.

One file per ``source`` label (``demonstration.mcap``, ``exploration.mcap``), zstd
chunks, indexed. The costs of the vehicle layout are not logged (a real car does not
log a cost): they are recomputed at ingestion from cross-track error and command.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from os import PathLike
from pathlib import Path

import numpy as np

from offline_adp.data import schema as S
from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import InvalidArgumentError

HEADER_DEFS = """================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""

MSGDEFS = {
    "offline_adp_msgs/msg/VehicleOdometry": (
        "std_msgs/Header header\nfloat64 x\nfloat64 y\nfloat64 yaw\nfloat64 speed\nfloat64 steering_angle\n"
    ),
    "offline_adp_msgs/msg/TrackingState": (
        "std_msgs/Header header\nfloat64 progress\nfloat64 cross_track_error\nfloat64 heading_error\n"
        "float64 curvature\nfloat64 curvature_ahead\n"
    ),
    "offline_adp_msgs/msg/SteeringCommand": "std_msgs/Header header\nfloat64 steering_angle\n",
    "offline_adp_msgs/msg/EpisodeEvent": "std_msgs/Header header\nstring episode_id\nstring event\nstring source\nbool "
    "terminated\n",
}
TOPIC_TYPES = {
    "/vehicle/odometry": "offline_adp_msgs/msg/VehicleOdometry",
    "/planning/tracking_state": "offline_adp_msgs/msg/TrackingState",
    "/control/steering_cmd": "offline_adp_msgs/msg/SteeringCommand",
    "/episode/event": "offline_adp_msgs/msg/EpisodeEvent",
}


def _header(t_ns: int, frame: str = "map") -> dict:
    return {"stamp": {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}, "frame_id": frame}


class _Sink:
    """Writes (topic, dict, log_time, publish_time) as JSON or ROS 2 CDR."""

    def __init__(self, path: Path, encoding: str, chunk_size: int = 1 << 20) -> None:
        self.encoding = encoding
        self.f = open(path, "wb")
        if encoding == "ros2":
            from mcap_ros2.writer import Writer as Ros2Writer

            self.w = Ros2Writer(self.f, chunk_size=chunk_size)
            self.schemas = {name: self.w.register_msgdef(name, d + HEADER_DEFS) for name, d in MSGDEFS.items()}
        else:
            from mcap.writer import Writer

            self.w = Writer(self.f, chunk_size=chunk_size)
            self.w.start(profile="", library="offline_adp simulate")
            self.channels: dict[str, int] = {}

    def write(self, topic: str, msg: dict, log_time: int, publish_time: int, schema: str = "") -> None:
        if self.encoding == "ros2":
            self.w.write_message(topic, self.schemas[TOPIC_TYPES[topic]], msg, log_time=log_time,
                                 publish_time=publish_time)
            return
        if topic not in self.channels:
            name = schema or topic.strip("/").replace("/", "_")
            props = {k: {"type": "object"} if isinstance(v, dict) else {"type": _json_type(v)} for k, v in msg.items()}
            sid = self.w.register_schema(name=name, encoding="jsonschema",
                                         data=json.dumps({"type": "object", "properties": props}).encode())
            self.channels[topic] = self.w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        self.w.add_message(self.channels[topic], log_time=log_time, data=json.dumps(msg).encode(),
                           publish_time=publish_time)

    def close(self) -> None:
        self.w.finish()
        self.f.close()


def _json_type(v: object) -> str:
    return {bool: "boolean", int: "integer", float: "number", str: "string"}.get(type(v), "string")


def _episodes(ds: TransitionDataset) -> Iterator[tuple[str, str, dict[str, np.ndarray]]]:
    a = ds.arrays()
    src = ds.column(S.SOURCE)
    t_ns = ds.table.column(S.T_NS).to_numpy() if S.T_NS in ds.table.column_names else None
    for lo, hi in zip(a.episode_starts, np.r_[a.episode_starts[1:], len(a)], strict=True):
        sl = slice(lo, hi)
        yield (
            str(ds.episode_ids[a.episode[lo]]),
            str(src[lo]),
            {
                "obs": a.obs[sl],
                "next_obs": a.next_obs[sl],
                "action": a.action[sl],
                "cost": a.cost[sl],
                "terminated": a.terminated[sl],
                "t_ns": t_ns[sl] if t_ns is not None else 1_704_067_200_000_000_000 + np.arange(hi - lo) * 100_000_000,
            },
        )


def write_mcap(
    ds: TransitionDataset,
    out_dir: str | PathLike[str],
    *,
    encoding: str = "json",
    layout: str = "auto",
    seed: int = 0,
    chunk_size: int = 1 << 20,
) -> list[Path]:
    """Write ``ds`` as MCAP files (one per source) into ``out_dir``; returns their paths.

    Parameters
    ----------
    encoding : {"json", "ros2"}
        Message encoding; ``ros2`` needs the ``vehicle`` layout.
    layout : {"auto", "generic", "vehicle"}
        ``auto`` takes the problem's ``mcap_layout`` (``vehicle`` for ``path_tracking``), else ``generic``.
    seed : int
        Seed of the timing jitter (latencies).
    chunk_size : int
        Bytes per (zstd) chunk before compression.
    """
    if encoding not in ("json", "ros2"):
        raise InvalidArgumentError(f"MCAP encoding must be 'json' or 'ros2', got {encoding!r}")
    if layout == "auto":
        from offline_adp.envs import PROBLEM_NAMES, problem_class

        layout = problem_class(ds.info.problem).mcap_layout if ds.info.problem in PROBLEM_NAMES else "generic"
    if encoding == "ros2" and layout != "vehicle":
        raise InvalidArgumentError("ROS 2 encoding is written for the vehicle layout (path_tracking data) only")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    sinks: dict[str, _Sink] = {}
    tmp_paths: dict[str, Path] = {}
    problem = None
    if layout == "vehicle":
        from offline_adp.envs.path_tracking import PathTracking

        problem = PathTracking()
    done = False
    try:
        for ep_id, source, e in _episodes(ds):
            if source not in sinks:
                tmp_paths[source] = out / f".{source}.mcap.tmp"
                sinks[source] = _Sink(tmp_paths[source], encoding, chunk_size)
            sink = sinks[source]
            if layout == "vehicle":
                _write_vehicle_episode(sink, problem, ep_id, source, e, rng)
            else:
                _write_generic_episode(sink, ds, ep_id, source, e)
        for s in sinks.values():
            s.close()
        paths = []
        for source, tmp in tmp_paths.items():
            final = out / f"{source}.mcap"
            tmp.replace(final)
            paths.append(final)
        done = True
    finally:
        if not done:  # a failed write (full disk, read-only folder): no temporary left behind
            for s in sinks.values():
                with contextlib.suppress(OSError):
                    s.f.close()
            for tmp in tmp_paths.values():
                tmp.unlink(missing_ok=True)
    return sorted(paths)


def _write_generic_episode(sink: _Sink, ds: TransitionDataset, ep_id: str, source: str, e: dict) -> None:
    names = ds.feature_names
    at = ds.info.action_table
    t = e["t_ns"]
    dt = int(np.median(np.diff(t))) if len(t) > 1 else 100_000_000
    ev = {"episode_id": ep_id, "event": "start", "source": source, "terminated": False}
    sink.write("/episode", ev, int(t[0]) - 1_000_000, int(t[0]) - 1_000_000)
    for k in range(len(t)):
        ts = int(t[k])
        sink.write("/observation", {"step": k, **{n: float(v) for n, v in zip(names, e["obs"][k], strict=True)}}, ts,
                   ts)
        a = int(e["action"][k])
        sink.write("/action", {"index": a, "name": at.names[a], "value": [float(v) for v in at.values[a]]},
                   ts + 5_000_000, ts + 5_000_000)
        sink.write("/cost", {"cost": float(e["cost"][k])}, ts + dt, ts + dt)
    tend = int(t[-1]) + dt
    sink.write("/observation", {"step": len(t), **{n: float(v) for n, v in zip(names, e["next_obs"][-1], strict=True)}},
               tend, tend)
    ev = {"episode_id": ep_id, "event": "end", "source": source, "terminated": bool(e["terminated"][-1])}
    sink.write("/episode", ev, tend + 1_000_000, tend + 1_000_000)


def _write_vehicle_episode(sink: _Sink, problem, ep_id: str, source: str, e: dict, rng: np.random.Generator) -> None:
    from offline_adp.envs.path_tracking import N_SUB, STEERING_COMMANDS

    t = e["t_ns"]
    dt_sub = 100_000_000 // N_SUB
    obs = np.vstack([e["obs"], e["next_obs"][-1:]])  # states at steps 0..T
    T = len(e["action"])
    t_all = np.r_[t, t[-1] + 100_000_000]

    # odometry at 50 Hz: the logged states plus sub-step states re-integrated without noise
    # and corrected linearly to the logged next state, so every step's pose is exact
    _, sub = problem.integrate(obs[:T], e["action"], seed=0, substeps=True)  # (N_SUB, T, 5)
    err = obs[1:, :5] - sub[-1]
    L = problem.course.length
    err[:, 0] = (err[:, 0] + L / 2) % L - L / 2
    frac = (np.arange(1, N_SUB) / N_SUB)[:, None, None]
    inner = sub[:-1] + frac * err[None]  # (N_SUB - 1, T, 5)
    odo = np.concatenate([obs[:T, None, :5], inner.transpose(1, 0, 2)], axis=1).reshape(-1, 5)
    odo = np.vstack([odo, obs[T:, :5]])
    odo_t = (t_all[:T, None] + np.arange(N_SUB)[None, :] * dt_sub).reshape(-1)
    odo_t = np.r_[odo_t, t_all[T]]
    px, py, yaw = problem.course.pose(odo[:, 0], odo[:, 1], odo[:, 2])

    ev = {"header": _header(int(t[0]) - 1_000_000), "episode_id": ep_id, "event": "start", "source": source,
          "terminated": False}
    sink.write("/episode/event", ev, int(t[0]) - 1_000_000, int(t[0]) - 1_000_000)
    lat = rng.integers(1_000_000, 3_000_001, size=len(odo_t) + 2 * (T + 1))
    cmd_delay = rng.integers(6_000_000, 10_000_001, size=T)
    for k in range(T + 1):
        ts = int(t_all[k])
        o = obs[k]
        msg = {"header": _header(ts), "progress": float(o[0]), "cross_track_error": float(o[1]),
               "heading_error": float(o[2]), "curvature": float(o[5]), "curvature_ahead": float(o[6])}
        sink.write("/planning/tracking_state", msg, ts + int(lat[-1 - k]), ts)
        for j in range(k * N_SUB, min((k + 1) * N_SUB, len(odo_t))):
            tj = int(odo_t[j])
            msg = {"header": _header(tj), "x": float(px[j]), "y": float(py[j]), "yaw": float(yaw[j]),
                   "speed": float(odo[j, 4]), "steering_angle": float(odo[j, 3])}
            sink.write("/vehicle/odometry", msg, tj + int(lat[j]), tj)
        if k < T:
            tc = ts + int(cmd_delay[k])
            sink.write("/control/steering_cmd", {"header": _header(tc),
                                                 "steering_angle": float(STEERING_COMMANDS[e["action"][k]])},
                                                 tc + int(lat[len(odo_t) + k]), tc)
    tend = int(t_all[T])
    ev = {"header": _header(tend + 1_000_000), "episode_id": ep_id, "event": "end", "source": source,
          "terminated": bool(e["terminated"][-1])}
    sink.write("/episode/event", ev, tend + 1_000_000, tend + 1_000_000)
