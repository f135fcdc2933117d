"""Is a spec topic in a recording at all? Asked on an error path only, to name the topics
that are there when a needed one has no message."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap.rosbags_source import is_rosbags_input
from offline_adp.ingest.mcap.scan import scan_records


def check_topic_present(files: list[Path], topic: str, step: str) -> None:
    """Raise, naming the files and the topics they hold, when ``topic`` has no message
    in any file of the recording (read again, on this error path only)."""
    from offline_adp.ingest.mcap.rosbags_source import raw_messages

    present: dict[str, int] = {}
    for path in files:
        report: dict[str, Any] = {}
        try:
            if is_rosbags_input(path):
                for _ in raw_messages(path, set(), report):
                    pass
                counts = {bt.topic: n for bt, n in report.get("bag_topics", {}).items()}
                if not any(counts.values()):  # no index counts: the scan's skipped counts
                    counts = dict(report.get("skipped", {}))
            else:
                with open(path, "rb") as f:
                    for _ in scan_records(f, set(), report):
                        pass
                counts = dict(report.get("skipped", {}))
        except (IngestError, OSError):
            return  # unreadable now: the caller's error stands
        for t, n in counts.items():
            present[t] = present.get(t, 0) + n
    if present.get(topic, 0) == 0:
        names = ", ".join(map(str, files))
        there = sorted(t for t, n in present.items() if n)
        raise IngestError(f"{names}: topic {topic!r} of the spec is not in the file (no message on it; the "
                          f"topics with messages are {there}); {step}")
