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
    path templates), ``meta/episodes.jsonl``, ``meta/episodes_stats.jsonl`` (per episode
    and feature: min, max, mean, std, count), ``meta/tasks.jsonl`` and
    ``data/chunk-000/episode_000000.parquet`` with one frame per transition:
    ``observation.state``, ``action`` (values), ``action_index``, ``next.reward``,
    ``next.done`` (terminated), ``next.truncated``, ``next.observation.state``,
    ``timestamp``, ``frame_index``, ``episode_index``, ``index``, ``task_index``.
"""

from __future__ import annotations

from pathlib import Path

from offline_adp.errors import InvalidArgumentError, OutputExistsError
from offline_adp.formats.common import ACTION_VALUE, META_KEY, _action_indices
from offline_adp.formats.d4rl import from_d4rl, save_d4rl, to_d4rl
from offline_adp.formats.lerobot import to_lerobot
from offline_adp.formats.minari import from_minari, to_minari

__all__ = ["ACTION_VALUE", "FORMATS", "META_KEY", "_action_indices", "convert", "from_d4rl", "from_minari", "save_d4rl",
           "to_d4rl", "to_lerobot", "to_minari"]


# ----------------------------------------------------------------------------- CLI entry
FORMATS = ("dataset", "d4rl", "minari", "lerobot")


def convert(source: str, out: str, *, from_format: str = "dataset", to_format: str = "dataset",
            overwrite: bool = False) -> Path:
    """``offline-adp convert``: read ``source`` in ``from_format`` (a dataset directory,
    a D4RL ``.npz``, a local Minari dataset id or path) and write ``out`` in ``to_format``
    (a dataset directory, a ``.npz`` file, a Minari dataset id under
    ``MINARI_DATASETS_PATH``, a LeRobot-layout directory)."""
    from offline_adp.data.dataset import read_dataset
    from offline_adp.errors import UnknownNameError

    for f in (from_format, to_format):
        if f not in FORMATS:
            raise UnknownNameError(f"unknown dataset format {f!r}; known: {list(FORMATS)}")
    if from_format == "lerobot":
        raise InvalidArgumentError("reading the LeRobot layout is not supported (export only)")
    if to_format != "minari":  # an id under MINARI_DATASETS_PATH, not a path next to the source
        from offline_adp.data.io import check_dataset_output

        check_dataset_output(out, [source] if Path(source).exists() else [])  # never into what it reads
    readers = {"dataset": read_dataset, "d4rl": from_d4rl, "minari": from_minari}
    ds = readers[from_format](source)
    if from_format == "dataset":  # d4rl / minari readers run the doctor themselves
        from offline_adp.data.validate import require_usable

        require_usable(ds, source)
    if to_format == "dataset":
        ds.save(out, overwrite=overwrite)
        return Path(out)
    if to_format == "d4rl":
        if Path(out).exists() and not overwrite:
            raise OutputExistsError(f"{out} already exists; pass --overwrite to replace it")
        return save_d4rl(ds, out)
    if to_format == "minari":
        return to_minari(ds, out)
    return to_lerobot(ds, out, overwrite=overwrite)
