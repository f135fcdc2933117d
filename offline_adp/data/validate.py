"""The dataset doctor: every rule a transition table must satisfy, checked vectorised.

Rules (check codes in brackets):

- steps of each episode are contiguous from 0 [``step_not_contiguous``];
- ``next_obs`` of step t equals ``obs`` of step t+1 unless the episode ended
  [``next_obs_mismatch``];
- ``terminated``/``truncated`` only on an episode's last row [``flag_not_last``], never
  both [``both_flags``], and the last row carries one of them [``end_unflagged``];
- no NaN/inf in obs, cost, next_obs [``non_finite``]; no nulls in required columns
  [``null_value``];
- actions inside the action table [``action_out_of_range``];
- propensities in (0, 1] [``propensity_out_of_range``];
- timestamps non-decreasing within an episode [``time_decreasing``].

Every finding names the file, the row in that file, the (episode_id, step) and the column.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path

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
    "both_flags",
    "end_unflagged",
    "non_finite",
    "action_out_of_range",
    "propensity_out_of_range",
    "time_decreasing",
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
    row_label: str = "row"

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
        }

    def to_text(self, max_findings: int = 20) -> str:
        """Human-readable report: counts per check, then the first findings."""
        if self.ok:
            return f"OK: {self.n_rows} transitions in {self.n_episodes} episodes pass every check."
        lines = [
            f"FAILED: {len(self.findings)} findings in {len(self.bad_episodes)} of {self.n_episodes} episodes "
            f"({self.n_rows} transitions checked)"
        ]
        for check, n in self.counts().items():
            lines.append(f"  {check:<26} {n}")
        for r in self.findings.head(max_findings).itertuples(index=False):
            lines.append(
                f"  {r.file}: {self.row_label} {r.row} (episode {r.episode_id!s}, step {r.step}) column {r.column!r}: "
                f"[{r.check}] {r.message}"
            )
        if len(self.findings) > max_findings:
            lines.append(f"  ... and {len(self.findings) - max_findings} more (see the findings table)")
        return "\n".join(lines)


def validate(
    ds: TransitionDataset,
    *,
    origin: RowOrigin | None = None,
    atol: float = 1e-9,
    rtol: float = 1e-7,
) -> ValidationReport:
    """Run every check on a dataset.

    Parameters
    ----------
    ds : TransitionDataset
    origin : RowOrigin, optional
        The file and row each dataset row came from. Defaults to the dataset's
        ``src_file``/``src_row`` columns, or ``"<memory>"`` and the dataset row index.
    atol, rtol : float
        Tolerance of the ``next_obs`` / ``obs`` continuity check.
    """
    t = ds.table
    n = t.num_rows
    ep_codes = ds.episode_index
    ep_ids = ds.episode_ids
    step = t.column(S.STEP).to_numpy(zero_copy_only=False)
    last = np.r_[ep_codes[1:] != ep_codes[:-1], True] if n else np.zeros(0, bool)
    first = np.r_[True, ep_codes[1:] != ep_codes[:-1]] if n else np.zeros(0, bool)
    parts: list[pd.DataFrame] = []

    def add(check: str, mask: np.ndarray, column: str | np.ndarray, message: str | np.ndarray) -> None:
        idx = np.flatnonzero(mask)
        if len(idx):
            parts.append(
                pd.DataFrame(
                    {
                        "check": check,
                        "_idx": idx,
                        "column": column if isinstance(column, str) else np.asarray(column)[idx],
                        "message": message if isinstance(message, str) else np.asarray(message)[idx],
                    }
                )
            )

    # nulls in required columns (cast to numpy would hide them)
    for c in (S.STEP, S.ACTION, S.COST, S.TERMINATED, S.TRUNCATED, *ds.obs_columns, *ds.next_obs_columns):
        col = t.column(c)
        if col.null_count:
            add("null_value", np.asarray(pc.is_null(col)), c, "value is missing (null)")

    # steps contiguous from 0
    starts = np.flatnonzero(first)
    expected = np.arange(n) - np.repeat(starts, np.diff(np.r_[starts, n]))
    bad = step != expected
    add("step_not_contiguous", bad, S.STEP, _messages(bad, lambda i: f"expected step {expected[i]}, found {step[i]}"))

    term = _bool(t, S.TERMINATED)
    trunc = _bool(t, S.TRUNCATED)
    add("both_flags", term & trunc, "terminated,truncated", "row is both terminated and truncated")
    add("flag_not_last", (term | trunc) & ~last, S.TERMINATED, "episode flagged as ended before its last row")
    add("end_unflagged", last & ~term & ~trunc, "terminated,truncated", "last row of the episode is neither terminated nor truncated")

    # continuity next_obs(t) == obs(t+1) within episodes
    inner = ~last
    for oc, nc in zip(ds.obs_columns, ds.next_obs_columns, strict=True):
        o = t.column(oc).to_numpy(zero_copy_only=False)
        x = t.column(nc).to_numpy(zero_copy_only=False)
        if n > 1:
            nxt = np.r_[o[1:], np.nan]
            mis = inner & ~np.isclose(x, nxt, atol=atol, rtol=rtol) & np.isfinite(x) & np.isfinite(nxt)
            if mis.any():
                add(
                    "next_obs_mismatch",
                    mis,
                    nc,
                    _messages(mis, lambda i, x=x, nxt=nxt, oc=oc: f"next_obs {x[i]!r} != {oc} of the following step {nxt[i]!r}"),
                )

    for c in (*ds.obs_columns, S.COST, *ds.next_obs_columns):
        v = t.column(c).to_numpy(zero_copy_only=False).astype(np.float64, copy=False)
        add("non_finite", ~np.isfinite(v) & ~np.asarray(pc.is_null(t.column(c))), c, "value is NaN or infinite")

    a = t.column(S.ACTION).to_numpy(zero_copy_only=False)
    add(
        "action_out_of_range",
        (a < 0) | (a >= ds.n_actions),
        S.ACTION,
        f"action index outside the action table [0, {ds.n_actions})",
    )

    if S.BEHAVIOR_PROB in t.column_names:
        p = t.column(S.BEHAVIOR_PROB).to_numpy(zero_copy_only=False).astype(np.float64)
        add(
            "propensity_out_of_range",
            ~np.isnan(p) & ~((p > 0) & (p <= 1)),
            S.BEHAVIOR_PROB,
            "behavior_prob outside (0, 1]",
        )
    if S.T_NS in t.column_names:
        ts = t.column(S.T_NS).to_numpy(zero_copy_only=False)
        dec = np.r_[False, (ts[1:] < ts[:-1]) & ~first[1:]] if n else np.zeros(0, bool)
        add("time_decreasing", dec, S.T_NS, "timestamp earlier than the previous step's")

    if not parts:
        return ValidationReport(n_rows=n, n_episodes=len(ep_ids))
    f = pd.concat(parts, ignore_index=True)
    idx = f.pop("_idx").to_numpy()
    origin = origin if origin is not None else RowOrigin.of(ds)
    f.insert(1, "file", np.asarray(origin.files, dtype=object)[origin.file_index[idx]])
    f.insert(2, "row", origin.row[idx])
    f.insert(3, S.EPISODE_ID, ep_ids[ep_codes[idx]].astype(str))
    f.insert(4, S.STEP, step[idx])
    f["check"] = pd.Categorical(f["check"], categories=list(CHECKS))
    f = f.sort_values(["row", "check"], kind="stable").reset_index(drop=True)
    f["check"] = f["check"].astype(str)
    return ValidationReport(findings=f[FINDING_COLUMNS], n_rows=n, n_episodes=len(ep_ids), row_label=origin.label)


def _bool(t: pa.Table, name: str) -> np.ndarray:
    return np.asarray(t.column(name).fill_null(False).to_numpy(zero_copy_only=False), dtype=bool)


def _messages(mask: np.ndarray, fmt) -> np.ndarray:
    """Per-row messages, formatted only for the flagged rows (defects are few)."""
    out = np.full(len(mask), "", dtype=object)
    for i in np.flatnonzero(mask):
        out[i] = fmt(i)
    return out


def validate_directory(path: str | PathLike[str]) -> ValidationReport:
    """Load a dataset directory and run the doctor, naming part files and rows in them
    (datasets ingested from MCAP: the recording and the message's log_time)."""
    from offline_adp.data.io import part_files, read_dataset

    path = Path(path)
    ds = read_dataset(path)
    if "src_file" in ds.table.column_names and "src_log_time" in ds.table.column_names:
        return validate(ds)  # ingested from MCAP: name the recording and the message's log_time
    parts = part_files(path)
    import pyarrow.parquet as pq

    sizes = [pq.ParquetFile(p).metadata.num_rows for p in parts]
    origin = RowOrigin(
        [str(p) for p in parts],
        np.repeat(np.arange(len(parts)), sizes),
        np.concatenate([np.arange(s) for s in sizes]) if sizes else np.zeros(0, int),
    )
    # rows are read in part order; the constructor re-sorts only a dataset whose parts were
    # edited out of order, and then the part/row names would no longer line up
    return validate(ds, origin=origin if ds.table.num_rows == len(origin.row) and ds.was_sorted else None)


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
            report.findings.assign(_k=key, _r="[" + report.findings["check"] + "] " + report.findings["column"] + ": " + report.findings["message"])
            .groupby("_k", sort=False)["_r"]
            .agg("; ".join)
        )
        ids = ds.episode_ids.astype(str)[ds.episode_index]
        keys = pd.Series(ids).str.cat(pd.Series(ds.table.column(S.STEP).to_numpy()).astype(str), sep="#")
        reasons = keys.map(per_row).fillna("").to_numpy(dtype=object)
        first_reason = (
            report.findings.assign(_r="[" + report.findings["check"] + "] at step " + report.findings[S.STEP].astype(str))
            .groupby(S.EPISODE_ID, sort=False)["_r"].first()
        )
        ep_reason = pd.Series(ids).map(first_reason).fillna("").to_numpy(dtype=object)
        empty = reasons == ""
        reasons[empty] = np.char.add("episode rejected: ", ep_reason[empty].astype(str)).astype(object)
    rejected = rejected.append_column("reason", pa.array(reasons[row_bad], pa.string()))
    clean = TransitionDataset(ds.table.filter(pa.array(~row_bad)), ds.info)
    return clean, rejected
