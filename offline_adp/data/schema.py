"""Column names, format version and directory layout of a dataset directory.

See ``docs/dataset-format.md`` for the prose account; this module is the single source
of those names in code.
"""

from __future__ import annotations

from typing import Final

FORMAT_VERSION: Final = "1.0"

EPISODE_ID: Final = "episode_id"
STEP: Final = "step"
T_NS: Final = "t_ns"
OBS_PREFIX: Final = "obs."
NEXT_OBS_PREFIX: Final = "next_obs."
ACTION: Final = "action"
COST: Final = "cost"
TERMINATED: Final = "terminated"
TRUNCATED: Final = "truncated"
SOURCE: Final = "source"
BEHAVIOR_PROB: Final = "behavior_prob"

REQUIRED_COLUMNS: Final = (EPISODE_ID, STEP, ACTION, COST, TERMINATED, TRUNCATED, SOURCE)
OPTIONAL_COLUMNS: Final = (T_NS, BEHAVIOR_PROB)

DATA_DIR: Final = "data"
META_DIR: Final = "meta"
INFO_FILE: Final = "meta/info.json"
EPISODES_FILE: Final = "meta/episodes.parquet"
STATS_FILE: Final = "meta/stats.json"
QUARANTINE_DIR: Final = "quarantine"
PART_TEMPLATE: Final = "part-{:05d}.parquet"
PARQUET_COMPRESSION: Final = "zstd"

#: Known values of the ``source`` column; others are allowed (free-form labels).
KNOWN_SOURCES: Final = ("demonstration", "exploration", "policy", "unknown")
#: Allowed values of ``propensity_source`` in info.json.
PROPENSITY_SOURCES: Final = ("logged", "estimated", "unknown")


def obs_column(name: str) -> str:
    """Column holding observation feature ``name``."""
    return OBS_PREFIX + name


def next_obs_column(name: str) -> str:
    """Column holding the next observation's feature ``name``."""
    return NEXT_OBS_PREFIX + name
