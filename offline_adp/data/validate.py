"""The dataset doctor: every rule a transition table must satisfy, checked vectorised.

Rules (check codes in brackets):

- steps of each episode are contiguous from 0 [``step_not_contiguous``];
- ``next_obs`` of step t equals ``obs`` of step t+1 unless the episode ended
  [``next_obs_mismatch``];
- ``terminated``/``truncated`` only on an episode's last row [``flag_not_last``], and the
  last row carries one of them [``end_unflagged``]; both on one row is valid (gymnasium
  reports both when a goal is reached on the time-limit step): the transition is
  terminated (absorbing, never bootstrapped) and the report counts such rows
  (``summary()["terminated_and_truncated"]``);
- no NaN/inf in obs, cost, next_obs [``non_finite``], nor magnitudes beyond
  :data:`MAX_ABS_VALUE` in the cost (1e150: their squares, in every regressor's loss,
  overflow) or :data:`MAX_ABS_INPUT` in a model input (1e38 in obs, next_obs and command
  components: trees compare inputs as float32) [``value_out_of_range``]; no nulls in required columns, nor in
  ``t_ns`` when present (a missing or non-finite time at ingestion), nor in ``source`` [``null_value``];
- actions inside the action table [``action_out_of_range``];
- continuous commands (an action table of kind ``"continuous"``, or ``action_value.<dim>``
  columns kept next to binned actions): every component has its float column
  [``command_width``; also an ingested list of the wrong length], is finite
  [``non_finite``] and lies within the table's ``low``/``high`` (tolerance
  :data:`COMMAND_BOUND_RTOL`) [``command_out_of_bounds``];
- propensities in (0, 1] [``propensity_out_of_range``];
- timestamps non-decreasing within an episode [``time_decreasing``];
- at ingestion (``extra``): one source label per episode [``source_changed``].

Every finding names the file, the row in that file, the (episode_id, step) and the column.

A dataset *directory* is also checked against its own metadata
(:func:`validate_directory`): ``meta/info.json`` counts [``info_stale``] and fingerprint
[``fingerprint_mismatch``], ``meta/episodes.parquet`` [``episodes_stale``], and every
episode inside one part file [``episode_split_across_parts``] - what a hand-edited or
partly replaced directory gets wrong. These findings name the metadata file and key
(row -1 when no data row is at fault).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc

from offline_adp.data import schema as S
from offline_adp.data.columns import bool_values
from offline_adp.data.dataset import TransitionDataset

# the report and the quarantine (findings.py), importable from here too
from offline_adp.data.findings import (  # noqa: F401
    CHECKS,
    FINDING_COLUMNS,
    RowOrigin,
    ValidationReport,
    refuse_all_quarantined,
    split_quarantine,
)

#: Largest magnitude of an observation or cost the doctor accepts: squared errors of larger
#: values overflow float64 (1.8e308) in every regressor, so a fit could only produce inf/NaN.
MAX_ABS_VALUE = 1e150
#: Largest magnitude of a model input the doctor accepts (observations, next observations,
#: command components): tree regressors compare inputs as float32 (scikit-learn's and ours),
#: whose largest finite value is 3.4e38; a larger input becomes inf and no fit can split on it.
MAX_ABS_INPUT = 1e38
_INPUT_TOO_LARGE = (f"magnitude beyond {MAX_ABS_INPUT:g} (a model input: trees compare inputs as float32, whose "
                    "largest value is 3.4e38); rescale the column")
#: Relative tolerance of the command bounds (``max(1, |bound|)`` times this): round-off of a
#: command written at its bound is not a finding.
COMMAND_BOUND_RTOL = 1e-9
_BLOCK = 1 << 16  # rows per block of the element-wise checks (their temporaries stay small)


def validate(
    ds: TransitionDataset,
    *,
    origin: RowOrigin | None = None,
    atol: float = 1e-9,
    rtol: float = 1e-7,
    extra: Sequence[tuple[str, np.ndarray, str, Any]] = (),
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
    extra : sequence of (check, mask, column, message)
        Findings the ingestion made on the input that the table cannot show (a command list
        of the wrong width: ``command_width``, whose rows the command checks skip: their
        command is missing because of it; a source label changing within an episode:
        ``source_changed``), one mask over the rows each.
    """
    t = ds.table
    n = t.num_rows
    ep_codes = ds.episode_codes  # int32: indexes as well as int64, without the copy
    ep_ids = ds.episode_ids
    step = t.column(S.STEP).to_numpy(zero_copy_only=False)
    # last[i]: row i ends its episode. The row masks of the checks below are made block by
    # block (_flagged), the size of the table only when a row is flagged: no column-sized
    # temporaries (and no fresh pages) for a clean dataset
    last = np.empty(n, bool)
    if n:
        np.not_equal(ep_codes[1:], ep_codes[:-1], out=last[:-1])
        last[-1] = True
    parts: list[pd.DataFrame] = []

    def add(check: str, mask: np.ndarray | None, column: str | np.ndarray, message: str | np.ndarray) -> None:
        if mask is None:  # no row flagged
            return
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
    timed = (S.T_NS,) if S.T_NS in t.column_names else ()
    timed += (S.SOURCE,) if S.SOURCE in t.column_names else ()
    for c in (S.EPISODE_ID, S.STEP, S.ACTION, S.COST, S.TERMINATED, S.TRUNCATED, *timed, *ds.obs_columns,
              *ds.next_obs_columns):
        col = t.column(c)
        if col.null_count:
            add("null_value", np.asarray(pc.is_null(col)), c,
                "time is missing, not finite or beyond int64 nanoseconds" if c == S.T_NS else "value is missing (null)")

    # steps contiguous from 0
    starts = np.r_[0, np.flatnonzero(last[:-1]) + 1] if n else np.zeros(0, np.int64)
    # expected step of row i: i minus the first row of its episode (rows are in episode order)
    bad = _flagged(n, lambda lo, hi: step[lo:hi] != np.arange(lo, hi) - starts[ep_codes[lo:hi]])
    add("step_not_contiguous", bad, S.STEP,
        _messages(bad, lambda i: f"expected step {i - starts[ep_codes[i]]}, found {step[i]}"))

    term = _bool(t, S.TERMINATED)
    trunc = _bool(t, S.TRUNCATED)
    # valid: terminated wins (absorbing); counted, not a finding
    n_both = sum(int(np.count_nonzero(term[lo:lo + _BLOCK] & trunc[lo:lo + _BLOCK])) for lo in range(0, n, _BLOCK))
    add("flag_not_last", _flagged(n, lambda lo, hi: np.greater(term[lo:hi] | trunc[lo:hi], last[lo:hi])),
        S.TERMINATED, "episode flagged as ended before its last row")
    add("end_unflagged", _flagged(n, lambda lo, hi: np.greater(last[lo:hi], term[lo:hi] | trunc[lo:hi])),
        "terminated,truncated",  # last row, not ended
        "last row of the episode is neither terminated nor truncated")

    # continuity next_obs(t) == obs(t+1) within episodes: np.isclose's rule
    # |x - y| <= atol + rtol * |y| on rows where both are finite, without its temporaries
    for oc, nc in zip(ds.obs_columns, ds.next_obs_columns, strict=True):
        o = t.column(oc).to_numpy(zero_copy_only=False)
        x = t.column(nc).to_numpy(zero_copy_only=False)
        if n > 1:
            xs, ys = x[:-1], o[1:]
            mis_head: np.ndarray | None = None  # made at the first mismatch (there is rarely one)
            with np.errstate(invalid="ignore", over="ignore"):
                for lo in range(0, n - 1, _BLOCK):  # temporaries the size of a block
                    xb, yb = xs[lo:lo + _BLOCK], ys[lo:lo + _BLOCK]
                    # equal values always pass: the rule is evaluated on the rows that differ
                    # (episode ends, rounding), all of the block's only when most differ
                    cand = np.not_equal(xb, yb)
                    np.greater(cand, last[lo:lo + len(xb)], out=cand)  # and not an episode's last row
                    k = np.count_nonzero(cand)
                    if not k:
                        continue
                    if k > len(xb) // 8:
                        j = slice(None)
                    else:
                        j = np.flatnonzero(cand)
                        xb, yb = xb[j], yb[j]
                    tol = np.abs(yb)
                    tol *= rtol
                    tol += atol
                    diff = np.subtract(xb, yb)
                    np.abs(diff, out=diff)
                    m = ~(diff <= tol)
                    m &= np.isfinite(xb)
                    m &= np.isfinite(yb)
                    if isinstance(j, slice):
                        m &= cand
                    if not m.any():
                        continue
                    if mis_head is None:
                        mis_head = np.zeros(n - 1, bool)
                    if isinstance(j, slice):
                        mis_head[lo:lo + _BLOCK] = m
                    else:
                        mis_head[lo + j[m]] = True
            if mis_head is not None:
                mis = np.r_[mis_head, False]
                nxt = np.r_[ys, np.nan]
                add(
                    "next_obs_mismatch",
                    mis,
                    nc,
                    _messages(mis, lambda i, x=x, nxt=nxt,
                              oc=oc: f"next_obs {float(x[i])!r} != {oc} of the following step {float(nxt[i])!r}"),
                )

    absbuf = np.empty(max(1, min(n, _BLOCK)))
    for c in (*ds.obs_columns, S.COST, *ds.next_obs_columns):
        col = t.column(c)
        v = col.to_numpy(zero_copy_only=False).astype(np.float64, copy=False)
        bound = MAX_ABS_VALUE if c == S.COST else MAX_ABS_INPUT
        if _all_within(v, bound, absbuf):  # no NaN, inf or huge value: neither check finds anything
            continue
        finite = np.isfinite(v)
        if not finite.all():
            add("non_finite", ~finite & ~np.asarray(pc.is_null(col)) if col.null_count else ~finite, c,
                "value is NaN or infinite")
        big = np.zeros(n, bool)
        with np.errstate(invalid="ignore"):
            for lo in range(0, n, _BLOCK):  # NaN compares False; inf is non_finite, not out of range
                big[lo:lo + _BLOCK] = np.abs(v[lo:lo + _BLOCK]) > bound
        big &= finite
        add("value_out_of_range", big, c,
            f"magnitude beyond {MAX_ABS_VALUE:g} (squared errors would overflow); rescale the column" if c == S.COST
            else _INPUT_TOO_LARGE)

    a = t.column(S.ACTION).to_numpy(zero_copy_only=False)
    # one comparison: a negative integer read as unsigned is beyond any action count
    au = a.view(f"u{a.itemsize}") if a.dtype.kind == "i" else None
    add(
        "action_out_of_range",
        _flagged(n, lambda lo, hi: au[lo:hi] >= ds.n_actions) if au is not None
        else _flagged(n, lambda lo, hi: (a[lo:hi] < 0) | (a[lo:hi] >= ds.n_actions)),
        S.ACTION,
        f"action index outside the action table [0, {ds.n_actions})",
    )

    skip = np.zeros(n, bool)
    for check, mask, column, message in extra:
        add(check, mask, column, message)
        if check == "command_width":
            skip |= mask
    _check_commands(ds, add, last, skip)

    if S.BEHAVIOR_PROB in t.column_names:
        p = t.column(S.BEHAVIOR_PROB).to_numpy(zero_copy_only=False).astype(np.float64, copy=False)
        add(
            "propensity_out_of_range",
            # outside (0, 1]; NaN (a missing propensity) compares False
            _flagged(n, lambda lo, hi: (p[lo:hi] <= 0) | (p[lo:hi] > 1)),
            S.BEHAVIOR_PROB,
            "behavior_prob outside (0, 1]",
        )
    if S.T_NS in t.column_names:
        ts = t.column(S.T_NS).to_numpy(zero_copy_only=False)
        # a row earlier than the row before it, of its episode (that row is not an episode's last)
        dec = _flagged(n, lambda lo, hi: np.greater(ts[lo:hi] < ts[lo - 1:hi - 1], last[lo - 1:hi - 1]), start=1)
        add("time_decreasing", dec, S.T_NS, "timestamp earlier than the previous step's")

    if not parts:
        return ValidationReport(n_rows=n, n_episodes=len(ep_ids), n_terminated_and_truncated=n_both)
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
    return ValidationReport(findings=f[FINDING_COLUMNS], n_rows=n, n_episodes=len(ep_ids),
                            n_terminated_and_truncated=n_both,
                            row_label=origin.label)


def _check_commands(ds: TransitionDataset, add: Any, last: np.ndarray, skip: np.ndarray) -> None:
    """The command checks (see the module docstring) on a dataset whose action table is
    continuous or that carries ``action_value.<dim>`` columns; ``last``: each episode's last
    row, ``skip``: rows already flagged for their command."""
    t = ds.table
    at = ds.info.action_table
    cols = at.command_columns
    present = [c in t.column_names for c in cols]
    if not (at.continuous or any(present)):
        return
    lo, hi = at.bounds()
    for j, c in enumerate(cols):
        if not present[j] or not pa.types.is_floating(t.column(c).type):
            what = "missing" if not present[j] else f"of type {t.column(c).type}, not float"
            first = np.r_[True, last[:-1]] if len(last) else last  # each episode's first row
            add("command_width", first, c,
                f"the command column is {what}: the action table's commands have {len(at.dims)} components "
                f"{list(at.dims)}, each kept in a float column action_value.<dim>")
            continue
        v = t.column(c).to_numpy(zero_copy_only=False).astype(np.float64, copy=False)  # nulls -> NaN
        finite = np.isfinite(v)
        if not finite.all():
            add("non_finite", ~finite & ~skip, c, "command is NaN, infinite or missing")
        with np.errstate(invalid="ignore"):
            big = finite & ~skip & (np.abs(v) > MAX_ABS_INPUT)
        add("value_out_of_range", big, c, "command " + _INPUT_TOO_LARGE)
        if np.isfinite(lo[j]) or np.isfinite(hi[j]):
            lo_j, hi_j = float(lo[j]), float(hi[j])
            tol_lo = COMMAND_BOUND_RTOL * max(1.0, abs(lo_j)) if np.isfinite(lo_j) else 0.0
            tol_hi = COMMAND_BOUND_RTOL * max(1.0, abs(hi_j)) if np.isfinite(hi_j) else 0.0
            with np.errstate(invalid="ignore"):
                out = finite & ~skip & ((v < lo_j - tol_lo) | (v > hi_j + tol_hi))
            add("command_out_of_bounds", out, c,
                _messages(out, lambda i, v=v, lo_j=lo_j, hi_j=hi_j, d=at.dims[j]:
                          f"command {d} = {float(v[i])!r} outside its bounds [{lo_j!r}, {hi_j!r}] (action.low/high)"))


def require_usable(ds: TransitionDataset, where: str | PathLike[str] = "<memory>", use: str = "fit"
                   ) -> ValidationReport:
    """Refuse a dataset an algorithm cannot be fitted on (or a policy evaluated on): empty,
    or failing the doctor.

    ``where`` is the dataset directory ``ds`` was read from (findings then name its part
    files and rows) or a label; ``use`` what there would be nothing to do ("fit", "evaluate on").

    Raises
    ------
    ValidationError
        One line naming ``where``, the counts per check and the first finding's file, row
        and column (``offline-adp validate`` lists them all).
    """
    from offline_adp.errors import ValidationError

    if len(ds) == 0:
        raise ValidationError(f"{where}: the dataset has no transitions; nothing to {use}")
    report = validate(ds, origin=_directory_origin(Path(where), ds) if Path(where).is_dir() else None)
    if not report.ok:
        f = report.findings.iloc[0]
        counts = ", ".join(f"{k} {v}" for k, v in report.counts().items())
        raise ValidationError(
            f"{where}: the dataset fails the doctor ({counts}); first: {f['file']}: row {f['row']} "
            f"(episode {f[S.EPISODE_ID]}, step {f[S.STEP]}) column {f['column']!r}: {f['message']}; "
            f"see `offline-adp validate {where}`", report)
    return report


def _directory_origin(path: Path, ds: TransitionDataset) -> RowOrigin | None:
    """Part file and row of each row of ``ds`` read from directory ``path`` (None if the
    rows were re-sorted on reading, so that they no longer line up with the parts)."""
    import pyarrow.parquet as pq

    from offline_adp.data.io import part_files

    parts = part_files(path)
    sizes = [pq.ParquetFile(p).metadata.num_rows for p in parts]
    origin = RowOrigin(
        [str(p) for p in parts],
        np.repeat(np.arange(len(parts)), sizes),
        np.concatenate([np.arange(s) for s in sizes]) if sizes else np.zeros(0, int),
    )
    return origin if ds.table.num_rows == len(origin.row) and ds.was_sorted else None


def _bool(t: pa.Table, name: str) -> np.ndarray:
    return bool_values(t.column(name))  # nulls as False


def _flagged(n: int, block: Callable[[int, int], np.ndarray], start: int = 0) -> np.ndarray | None:
    """The row mask whose rows ``lo:hi`` are ``block(lo, hi)`` (rows before ``start``:
    False), evaluated :data:`_BLOCK` rows at a time; None when no row is flagged, so that a
    mask the size of the table is made only for a finding.

    Parameters
    ----------
    n : int
        Rows of the table.
    block : callable
        ``block(lo, hi)``: the boolean mask of rows ``lo`` to ``hi``.
    start : int
        The first row checked.

    Returns
    -------
    numpy.ndarray or None
        ``n`` booleans, or None if ``block`` flagged no row.
    """
    out = None
    for lo in range(start, n, _BLOCK):
        hi = min(lo + _BLOCK, n)
        m = block(lo, hi)
        if m.any():
            if out is None:
                out = np.zeros(n, bool)
            out[lo:hi] = m
    return out


def _all_within(v: np.ndarray, bound: float, buf: np.ndarray) -> bool:
    """Whether every value of ``v`` is a number of magnitude at most ``bound`` (NaN is not),
    block by block through ``buf``: no temporary the size of the column."""
    for lo in range(0, len(v), len(buf)):
        block = v[lo:lo + len(buf)]
        a = np.abs(block, out=buf[:len(block)])
        if not a.max() <= bound:  # a NaN makes the max NaN
            return False
    return True


def _messages(mask: np.ndarray | None, fmt) -> np.ndarray | str:
    """Per-row messages, formatted only for the flagged rows (defects are few); ``""``
    when no row is flagged (then :func:`validate`'s ``add`` adds nothing)."""
    if mask is None or not mask.any():
        return ""
    out = np.full(len(mask), "", dtype=object)
    for i in np.flatnonzero(mask):
        out[i] = fmt(i)
    return out


def validate_directory(path: str | PathLike[str]) -> ValidationReport:
    """Load a dataset directory and run the doctor, naming part files and rows in them
    (datasets ingested from MCAP: the recording and the message's log_time); then check
    the directory's metadata against its data (see the module docstring)."""
    from offline_adp.data.dataset import read_dataset
    from offline_adp.data.io import read_info

    path = Path(path)
    ds = read_dataset(path)
    mcap = "src_file" in ds.table.column_names and "src_log_time" in ds.table.column_names
    # rows are read in part order; the constructor re-sorts only a dataset whose parts were
    # edited out of order, and then the part/row names would no longer line up
    origin = None if mcap else _directory_origin(path, ds)
    report = validate(ds, origin=origin)
    meta = _metadata_findings(path, ds, read_info(path), origin)
    if len(meta):
        report.findings = pd.concat([report.findings, meta],
                                    ignore_index=True)[FINDING_COLUMNS] if len(report.findings) else meta
    return report


def _metadata_findings(path: Path, ds: TransitionDataset, raw: dict, origin: RowOrigin | None) -> pd.DataFrame:
    """Findings of the directory's metadata against its data (dataset-level: row -1)."""
    rows: list[dict[str, object]] = []
    info_file = str(path / S.INFO_FILE)

    def add(check: str, file: str, column: str, message: str, row: int = -1, episode: str = "", step: int = -1) -> None:
        rows.append({"check": check, "file": file, "row": row, S.EPISODE_ID: episode, S.STEP: step, "column": column,
                     "message": message})

    for key, actual in (("n_transitions", len(ds)), ("n_episodes", ds.n_episodes)):
        if key in raw and raw[key] != actual:
            add("info_stale", info_file, key, f"info.json says {raw[key]!r}, the data has {actual}")
    if "fingerprint" in raw and not ds.matches_fingerprint(raw["fingerprint"]):
        add("fingerprint_mismatch", info_file, "fingerprint",
            "the data's fingerprint differs from info.json's: the parts were changed after writing")
    ep_path = path / S.EPISODES_FILE
    if ep_path.exists():
        try:
            stored = pd.read_parquet(ep_path)
        except (OSError, ValueError) as exc:
            add("episodes_stale", str(ep_path), "", f"unreadable ({exc})")
        else:
            actual_ep = ds.episode_table()
            cols = [c for c in (S.EPISODE_ID, "length", S.TERMINATED, S.TRUNCATED, "first_row") if c in stored.columns]
            same = len(stored) == len(actual_ep) and all(
                np.array_equal(stored[c].astype(str).to_numpy(), actual_ep[c].astype(str).to_numpy()) for c in cols)
            if not same:
                add("episodes_stale", str(ep_path), ",".join(cols),
                    f"episodes.parquet lists {len(stored)} episodes that do not match the data's {len(actual_ep)}")
    else:
        add("episodes_stale", str(ep_path), "", "missing")
    if origin is not None and len(origin.files) > 1 and len(ds):
        codes = ds.episode_index
        starts = np.flatnonzero(np.r_[True, codes[1:] != codes[:-1]])
        part = origin.file_index
        first_part = np.repeat(part[starts], np.diff(np.r_[starts, len(codes)]))
        split = np.flatnonzero(part != first_part)
        seen: set[int] = set()
        for i in split[:1000]:  # one finding per split episode
            if codes[i] in seen:
                continue
            seen.add(int(codes[i]))
            add("episode_split_across_parts", str(origin.files[part[i]]), S.EPISODE_ID,
                f"episode continues from {origin.files[first_part[i]]} (an episode must lie in one part)",
                row=int(origin.row[i]), episode=str(ds.episode_ids[codes[i]]),
                step=int(ds.table.column(S.STEP)[i].as_py()))
    return pd.DataFrame(rows, columns=FINDING_COLUMNS)
