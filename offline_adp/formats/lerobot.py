"""The LeRobot dataset layout (export only): :func:`to_lerobot` (see :mod:`offline_adp.formats`)."""

from __future__ import annotations

import json
from os import PathLike
from pathlib import Path

import numpy as np

from offline_adp.data.dataset import TransitionDataset
from offline_adp.formats.common import (
    _columns,
    _episode_bounds,
)
from offline_adp.progress import get_logger

log = get_logger(__name__)


def to_lerobot(ds: TransitionDataset, root: str | PathLike[str], *, fps: float | None = None, task: str | None = None,
               robot_type: str = "unknown", overwrite: bool = False) -> Path:
    """Write ``ds`` in the LeRobot dataset layout (v2.1, no videos) under ``root``.

    ``fps`` defaults to the median step period of ``t_ns`` (else 1); ``task`` to the
    dataset's name. One frame per transition (see module docstring).
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    from offline_adp.data.files import atomic_directory

    c = _columns(ds)
    bounds = _episode_bounds(ds.episode_index)
    n, d = len(ds), len(ds.feature_names)
    ep_index = np.repeat(np.arange(len(bounds) - 1), np.diff(bounds))
    frame = np.arange(n) - bounds[:-1][ep_index]
    if fps is None:
        dt = np.diff(c["t_ns"])[(np.diff(ep_index) == 0)] if c["t_ns"] is not None and n > 1 else np.zeros(0)
        fps = float(1e9 / np.median(dt)) if len(dt) and np.median(dt) > 0 else 1.0
    if c["t_ns"] is not None:
        timestamp = (c["t_ns"] - c["t_ns"][bounds[:-1][ep_index]]) / 1e9
    else:
        timestamp = frame / fps
    at = ds.info.action_table
    exact = ds.commands()  # continuous commands as logged: the action itself, never its coarse bin's value
    values = np.asarray(exact, np.float64) if exact is not None else at.values[c["action"]]
    task = task or ds.info.name or ds.info.problem or "offline_adp dataset"

    def lst(x: np.ndarray) -> pa.Array:
        return pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(x).reshape(-1)), x.shape[1])

    feats = {
        "observation.state": {"dtype": "float64", "shape": [d], "names": list(ds.feature_names),
                              "units": [f.unit for f in ds.info.features]},
        "action": {"dtype": "float64", "shape": [values.shape[1]], "names": list(at.dims), "units": list(at.units)},
        "action_index": {"dtype": "int64", "shape": [1], "names": None},
        "next.observation.state": {"dtype": "float64", "shape": [d], "names": list(ds.feature_names)},
        "next.reward": {"dtype": "float64", "shape": [1], "names": None},
        "next.done": {"dtype": "bool", "shape": [1], "names": None},
        "next.truncated": {"dtype": "bool", "shape": [1], "names": None},
        "timestamp": {"dtype": "float32", "shape": [1], "names": None},
        "frame_index": {"dtype": "int64", "shape": [1], "names": None},
        "episode_index": {"dtype": "int64", "shape": [1], "names": None},
        "index": {"dtype": "int64", "shape": [1], "names": None},
        "task_index": {"dtype": "int64", "shape": [1], "names": None},
    }
    chunks = 1000
    with atomic_directory(root, overwrite=overwrite) as tmp:
        meta = tmp / "meta"
        meta.mkdir()
        lines = []
        for k, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
            sl = slice(lo, hi)
            table = pa.table({
                "observation.state": lst(c["obs"][sl]), "action": lst(values[sl]),
                "action_index": pa.array(c["action"][sl]), "next.observation.state": lst(c["next_obs"][sl]),
                "next.reward": pa.array(-c["cost"][sl]), "next.done": pa.array(c["terminated"][sl]),
                "next.truncated": pa.array(c["truncated"][sl]), "timestamp": pa.array(timestamp[sl].astype(np.float32)),
                "frame_index": pa.array(frame[sl]), "episode_index": pa.array(ep_index[sl]),
                "index": pa.array(np.arange(lo, hi)), "task_index": pa.array(np.zeros(hi - lo, np.int64))})
            f = tmp / "data" / f"chunk-{k // chunks:03d}" / f"episode_{k:06d}.parquet"
            f.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(table, f)
            lines.append(json.dumps({"episode_index": k, "tasks": [task], "length": int(hi - lo),
                                     "episode_id": str(c["episode_id"][lo]), "source": str(c["source"][lo])}))
        (meta / "episodes.jsonl").write_text("\n".join(lines) + ("\n" if lines else ""))
        frames = {"observation.state": c["obs"], "action": values, "action_index": c["action"],
                  "next.observation.state": c["next_obs"], "next.reward": -c["cost"], "next.done": c["terminated"],
                  "next.truncated": c["truncated"], "timestamp": timestamp.astype(np.float32), "frame_index": frame,
                  "episode_index": ep_index, "index": np.arange(n), "task_index": np.zeros(n, np.int64)}
        (meta / "episodes_stats.jsonl").write_text(_episodes_stats(frames, bounds))
        (meta / "tasks.jsonl").write_text(json.dumps({"task_index": 0, "task": task}) + "\n")
        n_ep = len(bounds) - 1
        info = {"codebase_version": "v2.1", "robot_type": robot_type, "total_episodes": n_ep, "total_frames": n,
                "total_tasks": 1, "total_videos": 0, "total_chunks": (n_ep + chunks - 1) // chunks,
                "chunks_size": chunks,
                "fps": fps, "splits": {"train": f"0:{n_ep}"},
                "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet", "video_path": None,
                "features": feats, "offline_adp": json.loads(ds.info.to_json())}
        (meta / "info.json").write_text(json.dumps(info, indent=1))
    log.info("wrote LeRobot-layout dataset %s: %d episodes, %d frames", root, n_ep, n)
    return Path(root)


def _episodes_stats(frames: dict[str, np.ndarray], bounds: np.ndarray) -> str:
    """``meta/episodes_stats.jsonl`` of LeRobot v2.1: per episode, per feature, ``min``,
    ``max``, ``mean``, ``std`` (population) per component and ``count`` (frames), from
    the frames as written (a scalar feature has one component), all episodes at once."""
    starts = bounds[:-1]
    n_ep = len(starts)
    if n_ep == 0:
        return ""
    lengths = np.diff(bounds).astype(np.int64)
    ep = np.repeat(np.arange(n_ep), lengths)
    stats: dict[str, dict[str, np.ndarray]] = {}
    for name, x in frames.items():
        a = np.asarray(x, dtype=np.float64).reshape(len(x), -1)
        mean = np.add.reduceat(a, starts, axis=0) / lengths[:, None]
        var = np.add.reduceat((a - mean[ep]) ** 2, starts, axis=0) / lengths[:, None]
        stats[name] = {"min": np.minimum.reduceat(a, starts, axis=0), "max": np.maximum.reduceat(a, starts, axis=0),
                       "mean": mean, "std": np.sqrt(var)}
    lines = []
    for k in range(n_ep):  # one line per episode (the output's size)
        per = {name: {**{s: v[k].tolist() for s, v in st.items()}, "count": [int(lengths[k])]}
               for name, st in stats.items()}
        lines.append(json.dumps({"episode_index": k, "stats": per}))
    return "\n".join(lines) + "\n"
