"""What the dataset doctor (:mod:`offline_adp.data.validate`) reports and what becomes of it:
the check codes, where each row came from (:class:`RowOrigin`), the report
(:class:`ValidationReport`), and the quarantine: every episode with a finding moved out of
a dataset with a reason per row (:func:`split_quarantine`), and an ingestion that
quarantined everything refused (:func:`refuse_all_quarantined`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from os import PathLike
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc

from offline_adp.data import schema as S
from offline_adp.data.dataset import TransitionDataset

CHECKS: tuple[str, ...] = (
    "null_value",
    "step_not_contiguous",
    "next_obs_mismatch",
    "flag_not_last",
    "end_unflagged",
    "non_finite",
    "value_out_of_range",
    "action_out_of_range",
    "command_width",
    "command_out_of_bounds",
    "propensity_out_of_range",
    "time_decreasing",
    "source_changed",
    "info_stale",
    "fingerprint_mismatch",
    "episodes_stale",
    "episode_split_across_parts",
)
FINDING_COLUMNS = ["check", "file", "row", S.EPISODE_ID, S.STEP, "column", "message"]


@dataclass(frozen=True)
class RowOrigin:
    """Where each row came from: ``files[file_index[i]]``, row ``row[i]`` of that file."""

    files: Sequence[str]
    file_index: np.ndarray
    row: np.ndarray
    label: str = "row"  # what ``row`` counts: "row" (of a table) or "log_time" (ns, of an MCAP message)

    @classmethod
    def of(cls, ds: TransitionDataset) -> RowOrigin:
        """From the dataset's ``src_file``/``src_row`` (or, ingested from MCAP,
        ``src_file``/``src_log_time``) columns if present, else its own rows."""
        t = ds.table
        loc = next((c for c in ("src_row", "src_log_time") if c in t.column_names), None)
        if "src_file" in t.column_names and loc is not None:
            col = t.column("src_file").combine_chunks()
            if not pa.types.is_dictionary(col.type):
                col = pc.dictionary_encode(col)
            return cls(
                [str(x) for x in col.dictionary.to_pylist()],
                col.indices.to_numpy(zero_copy_only=False),
                t.column(loc).to_numpy(zero_copy_only=False),
                "row" if loc == "src_row" else "log_time",
            )
        return cls(["<memory>"], np.zeros(len(ds), np.int64), np.arange(len(ds)))


@dataclass
class ValidationReport:
    """Findings of the doctor over one table.

    Attributes
    ----------
    findings : pandas.DataFrame
        One row per finding, columns ``check, file, row, episode_id, step, column,
        message``; ``row`` is the 0-based row within ``file`` (for MCAP inputs: the
        message's ``log_time`` in ns, see ``row_label``).
    n_rows, n_episodes : int
        Size of what was checked.
    row_label : str
        ``"row"`` or ``"log_time"``: what the ``row`` column counts.
    """

    findings: pd.DataFrame = field(default_factory=lambda: pd.DataFrame(columns=FINDING_COLUMNS))
    n_rows: int = 0
    n_episodes: int = 0
    n_terminated_and_truncated: int = 0
    row_label: str = "row"
    #: the dataset's columns by the input's column names, where they differ (a Parquet/CSV
    #: spec's mapping): the text names both
    input_columns: dict[str, str] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return len(self.findings) == 0

    def counts(self) -> dict[str, int]:
        """Number of findings per check code."""
        return {str(k): int(v) for k, v in self.findings["check"].value_counts().sort_index().items()}

    @property
    def bad_episodes(self) -> np.ndarray:
        """Ids of episodes with at least one finding."""
        return np.unique(self.findings[S.EPISODE_ID].astype(str).to_numpy())

    def summary(self) -> dict[str, object]:
        return {
            "ok": self.ok,
            "n_rows": self.n_rows,
            "n_episodes": self.n_episodes,
            "n_findings": len(self.findings),
            "bad_episodes": int(len(self.bad_episodes)),
            "counts": self.counts(),
            "terminated_and_truncated": self.n_terminated_and_truncated,
        }

    def to_text(self, max_findings: int = 20) -> str:
        """Human-readable report: counts per check, then the first findings."""
        both = (f" ({self.n_terminated_and_truncated} rows both terminated and truncated: treated as terminated)"
                if self.n_terminated_and_truncated else "")
        if self.ok:
            return f"OK: {self.n_rows} transitions in {self.n_episodes} episodes pass every check.{both}"
        lines = [
            f"FAILED: {len(self.findings)} findings in {len(self.bad_episodes)} of {self.n_episodes} episodes "
            f"({self.n_rows} transitions checked)"
        ]
        for check, n in self.counts().items():
            lines.append(f"  {check:<26} {n}")
        if self.row_label == "row" and len(self.findings):
            csv = any(str(f).lower().endswith(".csv") for f in self.findings["file"].unique())
            lines.append("  (rows count each file's data rows from 0" + ("; in a CSV without blank lines or cells "
                                                                      "over several lines, the line is row + 2"
                                                                      if csv else "") + ")")
        for r in self.findings.head(max_findings).itertuples(index=False):
            lines.append(
                f"  {r.file}: {self.row_label} {r.row} (episode {r.episode_id!s}, step {r.step}) column {r.column!r}"
                + (f" (input column {self.input_columns[r.column]!r})"
                   if self.input_columns.get(r.column, r.column) != r.column else "")
                + f": [{r.check}] {r.message}"
            )
        if len(self.findings) > max_findings:
            lines.append(f"  ... and {len(self.findings) - max_findings} more (see the findings table)")
        return "\n".join(lines)


def split_quarantine(ds: TransitionDataset, report: ValidationReport) -> tuple[TransitionDataset, pa.Table]:
    """Move every episode with a finding out of ``ds``.

    Returns the clean dataset and a table of every rejected row (all of the dataset's
    columns, so ``src_file``/``src_row`` when ingested) with ``reason``: the findings on
    that row, or a pointer to the episode's findings. Nothing is dropped:
    ``len(clean) + len(quarantine) == len(ds)``.
    """
    bad_ids = report.bad_episodes
    bad_mask = np.isin(ds.episode_ids.astype(str), bad_ids)
    row_bad = bad_mask[ds.episode_index]
    rejected = ds.table.filter(pa.array(row_bad))
    n = ds.table.num_rows
    reasons = np.full(n, "", dtype=object)
    if len(report.findings):
        # findings carry row-in-file; map back to dataset rows via (episode_id, step)
        key = report.findings[S.EPISODE_ID].astype(str) + "#" + report.findings[S.STEP].astype(str)
        per_row = (
            report.findings.assign(_k=key,
                                   _r="[" + report.findings["check"] + "] " + report.findings["column"] + ": "
                                   + report.findings["message"])
            .groupby("_k", sort=False)["_r"]
            .agg("; ".join)
        )
        ids = ds.episode_ids.astype(str)[ds.episode_index]
        keys = pd.Series(ids).str.cat(pd.Series(ds.table.column(S.STEP).to_numpy()).astype(str), sep="#")
        reasons = keys.map(per_row).fillna("").to_numpy(dtype=object)
        first_reason = (
            report.findings.assign(_r="[" + report.findings["check"] + "] at step "
                                   + report.findings[S.STEP].astype(str))
            .groupby(S.EPISODE_ID, sort=False)["_r"].first()
        )
        ep_reason = pd.Series(ids).map(first_reason).fillna("").to_numpy(dtype=object)
        empty = reasons == ""
        reasons[empty] = np.char.add("episode rejected: ", ep_reason[empty].astype(str)).astype(object)
    rejected = rejected.append_column("reason", pa.array(reasons[row_bad], pa.string()))
    clean = TransitionDataset(ds.table.filter(pa.array(~row_bad)), ds.info)
    return clean, rejected


def refuse_all_quarantined(out: str | PathLike[str], summary: Mapping[str, Any]) -> None:
    """An ingestion whose every episode was quarantined is a failure, not an empty success:
    an :class:`~offline_adp.errors.IngestError` naming the quarantine (exit 2 on the CLI).
    ``summary`` is an ingestion's summary (``episodes``, ``quarantined_rows``, ...)."""
    if not summary.get("episodes") and summary.get("quarantined_rows"):
        from offline_adp.errors import IngestError

        n = summary.get("quarantined_episodes")
        raise IngestError(f"{out}: every episode was quarantined ({f'{n} episodes, ' if n else ''}"
                          f"{summary['quarantined_rows']} rows), no transitions are left; see {out}/quarantine/ "
                          "for a reason per row")
