"""Minari datasets: :func:`to_minari`, :func:`from_minari` (see :mod:`offline_adp.formats`)."""

from __future__ import annotations

import json
import os
import warnings
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import ActionTable, DatasetInfo
from offline_adp.errors import (
    ExportError,
    IngestError,
    MissingExtraError,
    OfflineADPError,
    WriteError,
)
from offline_adp.formats.common import (
    _INT32_MAX,
    _action_indices,
    _columns,
    _default_info,
    _encode_actions,
    _episode_bounds,
    _finite_floats,
    _flags,
    _integers,
    _numeric,
    _provenance,
    _require_doctor,
)
from offline_adp.progress import get_logger

log = get_logger(__name__)


def _minari() -> Any:
    try:
        import minari
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingExtraError("Minari support needs the minari package: pip install 'offline-adp[minari]'") from exc
    return minari


def to_minari(ds: TransitionDataset, dataset_id: str, *, datasets_path: str | PathLike[str] | None = None,
              author: str | None = None, description: str | None = None) -> Path:
    """Write ``ds`` as a local Minari dataset ``dataset_id`` (see module docstring);
    returns its directory. ``datasets_path`` overrides ``MINARI_DATASETS_PATH``."""
    if ds.commands() is not None:
        raise ExportError("this dataset holds continuous commands (action_value.*): the Minari export writes a "
                          "Discrete action space, which would keep only their coarse bins and lose the commands; "
                          "convert it --to d4rl or --to lerobot, which keep the exact commands")
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
        raise ExportError(f"episode {c['episode_id'][i]!r} step {c['step'][i]}: next_obs differs from the next "
                          "step's obs; Minari episodes are observation sequences and need contiguous episodes")
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
        raise WriteError(f"minari dataset {dataset_id!r}: {exc}") from exc
    finally:
        if datasets_path is not None:
            if old is None:
                os.environ.pop("MINARI_DATASETS_PATH", None)
            else:
                os.environ["MINARI_DATASETS_PATH"] = old
    log.info("wrote Minari dataset %s at %s: %d episodes, %d steps", dataset_id, path, len(first), len(ds))
    return path


def _minari_dir(source: Any) -> Path:
    """The ``data/`` directory of a local Minari dataset (a path or an id; never downloaded)."""
    p = Path(source)
    cands = [p / "data", p] if p.exists() else []
    if not cands:
        try:
            from minari.storage.datasets_root_dir import get_dataset_path

            q = get_dataset_path(str(source))
        except Exception as exc:  # minari's own id parsing: a malformed id
            raise IngestError(f"{source}: not a Minari dataset id or path ({type(exc).__name__}: "
                              f"{str(exc)[:200]})") from None
        cands = [q / "data"] if q.exists() else []
    data_dir = next((c for c in cands if (c / "metadata.json").is_file()), None)
    if data_dir is None:
        raise IngestError(f"{source}: no local Minari dataset there (looked for metadata.json; datasets path "
                          f"{os.environ.get('MINARI_DATASETS_PATH', '~/.minari/datasets')}); nothing is downloaded")
    meta = data_dir / "metadata.json"
    if meta.stat().st_size > 64 << 20:
        raise IngestError(f"{meta}: {meta.stat().st_size} bytes is too large for Minari metadata")
    try:
        m = json.loads(meta.read_bytes().decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise IngestError(f"{meta}: not valid JSON ({type(exc).__name__}: {str(exc)[:200]})") from None
    if not isinstance(m, dict):
        raise IngestError(f"{meta}: a JSON object is required, found {type(m).__name__}")
    return data_dir


def _space_kind(space: Any, where: str, what: str) -> str:
    name = type(space).__name__
    if name not in ("Box", "Discrete"):
        raise IngestError(f"{where}: {what} space {name} is not supported (Box or Discrete)")
    return name


def from_minari(source: Any, info: DatasetInfo | None = None, *, feature_names: list[str] | None = None,
                action_table: ActionTable | None = None) -> TransitionDataset:
    """A dataset from a local Minari dataset: a ``MinariDataset``, a dataset directory
    (or its ``data/``), or an id under ``MINARI_DATASETS_PATH`` (never downloaded).

    Metadata: ``info``, else the ``offline_adp`` entry of the dataset's metadata, else
    ``feature_names`` and ``action_table`` (default: ``Discrete(n)`` actions are indices
    with values ``0..n-1``; ``Box`` actions are continuous commands: the distinct rows
    when there are at most :data:`MAX_EXACT_ACTIONS`, else binned, with the exact
    commands in ``action_value.<dim>`` columns).

    The directory is untrusted: missing or unreadable files, spaces we cannot store,
    episodes of the wrong shapes, non-boolean flags and out-of-range steps are an
    :class:`IngestError` naming the dataset and episode; the result passes the ingestion
    doctor (findings name the episode and step).
    """
    minari = _minari()
    if isinstance(source, minari.MinariDataset):
        mds, where = source, "minari dataset"
    else:
        data_dir = _minari_dir(source)
        where = str(source)
        try:
            mds = minari.MinariDataset(data_dir)
        except Exception as exc:  # minari raises whatever its parsers raise on a damaged directory
            raise IngestError(f"{where}: not a readable Minari dataset ({type(exc).__name__}: "
                              f"{str(exc)[:300]})") from None
    try:
        return _read_minari(mds, where, info, feature_names, action_table)
    except OfflineADPError:
        raise
    except Exception as exc:  # a damaged episode file, a wrong type deep inside minari / pyarrow
        raise IngestError(f"{where}: not a readable Minari dataset ({type(exc).__name__}: {str(exc)[:300]})") from None


def _read_minari(mds: Any, where: str, info: DatasetInfo | None, feature_names: list[str] | None,
                 action_table: ActionTable | None) -> TransitionDataset:
    meta = mds.storage.metadata
    if not isinstance(meta, dict):
        raise IngestError(f"{where}: metadata is not a JSON object")
    if info is None and "offline_adp" in meta:
        if not isinstance(meta["offline_adp"], dict):
            raise IngestError(f"{where}: metadata offline_adp: a JSON object is required")
        info = DatasetInfo.from_dict(meta["offline_adp"], where=f"{where}: metadata offline_adp")
    akind = _space_kind(mds.action_space, where, "action")
    _space_kind(mds.observation_space, where, "observation")
    discrete = akind == "Discrete"
    d = int(np.prod(mds.observation_space.shape))
    k = 1 if discrete else int(np.prod(mds.action_space.shape))
    cols: dict[str, list[Any]] = {c: [] for c in ("ep", "step", "obs", "next", "act", "rew", "term", "trunc", "src",
                                                  "bp", "t",
                                                   "e", "row")}
    names: list[str] = []
    n_ep = 0
    for e in mds.iterate_episodes():
        ew = f"{where} episode {e.id}"
        rew = _numeric(e.rewards, ew, "rewards")
        T = len(rew)
        if rew.shape != (T,):
            raise IngestError(f"{ew}: rewards: shape {rew.shape} where (T,) is required")
        o = _numeric(e.observations, ew, "observations")
        if o.shape[0] != T + 1 or o.size != (T + 1) * d:
            raise IngestError(f"{ew}: observations: shape {o.shape} where ({T + 1}, {d}) is required (T + 1 "
                              f"for {T} steps)")
        o = _finite_floats(o.reshape(T + 1, d), ew, "observations")
        a = _numeric(e.actions, ew, "actions")
        if a.shape[0] != T or a.size != T * k:
            raise IngestError(f"{ew}: actions: shape {a.shape} where ({T}{'' if discrete else f', {k}'}) is required")
        inf = e.infos if isinstance(e.infos, dict) else {}
        cols["ep"].append(np.asarray(inf["episode_id"][:T]).astype(str) if "episode_id" in inf
                          else np.full(T, f"minari-{e.id:06d}"))
        cols["step"].append(_integers(np.asarray(inf["step"])[:T], ew, "infos/step", T, 0, _INT32_MAX,
                                      "steps are stored as int32 from 0") if "step" in inf else np.arange(T))
        cols["obs"].append(o[:-1])
        cols["next"].append(o[1:])
        cols["act"].append(a.reshape(T, k))
        cols["rew"].append(_finite_floats(rew, ew, "rewards"))
        cols["term"].append(_flags(e.terminations, ew, "terminations", T))
        cols["trunc"].append(_flags(e.truncations, ew, "truncations", T))
        cols["src"].append(np.asarray(inf["source"][:T]).astype(str) if "source" in inf else np.full(T, "unknown"))
        cols["bp"].append(np.asarray(inf["behavior_prob"][:T],
                                     np.float64) if "behavior_prob" in inf else np.full(T, np.nan))
        if "t_ns" in inf:
            cols["t"].append(_integers(np.asarray(inf["t_ns"])[:T], ew, "infos/t_ns", T, -(2**63) + 1, 2**63 - 1024,
                                       "int64 nanoseconds"))
        cols["e"].append(np.full(T, n_ep, np.int64))
        cols["row"].append(np.arange(T))
        names.append(ew)
        n_ep += 1
    if not n_ep:
        raise IngestError(f"{where}: no episodes")
    n_steps = sum(len(r) for r in cols["rew"])
    for key, found in (("total_episodes", n_ep), ("total_steps", n_steps)):
        declared = meta.get(key)
        if declared is not None and declared != found:
            raise IngestError(f"{where}: metadata {key} = {declared!r} but {found} were read (a missing or damaged "
                              "episode file)")
    cat = {c: np.concatenate(v) if v else np.zeros(0) for c, v in cols.items()}
    acts = cat["act"]
    extra: dict[str, Any] = {}
    if discrete:
        n_act = int(mds.action_space.n)
        action = _integers(acts.reshape(-1), where, "actions", len(acts), 0, n_act - 1, f"Discrete({n_act}) indices")
        if info is None:
            table = action_table or ActionTable.from_values(np.arange(n_act, dtype=float))
    elif info is not None or action_table is not None:
        vals = _finite_floats(acts, where, "actions")
        action = _action_indices(vals, (info.action_table if info is not None else action_table), where)  # type: ignore[union-attr]
        table = action_table  # type: ignore[assignment]
    else:
        space = mds.action_space  # a Box: its declared bounds are the commands' (when finite)
        low, high = (np.asarray(getattr(space, b, np.nan), np.float64).reshape(-1) for b in ("low", "high"))
        finite = low.shape == high.shape == (acts.reshape(len(acts), -1).shape[1],) and np.isfinite(low).all() \
            and np.isfinite(high).all()
        action, table, extra = _encode_actions(_finite_floats(acts, where, "actions"), where,
                                               low=low if finite else None,
                                               high=high if finite else None)
    if info is None:
        info = _default_info(d, table, feature_names, str(meta.get("dataset_id", "minari")))
    if len(info.features) != d:
        raise IngestError(f"{where}: observations have {d} components, the metadata names "
                          f"{len(info.features)} features")
    if discrete and info.n_actions < int(mds.action_space.n):
        bad = action >= info.n_actions
        if bad.any():
            raise IngestError(f"{where}: actions: index {int(action[bad][0])} outside the "
                              f"{info.n_actions}-action table")
    bp = cat["bp"] if len(cat["bp"]) and not np.isnan(cat["bp"]).all() else None
    ds = TransitionDataset.from_arrays(
        info, episode_id=cat["ep"], step=cat["step"], obs=cat["obs"], action=action, cost=-cat["rew"],
        next_obs=cat["next"], terminated=cat["term"], truncated=cat["trunc"], source=cat["src"], behavior_prob=bp,
        t_ns=cat["t"] if len(cols["t"]) == n_ep else None, extra={**extra, **_provenance(names, cat["e"], cat["row"])})
    return _require_doctor(ds, where)
