"""Typed records passed between the parts of MCAP ingestion."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(slots=True)
class Message:
    """One decoded message as the assembler sees it: topic, MCAP times (ns) and the
    decoded value (a dict, a ROS 2 or protobuf object)."""

    topic: str
    log_time: int
    publish_time: int
    data: Any


@dataclass
class EpisodeRows:
    """One assembled episode: its transitions (``t``, ``file``, ``obs``, ``next``, ``aux``,
    ``aux_next``, ``act``, one row per transition) and how it ended."""

    ep: str
    src: str
    t: np.ndarray
    file: np.ndarray
    obs: np.ndarray
    next: np.ndarray
    aux: np.ndarray
    aux_next: np.ndarray
    act: np.ndarray
    terminated: bool
    t_end: int
    epoch: int = 0
    log_time: np.ndarray | None = None
    reason: str = ""  # why the episode is rejected ("" = kept): it goes to quarantine/ with this reason


@dataclass
class RecordingResult:
    """What assembling one recording gives: its episodes and the counts of the summary."""

    episodes: list[EpisodeRows]
    stats: dict[str, int]
    used: dict[str, int]  # per topic: messages placed against the clock's steps (decoded, not set aside)
    late: dict[str, int]
    files: list[dict[str, Any]]
    missing_topics: list[str]
    filled: dict[str, int] = field(default_factory=dict)  # steps given a stream's fill value, per topic
    decoded: dict[str, int] = field(default_factory=dict)  # per topic: messages decoded (used + set aside)
    orphaned: dict[str, int] = field(default_factory=dict)  # per topic: held for an epoch the clock never reached
    dropped_late: dict[str, int] = field(default_factory=dict)  # per topic: came after their epoch was over
    stale: dict[str, int] = field(default_factory=dict)  # per topic: held after a jump back that proved no restart
    unselected: dict[str, int] = field(default_factory=dict)  # per topic: for no key (no selector found its element)
    #: per key of a selector that found no element: the spec's place of it, and the values seen instead
    selector_misses: dict[str, list[str]] = field(default_factory=dict)
