"""Parquet/CSV transition or step tables -> validated dataset directory.

The user's files are read as they are (only the spec's columns), mapped through the
spec, sorted by (episode, order), checked by the doctor, and written atomically. Every
row keeps ``src_file``/``src_row`` so a finding or a quarantined row names its origin.

Step tables (``kind = "steps"``) get ``next_obs`` by shifting within each episode. The
last row of an episode has no following row:

- if it is ``terminated``, ``next_obs`` is set to its own ``obs`` (a placeholder: no
  algorithm bootstraps through termination);
- otherwise, if the spec gives ``next_columns``, they supply its next state;
- otherwise the row cannot form a transition: it is dropped, the previous row becomes
  the episode's (truncated) end, and the count is reported in the summary and in
  ``info.json`` (``ingest.dropped_last_rows``) - never silently.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from offline_adp._version import __version__
from offline_adp.data import schema as S
from offline_adp.data.columns import encode_strings, sorted_encoding
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.files import locked_directory, sha256_file
from offline_adp.data.info import DatasetInfo, Feature
from offline_adp.data.io import check_dataset_output, write_dataset
from offline_adp.data.pages import small_pages
from offline_adp.data.repeats import warn_repeated
from offline_adp.data.validate import ValidationReport, split_quarantine, validate
from offline_adp.errors import IngestError, InvalidArgumentError, ValidationError
from offline_adp.ingest.actions import (
    bin_continuous,
    command_actions,
    command_columns,
    map_discrete,
)
from offline_adp.ingest.parquet_checks import (
    action_labels,
    check_json_commands,
    check_order_column,
    input_paths,
    source_findings,
    warn_many_labels,
)
from offline_adp.ingest.parquet_columns import (
    _blockwise,
    _commands,
    _f64,
    _flag,
    _is_list,
    _np,
    _one_chunk,
    _read,
    _steps,
    _times_ns,
    _type_conflict,
    _width_findings,
    check_command_column,
)
from offline_adp.ingest.spec import ParquetSpec, load_parquet_spec


@dataclass
class IngestResult:
    """What an ingestion produced and found."""

    dataset: TransitionDataset
    report: ValidationReport
    quarantined_rows: int = 0
    quarantined_episodes: int = 0
    dropped_last_rows: int = 0
    inputs: list[dict[str, Any]] = field(default_factory=list)
    path: Path | None = None
    quarantine: pa.Table | None = None
    repeated_episodes: int = 0  #: episodes equal row for row to an earlier one (offline_adp.data.repeats)

    def summary(self) -> dict[str, Any]:
        return {
            "episodes": self.dataset.n_episodes,
            "transitions": len(self.dataset),
            "per_source": self.dataset.source_counts(),
            "quarantined_episodes": self.quarantined_episodes,
            "quarantined_rows": self.quarantined_rows,
            "dropped_last_rows": self.dropped_last_rows,
            "terminated_and_truncated": self.report.n_terminated_and_truncated,
            "repeated_episodes": self.repeated_episodes,
            "inputs": len(self.inputs),
        }


def ingest_tables(
    inputs: Sequence[str | PathLike[str]] | str | PathLike[str],
    spec: ParquetSpec,
    *,
    on_error: str | None = None,
    progress: Callable[[str], None] | None = None,
) -> IngestResult:
    """Read, map, sort and check the inputs; returns the (clean) dataset and report."""
    on_error = on_error or spec.on_error
    if on_error not in ("fail", "quarantine"):
        raise IngestError(f"on_error must be 'fail' or 'quarantine', got {on_error!r}")
    paths = input_paths(inputs)
    if not paths:
        raise IngestError("no input files given")
    # every intermediate of the mapping (and the input's columns the dataset does not
    # share) is freed when _map returns, before validation and writing
    out, atable, dropped, metas, names, enc, width = _map(paths, spec, progress)
    units = dict(spec.observations.units)
    info = DatasetInfo(
        features=tuple(Feature(nm, units.get(nm, "")) for nm in names),
        action_table=atable,
        gamma=spec.gamma,
        horizon=spec.horizon,
        propensity_source="logged" if spec.propensity_column else "unknown",
        provenance={
            "inputs": metas,
            "spec": spec.raw,
            "spec_sha256": spec.sha256,
            "package_version": __version__,
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "generator": "offline-adp ingest parquet",
        },
        name=spec.name,
    )
    ds = TransitionDataset(out, info, _sorted_ids=enc)  # sorted by _map: not checked again
    del out, enc  # the dataset holds what it needs (its table, int64 codes)
    if progress:
        progress("validating")
    report = validate(ds, extra=width)  # names src_file/src_row of each finding
    report.input_columns = _input_columns(spec, names)
    result = IngestResult(ds, report, dropped_last_rows=dropped, inputs=metas)
    if not report.ok:
        if on_error == "fail":
            raise ValidationError(
                report.to_text() + "\nFix the input, or re-run with --on-error quarantine to set bad episodes aside.",
                report,
            )
        clean, rejected = split_quarantine(ds, report)
        result.dataset = clean
        result.quarantine = rejected
        result.quarantined_rows = rejected.num_rows
        result.quarantined_episodes = int(len(report.bad_episodes))
    result.repeated_episodes = len(warn_repeated(result.dataset, ", ".join(map(str, paths[:2]))
                                                 + (", ..." if len(paths) > 2 else "")))
    return result


def _input_columns(spec: ParquetSpec, names: list[str]) -> dict[str, str]:
    """The dataset's columns by the spec's input columns (the doctor names both)."""
    o = spec.observations
    out = {S.EPISODE_ID: spec.episode.id, S.STEP: spec.episode.step or spec.episode.order or spec.episode.time,
           S.COST: spec.cost_column or spec.reward_column, S.TERMINATED: spec.terminated_column,
           S.TRUNCATED: spec.truncated_column, S.SOURCE: spec.source_column, S.BEHAVIOR_PROB: spec.propensity_column,
           S.ACTION: ", ".join(spec.action.source_columns),
           **{S.obs_column(n): c for n, c in zip(names, o.columns, strict=False)},
           **{S.next_obs_column(n): c for n, c in zip(names, o.next_columns or o.columns, strict=False)}}
    return {k: v for k, v in out.items() if v}


def _map(paths: list[Path], spec: ParquetSpec, progress: Callable[[str], None] | None
         ) -> tuple[pa.Table, Any, int, list[dict[str, Any]], list[str], pa.DictionaryArray | None, list[Any]]:
    """Read the inputs and map them through the spec: the dataset's table (sorted by
    episode and step), action table, dropped last rows, input metadata, feature names, the
    episode ids' encoding for the table's rows (None when rows were dropped), and the
    findings of command lists of the wrong width (for :func:`validate`'s ``extra``)."""
    tables, metas = [], []
    # input hashes (provenance) are computed in a thread while the tables are read
    with ThreadPoolExecutor(max_workers=1) as hasher:
        hashes = [hasher.submit(sha256_file, p) if p.is_file() else None for p in paths]
        for k, p in enumerate(paths):
            if progress:
                progress(f"reading {p}")
            t = _read(p, spec)
            ids = t.column(spec.episode.id)
            if ids.null_count:
                i = int(np.flatnonzero(np.asarray(pc.is_null(ids)))[0])
                raise IngestError(f"{p}: row {i} column {spec.episode.id!r}: episode id is missing (null); every "
                                  "row needs one")
            # file 0's indices as calloc'd zeros: pages the kernel maps only when written (never)
            fi = np.zeros(t.num_rows, np.int32) if k == 0 else np.full(t.num_rows, k, np.int32)
            t = t.append_column("__file", pa.array(fi)).append_column(
                "__row", pa.array(np.arange(t.num_rows, dtype=np.int64))
            )
            # unify id column type across files
            t = t.set_column(0, spec.episode.id, t.column(spec.episode.id).cast(pa.string()))
            src = spec.source_column
            if src and src != spec.episode.id:  # text labels: dictionary<int32, string> in every file
                j = t.column_names.index(src)
                c = t.column(j)
                if pa.types.is_dictionary(c.type) and pa.types.is_string(c.type.value_type):
                    pass
                elif pa.types.is_string(c.type) or pa.types.is_large_string(c.type):
                    t = t.set_column(j, src, pc.dictionary_encode(c.cast(pa.string())))
            tables.append(t)
            metas.append({"path": str(p), "sha256": None, "rows": t.num_rows})
            del t
        for m, h in zip(metas, hashes, strict=True):
            m["sha256"] = h.result() if h is not None else None
    try:
        table = pa.concat_tables(tables, promote_options="permissive")
    except (pa.ArrowInvalid, pa.ArrowTypeError, pa.ArrowNotImplementedError) as exc:
        raise IngestError(_type_conflict(tables,
                                         metas) or f"input files have incompatible column types: {exc}") from None
    del tables  # the table holds the columns now: each one combined below frees its chunks
    for j in range(table.num_columns):  # one column at a time: each frees its chunks before the next
        table = _one_chunk(table, j)
    names_of = np.array([m["path"] for m in metas], dtype=object)
    if table.num_rows == 0:  # e.g. a CSV with a header and no rows
        raise IngestError(f"{', '.join(str(m['path']) for m in metas)}: no rows (only a header, or empty tables); "
                          "nothing to ingest")

    # episodes may not span files (they would silently merge)
    ep_file = (
        None
        if len(paths) == 1
        else pa.table({"e": table.column(spec.episode.id), "f": table.column("__file")})
        .group_by("e")
        .aggregate([("f", "count_distinct"), ("f", "min"), ("f", "max")])
    )
    multi = ep_file.filter(pc.greater(ep_file.column("f_count_distinct"), 1)) if ep_file is not None else None
    if multi is not None and multi.num_rows:
        r = multi.slice(0, 1).to_pylist()[0]
        raise IngestError(
            f"episode id {r['e']!r} occurs in {names_of[r['f_min']]} and {names_of[r['f_max']]} "
            f"({multi.num_rows} ids in several files); give each file distinct episode ids"
        )

    # order within episodes
    order_col = spec.episode.step or spec.episode.order or spec.episode.time
    assert order_col is not None
    if not spec.episode.step and spec.episode.order:  # a missing time stays null: the doctor's, quarantinable
        check_order_column(table, order_col, names_of)
    enc = sorted_encoding(table.column(spec.episode.id), table.column(order_col).to_numpy(zero_copy_only=False))
    if enc is None:  # sort only when needed (ties keep file order)
        idx = pc.sort_indices(table, sort_keys=[(spec.episode.id, "ascending"), (order_col, "ascending"),
                                                ("__file", "ascending"), ("__row", "ascending")])
        table = table.take(idx)
        enc = encode_strings(table.column(spec.episode.id))
    n = table.num_rows
    fidx = table.column("__file").to_numpy()
    rows = table.column("__row").to_numpy()

    def file_of(i: np.ndarray) -> str:
        return str(names_of[fidx[i[0]]]) if len(i) else "?"

    file_of.rows = rows  # type: ignore[attr-defined]  # row in its file, for _where

    ep_ids = table.column(spec.episode.id)
    codes = enc.indices.to_numpy(zero_copy_only=False)  # int32: a view
    last = np.empty(n, bool)  # each episode's last row (n > 0 here); starts from it: no second mask
    np.not_equal(codes[1:], codes[:-1], out=last[:-1])
    last[-1] = True
    starts = np.r_[0, np.flatnonzero(last[:-1]) + 1]
    lens = np.diff(np.r_[starts, n])
    if spec.episode.step:
        step = _steps(table, spec.episode.step, spec.episode.step_base, file_of)
    else:
        # dense rank of the order value within the episode: ties share a step (doctor flags them)
        ov = table.column(order_col).to_numpy(zero_copy_only=False)
        new_val = np.r_[True, ov[1:] != ov[:-1]] if n else np.zeros(0, bool)
        new_val[starts] = True  # an episode's first row
        cum = np.cumsum(new_val) - 1
        step = cum - np.repeat(cum[starts], lens)

    # float64 columns stay the input's Arrow buffers (no copy); steps tables shift in numpy
    obs: list[Any] = [_f64(table, c, file_of) for c in spec.observations.columns]
    has_next = bool(spec.observations.next_columns)
    nxt_given: list[Any] | None = [_f64(table, c,
                                        file_of) for c in spec.observations.next_columns] if has_next else None

    term, term_null = _flag(table, spec.terminated_column, n, file_of)
    trunc_col, trunc_null = _flag(table, spec.truncated_column, n, file_of)
    # rule: an episode's end is truncated unless the terminal column says terminated; set
    # in place (the column's own unpacked flags) at the episodes' last rows only
    trunc = trunc_col
    ends = np.r_[starts[1:] - 1, n - 1]
    trunc[ends] |= ~term[ends]

    keep: np.ndarray | None = None  # rows kept (None: every row)
    dropped = 0
    if spec.kind == "transitions":
        assert nxt_given is not None
        nxt = nxt_given
    else:
        end_term = last & term
        nxt = []
        obs = [o.to_numpy() for o in obs]
        if nxt_given is not None:
            nxt_given = [x.to_numpy() for x in nxt_given]
        for j, o in enumerate(obs):
            x = np.empty_like(o)
            x[:-1] = o[1:]
            x[end_term] = o[end_term]  # placeholder: never bootstrapped through termination
            if n:
                x[-1] = o[-1]
            if has_next:
                sel = last & ~term
                x[sel] = nxt_given[j][sel]  # type: ignore[index]
            nxt.append(x)
        if not has_next:
            drop = last & ~term
            dropped = int(drop.sum())
            keep = ~drop
            d = np.flatnonzero(drop)
            prev = d - 1
            same = (prev >= 0) & (codes[np.maximum(prev, 0)] == codes[d])
            trunc = trunc.copy()
            trunc[prev[same]] = True  # the previous row becomes the episode's truncated end

    # actions from the rows that stay (a dropped row must not shape the bins)
    all_kept = keep is None or bool(keep.all())
    aspec = spec.action
    if not aspec.columns and pa.types.is_struct(table.column(aspec.column).type):
        raise IngestError(f"{file_of(np.array([0]))}: column {aspec.column!r} is a struct "
                          f"({table.column(aspec.column).type}): give each component its own column "
                          "(action.columns = [...], type = 'continuous') or store the command as a list column")
    check_json_commands(table, aspec, file_of)
    list_col = not aspec.columns and _is_list(table.column(aspec.column).type)
    if list_col and aspec.type == "discrete":
        if aspec.type_declared:
            raise IngestError(f"{file_of(np.array([0]))}: column {aspec.column!r} holds lists (a command "
                              "vector per row): "
                              "set action.type = 'continuous' (discrete actions are one label per row)")
        aspec = replace(aspec, type="continuous", components=aspec.names, names=None)  # names: its components
    elif aspec.type == "discrete" and (aspec.low is not None or aspec.high is not None or aspec.units is not None):
        raise IngestError(f"{file_of(np.array([0]))}: column {aspec.column!r} holds one label per row: action.low/high/"
                          "units are only for continuous commands (type = 'continuous')")
    commands: dict[str, Any] = {}
    widths: np.ndarray | None = None  # list lengths of a list column (else no width to check)
    a_null: np.ndarray | None = None  # rows whose discrete label is null: a null action (the doctor's null_value)
    if aspec.type == "discrete":
        raw_action, a_null = action_labels(table, aspec.column, file_of)
        if all_kept:
            action, atable = _blockwise(map_discrete, raw_action, aspec)
        else:
            action = np.full(n, -1, np.int32)
            action[keep], atable = map_discrete(raw_action[keep], aspec)
        warn_many_labels(raw_action, len(atable.actions), aspec, file_of(np.array([0])))
        del raw_action
    elif (
        not aspec.exact
        and not aspec.columns
        and not list_col
        and all_kept
        and not (aspec.low or aspec.high or aspec.units)
    ):
        # a binned scalar column as before (block by block), its exact commands kept alongside
        check_command_column(table, aspec.column, file_of)
        raw_action = _np(table, aspec.column, np.float64, file_of)
        action, atable = _blockwise(bin_continuous, raw_action, aspec)
        commands = command_columns(raw_action, atable.dims)
        del raw_action
    else:
        x, widths, dims = _commands(table, aspec, list_col, file_of)
        where = f"{file_of(np.array([0]))}: action"
        vector = bool(aspec.columns) or list_col
        if all_kept:
            action, atable = command_actions(x, aspec, dims, vector=vector, where=where)
        else:
            action = np.full(n, -1, np.int32)
            action[keep], atable = command_actions(x[keep], aspec, dims, vector=vector, where=where)
        commands = command_columns(x, dims)
        del x
    if spec.cost_column:
        cost = _f64(table, spec.cost_column, file_of)
    else:
        cost = pc.negate(_f64(table, spec.reward_column, file_of))  # type: ignore[arg-type]

    names = list(spec.observations.names or spec.observations.columns)
    cols: dict[str, Any] = {S.EPISODE_ID: ep_ids,
                            S.STEP: step.astype(np.int32) if isinstance(step, np.ndarray) else step}
    if spec.episode.time:
        cols[S.T_NS] = _times_ns(table, spec.episode.time, spec.episode.time_unit, file_of)
    for j, nm in enumerate(names):
        cols[S.obs_column(nm)] = obs[j]
    cols[S.ACTION] = pa.array(action, mask=a_null) if a_null is not None else action
    cols.update(commands)
    cols[S.COST] = cost
    for j, nm in enumerate(names):
        cols[S.next_obs_column(nm)] = nxt[j]
    cols[S.TERMINATED] = pa.array(term, mask=term_null) if term_null is not None else term
    cols[S.TRUNCATED] = pa.array(trunc, mask=trunc_null) if trunc_null is not None else trunc
    if spec.source_column:
        src = table.column(spec.source_column)
        if pa.types.is_dictionary(src.type):  # read as such: one dictionary for every chunk
            cols[S.SOURCE] = src.cast(pa.dictionary(pa.int32(), pa.string())).unify_dictionaries().combine_chunks()
        else:
            cols[S.SOURCE] = encode_strings(src.cast(pa.string()))
    else:
        cols[S.SOURCE] = pa.DictionaryArray.from_arrays(pa.array(np.zeros(n, np.int32)), pa.array([spec.source_value]))
    if spec.propensity_column:
        # a non-number names its file and row; a missing value stays null (the doctor's business)
        cols[S.BEHAVIOR_PROB] = _f64(table, spec.propensity_column, file_of, keep_nulls=True)
    cols["src_file"] = pa.DictionaryArray.from_arrays(pa.array(fidx.astype(np.int32, copy=False)),
                                                      pa.array(names_of.astype(str).tolist()))
    cols["src_row"] = table.column("__row")
    # chunked columns stay chunked: the output shares the input's buffers where it can
    out = pa.table(cols)
    width = _width_findings(widths, aspec, atable)
    if spec.source_column:
        width += source_findings(cols[S.SOURCE], codes, spec.source_column)
    if not all_kept:
        out = out.filter(pa.array(keep))
        width = [(c, m[keep], col, msg if isinstance(msg, str) else msg[keep]) for c, m, col, msg in width]
    return out, atable, dropped, metas, names, enc if all_kept else None, width


def ingest_parquet(
    inputs: Sequence[str | PathLike[str]] | str | PathLike[str],
    spec: ParquetSpec | str | PathLike[str],
    out: str | PathLike[str],
    *,
    on_error: str | None = None,
    overwrite: bool = False,
    progress: Callable[[str], None] | None = None,
) -> IngestResult:
    """Ingest Parquet/CSV tables into a dataset directory at ``out`` (atomic write).

    ``inputs`` is one path or a list of paths; ``spec`` a :class:`ParquetSpec` or the path
    of a spec file.

    Raises
    ------
    InvalidArgumentError
        ``inputs``, ``spec`` or ``out`` is not of a type above (e.g. None).
    SpecError
        The spec is malformed.
    IngestError
        An input is unreadable or lacks a column the spec names.
    ValidationError
        The doctor found defects and ``on_error`` is ``"fail"`` (the default).
    """
    paths = input_paths(inputs)  # before the lock: a wrong argument names itself
    if not isinstance(out, (str, PathLike)):
        raise InvalidArgumentError(f"out must be a path (str or os.PathLike), got {type(out).__name__}")
    check_dataset_output(out, paths)  # before anything is written (the lock file, the parent)
    if not isinstance(spec, ParquetSpec):
        if not isinstance(spec, (str, PathLike)):
            raise InvalidArgumentError(f"spec must be a ParquetSpec or the path of a spec file (str or os.PathLike), "
                                       f"got {type(spec).__name__}; parse a mapping with "
                                       "offline_adp.ingest.spec.parse_parquet_spec")
        spec = load_parquet_spec(spec)
    # small pages while the tables are read, checked and written: huge-page faults cost the
    # kernel up to 1.4 s of zeroing at 2M rows (offline_adp.data.pages)
    with locked_directory(out, what="dataset"), small_pages():  # a second ingest into `out` fails now
        return _ingest_locked(paths, spec, out, on_error=on_error, overwrite=overwrite, progress=progress)


def _ingest_locked(inputs: Sequence[str | PathLike[str]] | str | PathLike[str], spec: ParquetSpec,
                   out: str | PathLike[str], *,
                   on_error: str | None, overwrite: bool, progress: Callable[[str], None] | None) -> IngestResult:
    if (Path(out).exists() or Path(out).is_symlink()) and not overwrite:
        raise IngestError(f"{out} already exists; pass overwrite=True (CLI: --overwrite) to replace it")
    res = ingest_tables(inputs, spec, on_error=on_error, progress=progress)
    if progress:
        progress(f"writing {out}")
    res.path = write_dataset(
        res.dataset,
        out,
        overwrite=overwrite,
        quarantine=res.quarantine,
        extra_meta={
            "ingest": {
                "doctor": res.report.summary(),
                "quarantined_rows": res.quarantined_rows,
                "quarantined_episodes": res.quarantined_episodes,
                "dropped_last_rows": res.dropped_last_rows,
                "repeated_episodes": res.repeated_episodes,
            }
        },
    )
    return res
