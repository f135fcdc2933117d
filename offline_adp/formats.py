"""Offline-RL dataset formats: D4RL-style arrays, Minari datasets, LeRobot layout.

Our datasets are transitions with named features, a declared action table and costs;
these formats are flat arrays (D4RL), episodes of ``T + 1`` observations (Minari) or
frames (LeRobot). The conversions keep every transition exactly (float64 throughout,
``reward = -cost`` and back, which is exact in floating point) and carry our metadata
(feature names and units, the action table, episode ids, steps, sources, logged
propensities) in the places each format has for it, so an export followed by an
import gives the same dataset.

D4RL arrays (:func:`to_d4rl`, :func:`save_d4rl`, :func:`from_d4rl`)
    ``observations``, ``next_observations``, ``actions`` (the action *values*, (n, k)),
    ``rewards``, ``terminals``, ``timeouts`` (= our ``truncated``) and ``infos/...``
    (``action_index``, ``episode_id``, ``step``, ``source``, ``behavior_prob``,
    ``t_ns``), plus ``metadata/offline_adp`` (the dataset's ``info.json``) in an
    ``.npz`` file (no pickle). Episode boundaries come from ``infos/episode_id``, else
    from ``terminals | timeouts``; without ``next_observations`` the next row of the
    same episode is the next state and an episode's last row (no successor) is dropped,
    as in D4RL's ``qlearning_dataset``.
Minari (:func:`to_minari`, :func:`from_minari`)
    One Minari episode per episode: ``observations`` ``(T + 1, d)`` (the last is the
    final next state; episodes must be contiguous, ``next_obs[t] == obs[t + 1]``),
    ``actions`` (``Discrete`` indices), ``rewards``, ``terminations``, ``truncations``,
    ``infos`` (``episode_id``, ``step``, ``source``, ``behavior_prob``). Written with
    Minari's arrow storage under ``MINARI_DATASETS_PATH`` (or ``datasets_path``); our
    ``info.json`` is in the dataset metadata under ``offline_adp``. Nothing is
    downloaded: reading takes a local dataset (id, path or ``MinariDataset``).
LeRobot layout (:func:`to_lerobot`)
    ``meta/info.json`` (codebase v2.1 layout: features with names and shapes, fps,
    path templates), ``meta/episodes.jsonl``, ``meta/tasks.jsonl`` and
    ``data/chunk-000/episode_000000.parquet`` with one frame per transition:
    ``observation.state``, ``action`` (values), ``action_index``, ``next.reward``,
    ``next.done`` (terminated), ``next.truncated``, ``next.observation.state``,
    ``timestamp``, ``frame_index``, ``episode_index``, ``index``, ``task_index``.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Mapping
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.errors import IngestError, OfflineADPError
from offline_adp.progress import get_logger

log = get_logger(__name__)

META_KEY = "metadata/offline_adp"


# ----------------------------------------------------------------------------- helpers
def _columns(ds: TransitionDataset) -> dict[str, Any]:
    a = ds.arrays()
    out = {"obs": a.obs, "next_obs": a.next_obs, "action": a.action.astype(np.int64), "cost": a.cost,
           "terminated": a.terminated.astype(bool), "truncated": a.truncated.astype(bool), "step": a.step.astype(np.int64),
           "episode_id": ds.column("episode_id").astype(str), "source": ds.column("source").astype(str),
           "behavior_prob": a.behavior_prob}
    out["t_ns"] = ds.column("t_ns").astype(np.int64) if "t_ns" in ds.table.column_names else None
    return out


def _action_indices(values: np.ndarray, table: ActionTable, where: str) -> np.ndarray:
    """Index of each action value row in the table (exact match), else IngestError."""
    vals = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
    tv = table.values
    if vals.shape[1] != tv.shape[1]:
        raise IngestError(f"{where}: actions have {vals.shape[1]} components, the action table {tv.shape[1]} {list(table.dims)}")
    eq = (vals[:, None, :] == tv[None, :, :]).all(axis=2)
    found = eq.any(axis=1)
    if not found.all():
        i = int(np.flatnonzero(~found)[0])
        raise IngestError(f"{where}: row {i}: action {vals[i].tolist()} is not in the action table {tv.tolist()} "
                          f"({int((~found).sum())} rows); pass action_table=, or bin continuous actions with an ingestion spec")
    return eq.argmax(axis=1)


def _default_info(d: int, table: ActionTable, feature_names: list[str] | None, name: str) -> DatasetInfo:
    names = feature_names or [f"x{j}" for j in range(d)]
    if len(names) != d:
        raise IngestError(f"{name}: {len(names)} feature names for {d} observation columns")
    return DatasetInfo(features=tuple(Feature(n) for n in names), action_table=table, name=name)


def _table_from_values(values: np.ndarray) -> ActionTable:
    vals = np.unique(np.asarray(values, np.float64).reshape(len(values), -1), axis=0)
    dims = ("a",) if vals.shape[1] == 1 else tuple(f"a{j}" for j in range(vals.shape[1]))
    return ActionTable.from_values(vals, dims=dims)


# ----------------------------------------------------------------------------- D4RL
def to_d4rl(ds: TransitionDataset) -> dict[str, np.ndarray]:
    """D4RL-style arrays of a dataset (see module docstring)."""
    c = _columns(ds)
    out = {
        "observations": c["obs"],
        "next_observations": c["next_obs"],
        "actions": ds.info.action_table.values[c["action"]],
        "rewards": -c["cost"],
        "terminals": c["terminated"],
        "timeouts": c["truncated"],
        "infos/action_index": c["action"],
        "infos/episode_id": c["episode_id"].astype(str),
        "infos/step": c["step"],
        "infos/source": c["source"].astype(str),
        META_KEY: np.array(ds.info.to_json()),
    }
    if c["behavior_prob"] is not None:
        out["infos/behavior_prob"] = c["behavior_prob"]
    if c["t_ns"] is not None:
        out["infos/t_ns"] = c["t_ns"]
    return out


def save_d4rl(ds: TransitionDataset, path: str | PathLike[str]) -> Path:
    """Write :func:`to_d4rl` arrays to an ``.npz`` file (atomically; loads without pickle)."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp.npz")
    np.savez(tmp, **to_d4rl(ds))
    os.replace(tmp, out)
    log.info("wrote %s: %d transitions (D4RL arrays)", out, len(ds))
    return out


def from_d4rl(data: Mapping[str, Any] | str | PathLike[str], info: DatasetInfo | None = None, *,
              feature_names: list[str] | None = None, action_table: ActionTable | None = None,
              name: str = "d4rl") -> TransitionDataset:
    """A dataset from D4RL-style arrays (a mapping or an ``.npz`` file).

    Metadata comes from ``info``, else the arrays' ``metadata/offline_adp``, else
    ``feature_names`` (default ``x0, x1, ...``) and ``action_table`` (default: the
    distinct action rows). Actions are matched exactly to the action table unless
    ``infos/action_index`` is given.
    """
    where = str(data) if isinstance(data, str | PathLike) else name
    if isinstance(data, str | PathLike):
        try:
            with np.load(data, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError) as exc:
            raise IngestError(f"{data}: not a readable .npz of D4RL arrays ({exc})") from exc
    else:
        arrays = dict(data)
    missing = [k for k in ("observations", "actions", "rewards", "terminals") if k not in arrays]
    if missing:
        raise IngestError(f"{where}: missing D4RL arrays {missing}; found {sorted(arrays)}")
    obs = np.asarray(arrays["observations"], np.float64)
    obs = obs.reshape(len(obs), -1)
    n = len(obs)
    for k in ("actions", "rewards", "terminals", "timeouts", "next_observations"):
        if k in arrays and len(arrays[k]) != n:
            raise IngestError(f"{where}: {k} has {len(arrays[k])} rows, observations {n}")
    if info is None and META_KEY in arrays:
        info = DatasetInfo.from_dict(json.loads(str(arrays[META_KEY])), where=f"{where}:{META_KEY}")
    if info is None:
        table = action_table or _table_from_values(np.asarray(arrays["actions"]))
        info = _default_info(obs.shape[1], table, feature_names, name)
    if "infos/action_index" in arrays:
        action = np.asarray(arrays["infos/action_index"], np.int64)
    else:
        action = _action_indices(np.asarray(arrays["actions"]), info.action_table, where)
    term = np.asarray(arrays["terminals"]).astype(bool)
    tout = np.asarray(arrays.get("timeouts", np.zeros(n, bool))).astype(bool)
    if "infos/episode_id" in arrays:
        ep = np.asarray(arrays["infos/episode_id"]).astype(str)
        new_ep = np.r_[True, ep[1:] != ep[:-1]] if n else np.zeros(0, bool)
    else:
        new_ep = np.r_[True, (term | tout)[:-1]] if n else np.zeros(0, bool)
        ep = np.char.add(f"{name}-", np.char.zfill((np.cumsum(new_ep) - 1).astype(str), 6))
    step = np.asarray(arrays["infos/step"], np.int64) if "infos/step" in arrays else \
        np.arange(n) - np.flatnonzero(new_ep)[np.cumsum(new_ep) - 1]
    keep = np.ones(n, bool)
    if "next_observations" in arrays:
        next_obs = np.asarray(arrays["next_observations"], np.float64).reshape(n, -1)
    else:  # the next row of the same episode; an episode's last row has no successor
        last = np.r_[new_ep[1:], True]
        next_obs = np.vstack([obs[1:], obs[-1:]]) if n else obs
        keep = ~last | term
        next_obs = np.where(last[:, None], obs, next_obs)  # terminal rows: next state unused (no bootstrap)
        if (~keep).any():
            log.info("%s: dropped %d last rows of episodes without a next observation", where, int((~keep).sum()))
    src = np.asarray(arrays["infos/source"]).astype(str) if "infos/source" in arrays else "unknown"
    bp = np.asarray(arrays["infos/behavior_prob"], np.float64) if "infos/behavior_prob" in arrays else None
    t_ns = np.asarray(arrays["infos/t_ns"], np.int64) if "infos/t_ns" in arrays else None

    def sel(x: Any) -> Any:
        return x if x is None or isinstance(x, str) else x[keep]

    return TransitionDataset.from_arrays(
        info, episode_id=ep[keep], step=step[keep], obs=obs[keep], action=action[keep],
        cost=-np.asarray(arrays["rewards"], np.float64)[keep], next_obs=next_obs[keep], terminated=term[keep],
        truncated=tout[keep], source=sel(src), behavior_prob=sel(bp), t_ns=sel(t_ns))


# ----------------------------------------------------------------------------- Minari
def _minari() -> Any:
    try:
        import minari
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise OfflineADPError("Minari support needs the minari package: pip install 'offline-adp[minari]'") from exc
    return minari


def _episode_bounds(ep_codes: np.ndarray) -> np.ndarray:
    return np.r_[np.flatnonzero(np.r_[True, ep_codes[1:] != ep_codes[:-1]]), len(ep_codes)] if len(ep_codes) else np.zeros(1, int)


def to_minari(ds: TransitionDataset, dataset_id: str, *, datasets_path: str | PathLike[str] | None = None,
              author: str | None = None, description: str | None = None) -> Path:
    """Write ``ds`` as a local Minari dataset ``dataset_id`` (see module docstring);
    returns its directory. ``datasets_path`` overrides ``MINARI_DATASETS_PATH``."""
    minari = _minari()
    import gymnasium as gym
    from minari.data_collector import EpisodeBuffer

    c = _columns(ds)
    bounds = _episode_bounds(ds.episode_index)
    first, last = bounds[:-1], bounds[1:] - 1
    inner = np.ones(len(ds), bool)
    inner[last] = False
    gap = np.flatnonzero(inner[:-1] & (c["next_obs"][:-1] != c["obs"][1:]).any(axis=1)) if len(ds) > 1 else []
    if len(gap):
        i = int(gap[0])
        raise OfflineADPError(f"episode {c['episode_id'][i]!r} step {c['step'][i]}: next_obs differs from the next step's obs; "
                              "Minari episodes are observation sequences and need contiguous episodes")
    buffers = []
    nan = np.full(1, np.nan)
    for k, (lo, hi) in enumerate(zip(first, last + 1, strict=True)):
        obs = np.vstack([c["obs"][lo:hi], c["next_obs"][hi - 1:hi]])
        bp = c["behavior_prob"][lo:hi] if c["behavior_prob"] is not None else np.full(hi - lo, np.nan)
        infos = {"episode_id": np.append(c["episode_id"][lo:hi], c["episode_id"][hi - 1]).astype(str).tolist(),
                 "step": np.r_[c["step"][lo:hi], c["step"][hi - 1] + 1].astype(np.int64).tolist(),
                 "source": np.append(c["source"][lo:hi], c["source"][hi - 1]).astype(str).tolist(),
                 "behavior_prob": np.r_[bp, nan].astype(np.float64).tolist()}
        if c["t_ns"] is not None:
            infos["t_ns"] = np.r_[c["t_ns"][lo:hi], c["t_ns"][hi - 1]].astype(np.int64).tolist()
        # infos as lists: minari's arrow storage cannot decode 1-D numpy info arrays (empty shape)
        buffers.append(EpisodeBuffer(id=k, observations=obs, actions=c["action"][lo:hi],
                                     rewards=-c["cost"][lo:hi], terminations=c["terminated"][lo:hi],
                                     truncations=c["truncated"][lo:hi], infos=infos))
    d = len(ds.feature_names)
    obs_space = gym.spaces.Box(-np.inf, np.inf, shape=(d,), dtype=np.float64)
    act_space = gym.spaces.Discrete(ds.n_actions)
    old = os.environ.get("MINARI_DATASETS_PATH")
    if datasets_path is not None:
        os.environ["MINARI_DATASETS_PATH"] = str(datasets_path)
    try:
        with warnings.catch_warnings():  # minari's reminders about optional metadata fields
            warnings.filterwarnings("ignore", message=r".*(is set to None|env_spec is None)", category=UserWarning)
            out = minari.create_dataset_from_buffers(
                dataset_id, buffers, observation_space=obs_space, action_space=act_space, algorithm_name="offline_adp",
                author=author, description=description or f"exported by offline_adp from {ds.info.name or 'a dataset'}",
                code_permalink="https://github.com/offline-adp", data_format="arrow")
        out.storage.update_metadata({"offline_adp": json.loads(ds.info.to_json())})
        path = Path(out.storage.data_path).parent
    except ValueError as exc:  # e.g. the id exists already
        raise OfflineADPError(f"minari dataset {dataset_id!r}: {exc}") from exc
    finally:
        if datasets_path is not None:
            if old is None:
                os.environ.pop("MINARI_DATASETS_PATH", None)
            else:
                os.environ["MINARI_DATASETS_PATH"] = old
    log.info("wrote Minari dataset %s at %s: %d episodes, %d steps", dataset_id, path, len(first), len(ds))
    return path


def from_minari(source: Any, info: DatasetInfo | None = None, *, feature_names: list[str] | None = None,
                action_table: ActionTable | None = None) -> TransitionDataset:
    """A dataset from a local Minari dataset: a ``MinariDataset``, a dataset directory
    (or its ``data/``), or an id under ``MINARI_DATASETS_PATH`` (never downloaded).

    Metadata: ``info``, else the ``offline_adp`` entry of the dataset's metadata, else
    ``feature_names`` and ``action_table`` (default: ``Discrete(n)`` actions are indices
    with values ``0..n-1``; ``Box`` actions are matched to the distinct action rows).
    """
    minari = _minari()
    if isinstance(source, minari.MinariDataset):
        mds, where = source, "minari dataset"
    else:
        p = Path(source)
        cands = [p / "data", p] if p.exists() else []
        if not cands:
            from minari.storage.datasets_root_dir import get_dataset_path

            q = get_dataset_path(str(source))
            cands = [q / "data"] if q.exists() else []
        data_dir = next((c for c in cands if (c / "metadata.json").exists()), None)
        if data_dir is None:
            raise IngestError(f"{source}: no local Minari dataset there (looked for metadata.json; datasets path "
                              f"{os.environ.get('MINARI_DATASETS_PATH', '~/.minari/datasets')}); nothing is downloaded")
        mds, where = minari.MinariDataset(data_dir), str(source)
    meta = mds.storage.metadata
    if info is None and "offline_adp" in meta:
        info = DatasetInfo.from_dict(meta["offline_adp"], where=f"{where}: metadata offline_adp")
    aspace = mds.action_space
    discrete = type(aspace).__name__ == "Discrete"
    eps = list(mds.iterate_episodes())
    if info is None:
        if action_table is None:
            if discrete:
                action_table = ActionTable.from_values(np.arange(int(aspace.n), dtype=float))
            else:
                action_table = _table_from_values(np.vstack([np.asarray(e.actions).reshape(len(e.rewards), -1) for e in eps]))
        d = int(np.prod(mds.observation_space.shape))
        info = _default_info(d, action_table, feature_names, meta.get("dataset_id", "minari"))
    cols: dict[str, list[Any]] = {k: [] for k in ("ep", "step", "obs", "next", "act", "rew", "term", "trunc", "src", "bp", "t")}
    for e in eps:
        T = len(e.rewards)
        o = np.asarray(e.observations, np.float64).reshape(T + 1, -1)
        inf = e.infos or {}
        cols["ep"].append(np.asarray(inf["episode_id"][:T]).astype(str) if "episode_id" in inf else np.full(T, f"minari-{e.id:06d}"))
        cols["step"].append(np.asarray(inf["step"][:T], np.int64) if "step" in inf else np.arange(T))
        cols["obs"].append(o[:-1])
        cols["next"].append(o[1:])
        a = np.asarray(e.actions)
        cols["act"].append(a.astype(np.int64).reshape(T) if discrete else _action_indices(a.reshape(T, -1), info.action_table, where))
        cols["rew"].append(np.asarray(e.rewards, np.float64))
        cols["term"].append(np.asarray(e.terminations, bool))
        cols["trunc"].append(np.asarray(e.truncations, bool))
        cols["src"].append(np.asarray(inf["source"][:T]).astype(str) if "source" in inf else np.full(T, "unknown"))
        cols["bp"].append(np.asarray(inf["behavior_prob"][:T], np.float64) if "behavior_prob" in inf else np.full(T, np.nan))
        if "t_ns" in inf:
            cols["t"].append(np.asarray(inf["t_ns"][:T], np.int64))
    cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in cols.items()}
    bp = cat["bp"] if len(cat["bp"]) and not np.isnan(cat["bp"]).all() else None
    return TransitionDataset.from_arrays(
        info, episode_id=cat["ep"], step=cat["step"], obs=cat["obs"], action=cat["act"], cost=-cat["rew"],
        next_obs=cat["next"], terminated=cat["term"], truncated=cat["trunc"], source=cat["src"], behavior_prob=bp,
        t_ns=cat["t"] if len(cols["t"]) == len(eps) and eps else None)


# ----------------------------------------------------------------------------- LeRobot
def to_lerobot(ds: TransitionDataset, root: str | PathLike[str], *, fps: float | None = None, task: str | None = None,
               robot_type: str = "unknown", overwrite: bool = False) -> Path:
    """Write ``ds`` in the LeRobot dataset layout (v2.1, no videos) under ``root``.

    ``fps`` defaults to the median step period of ``t_ns`` (else 1); ``task`` to the
    dataset's name. One frame per transition (see module docstring).
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    from offline_adp.data.io import atomic_directory

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
    values = at.values[c["action"]]
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
        (meta / "tasks.jsonl").write_text(json.dumps({"task_index": 0, "task": task}) + "\n")
        n_ep = len(bounds) - 1
        info = {"codebase_version": "v2.1", "robot_type": robot_type, "total_episodes": n_ep, "total_frames": n,
                "total_tasks": 1, "total_videos": 0, "total_chunks": (n_ep + chunks - 1) // chunks, "chunks_size": chunks,
                "fps": fps, "splits": {"train": f"0:{n_ep}"},
                "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet", "video_path": None,
                "features": feats, "offline_adp": json.loads(ds.info.to_json())}
        (meta / "info.json").write_text(json.dumps(info, indent=1))
    log.info("wrote LeRobot-layout dataset %s: %d episodes, %d frames", root, n_ep, n)
    return Path(root)


# ----------------------------------------------------------------------------- CLI entry
FORMATS = ("dataset", "d4rl", "minari", "lerobot")


def convert(source: str, out: str, *, from_format: str = "dataset", to_format: str = "dataset",
            overwrite: bool = False) -> Path:
    """``offline-adp convert``: read ``source`` in ``from_format`` (a dataset directory,
    a D4RL ``.npz``, a local Minari dataset id or path) and write ``out`` in ``to_format``
    (a dataset directory, a ``.npz`` file, a Minari dataset id under
    ``MINARI_DATASETS_PATH``, a LeRobot-layout directory)."""
    from offline_adp.data.io import read_dataset
    from offline_adp.errors import UnknownNameError

    for f in (from_format, to_format):
        if f not in FORMATS:
            raise UnknownNameError(f"unknown dataset format {f!r}; known: {list(FORMATS)}")
    if from_format == "lerobot":
        raise OfflineADPError("reading the LeRobot layout is not supported (export only)")
    readers = {"dataset": read_dataset, "d4rl": from_d4rl, "minari": from_minari}
    ds = readers[from_format](source)
    if to_format == "dataset":
        ds.save(out, overwrite=overwrite)
        return Path(out)
    if to_format == "d4rl":
        if Path(out).exists() and not overwrite:
            raise OfflineADPError(f"{out} already exists; pass --overwrite to replace it")
        return save_d4rl(ds, out)
    if to_format == "minari":
        return to_minari(ds, out)
    return to_lerobot(ds, out, overwrite=overwrite)
