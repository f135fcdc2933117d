"""Recordings -> dataset: the ``ingest_mcap`` entry point."""

from __future__ import annotations

import datetime as _dt
from collections.abc import Iterable, Sequence
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp._version import __version__
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.files import sha256_file
from offline_adp.data.info import Action, ActionTable, DatasetInfo, Feature
from offline_adp.data.io import check_dataset_output, write_dataset
from offline_adp.data.repeats import warn_repeated
from offline_adp.data.validate import split_quarantine, validate
from offline_adp.errors import IngestError, SpecError, ValidationError
from offline_adp.ingest.actions import (
    bin_continuous,
    command_actions,
    command_columns,
    map_discrete,
)
from offline_adp.ingest.mcap.assembler import _Recording
from offline_adp.ingest.mcap.records import EpisodeRows, Message, RecordingResult
from offline_adp.ingest.mcap.sources import resolve_sources
from offline_adp.ingest.mcap.spec import McapSpec, load_mcap_spec


def _run_recording(files: list[Path], spec: McapSpec, on_error: str, file_index: int) -> RecordingResult | str:
    """One recording; under quarantine a recording that cannot be read at all gives the
    error text (the file is skipped and counted), under fail the error."""
    try:
        return _Recording(files, spec, on_error, file_index).run()
    except IngestError as exc:
        if on_error == "fail" or isinstance(exc, SpecError):
            raise
        return str(exc)


def ingest_mcap(
    files: Sequence[str | PathLike[str]],
    spec: McapSpec | str | PathLike[str],
    out: str | PathLike[str] | None = None,
    *,
    on_error: str | None = None,
    overwrite: bool = False,
    jobs: int = 1,
    progress: Any = None,
) -> tuple[TransitionDataset, dict[str, Any]]:
    """Ingest MCAP files into a dataset (written atomically to ``out`` when given).

    ``files`` may hold globs and rosbag2 bag directories; empty means the spec's
    ``[sources] files``. Recordings (a file, or the parts of a split recording) are
    assembled independently — in a process pool with ``jobs > 1`` — and concatenated in
    input order, so the result does not depend on ``jobs``. Returns the dataset and a
    summary: per file its sha256, damage recovered and, per topic, the messages read =
    used + skipped + unselected + orphaned + stale + dropped late + undecodable (the same counts over all
    files; see :mod:`offline_adp.ingest.mcap.accounting`); steps dropped, outside any
    episode or under an end condition; episodes, transitions and per-source counts; under ``on_error =
    "quarantine"`` the rows set aside in ``quarantine/`` (``rows in the dataset + rows in
    quarantine = transitions_assembled``) and the files skipped.
    ``progress(done, total)`` is called after each recording.
    """
    files = [files] if isinstance(files, (str, PathLike)) else list(files)  # a generator is read once, here
    if out is None:
        ds, _, summary = ingest_mcap_tables(files, spec, on_error=on_error, jobs=jobs, progress=progress)
        return ds, summary
    from offline_adp.data.files import locked_directory

    if not isinstance(spec, McapSpec):
        spec = load_mcap_spec(spec)
    try:
        inputs = [p for rec in resolve_sources(files, spec) for p in rec]
    except IngestError:  # a missing or unreadable input is reported once the lock is held (as a second writer is)
        inputs = [Path(f) for f in files]
    check_dataset_output(out, inputs)  # before anything is written
    with locked_directory(out, what="dataset"):  # from the start, as the Parquet ingest: a second ingest fails now
        if Path(out).exists() and not overwrite:
            raise IngestError(f"{out} already exists; pass overwrite=True (CLI: --overwrite) to replace it")
        ds, quarantine, summary = ingest_mcap_tables(files, spec, on_error=on_error, jobs=jobs, progress=progress)
        write_dataset(ds, out, overwrite=overwrite, quarantine=quarantine, extra_meta={"ingest": _jsonable(summary)})
    return ds, summary


def ingest_mcap_tables(
    files: Sequence[str | PathLike[str]],
    spec: McapSpec | str | PathLike[str],
    *,
    on_error: str | None = None,
    jobs: int = 1,
    progress: Any = None,
) -> tuple[TransitionDataset, Any, dict[str, Any]]:
    """:func:`ingest_mcap` without writing: (dataset, quarantine table or None, summary)."""
    if not isinstance(spec, McapSpec):
        spec = load_mcap_spec(spec)
    on_error = on_error or spec.on_error
    if on_error not in ("fail", "quarantine"):
        raise IngestError(f"on_error must be 'fail' or 'quarantine', got {on_error!r}")
    recordings = resolve_sources(files, spec)
    starts = np.cumsum([0] + [len(r) for r in recordings])[:-1].tolist()
    args = [(r, spec, on_error, s) for r, s in zip(recordings, starts, strict=True)]
    results: list[RecordingResult | str] = []
    if jobs > 1 and len(recordings) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(max_workers=min(jobs, len(recordings)), mp_context=mp.get_context("spawn")) as pool:
            for k, res in enumerate(pool.map(_run_recording, *zip(*args, strict=True))):  # input order
                results.append(res)
                if progress:
                    progress(k + 1, len(recordings))
    else:
        for k, a in enumerate(args):
            results.append(_run_recording(*a))
            if progress:
                progress(k + 1, len(recordings))
    import warnings

    summary: dict[str, Any] = {"files": [], "recordings": [[str(p) for p in r] for r in recordings],
                               "messages_read": {}, "messages_used": {}, "messages_skipped": {},
                               "messages_unselected": {}, "messages_orphaned": {}, "messages_stale": {},
                               "messages_dropped_late": {}, "messages_undecodable": {},
                               "late_messages": {}, "filled_steps": {}, "skipped_files": []}
    good: list[tuple[RecordingResult, list[Path]]] = []
    for res, rec in zip(results, recordings, strict=True):
        if isinstance(res, str):  # unreadable under quarantine: named, skipped, counted
            summary["skipped_files"].append({"files": [str(p) for p in rec], "error": res})
            warnings.warn(f"skipped: {res}", stacklevel=2)
            continue
        if res.files and all(f.get("empty") for f in res.files):
            msg = f"{', '.join(map(str, rec))}: empty file (0 bytes)"
            if on_error == "fail":
                raise IngestError(msg)
            summary["skipped_files"].append({"files": [str(p) for p in rec], "error": msg})
            warnings.warn(f"skipped: {msg}", stacklevel=2)
            continue
        good.append((res, rec))
        for k, v in res.stats.items():
            summary[k] = (max(summary.get(k, 0), v) if k in ("max_buffered_messages", "longest_gap_s")
                          else summary.get(k, 0) + v)
        for name, key in (("used", "messages_used"), ("orphaned", "messages_orphaned"), ("stale", "messages_stale"),
                          ("unselected", "messages_unselected"), ("dropped_late", "messages_dropped_late"),
                          ("late", "late_messages"), ("filled", "filled_steps")):
            for t, v in getattr(res, name).items():
                summary[key][t] = summary[key].get(t, 0) + v
        for f in res.files:  # per topic: read = used + skipped + unselected + orphaned + stale + late + undecodable
            for key in ("messages_read", "messages_skipped", "messages_undecodable"):
                for t, v in f[key].items():
                    summary[key][t] = summary[key].get(t, 0) + v
            fp = Path(f["path"])
            digest = sha256_file(fp) if fp.is_file() else {q.name: sha256_file(q) for q in sorted(fp.iterdir())
                                                           if q.is_file()}
            summary["files"].append({**f, "sha256": digest})
        if res.missing_topics:
            needed = [s for s in (*spec.streams, spec.action_stream) if s.topic in res.missing_topics]
            clock_missing = (spec.clock_topic or "") in res.missing_topics
            if clock_missing or any(s.missing == "error" for s in needed):
                msg = (f"{', '.join(map(str, rec))}: no decodable messages on needed topic(s) {res.missing_topics} "
                       "(present in other recordings? set missing = 'fill' or 'drop_step' on that stream)")
                if on_error == "fail" or not any(not isinstance(r, str) and len(r.episodes) for r in results):
                    raise IngestError(msg)
                warnings.warn(msg, stacklevel=2)
    if summary.get("clock_steps_back"):
        warnings.warn(f"{_n(summary['clock_steps_back'], 'clock message is', 'clock messages are')} earlier than "
                      f"one before them in the file, by less than [episodes] restart = {spec.restart} s: their steps "
                      "are ordered by time, so a transition may pair steps the robot did not take in that order. If "
                      "the clock restarted, lower restart; if the messages are reordered in the file, this is "
                      "expected.", stacklevel=2)
    if summary.get("orphan_messages"):
        warnings.warn(f"{_n(summary['orphan_messages'], 'message was', 'messages were')} set aside, unused: they "
                      f"belong to an epoch the clock never reached (per topic {summary['messages_orphaned']}; a "
                      f"stream's time jumped back more than [episodes] restart = {spec.restart} s, read as a restart "
                      "the clock did not follow). Raise restart above the jump"
                      + _jump_hint(spec, summary["messages_orphaned"]), stacklevel=2)
    if n_stale := sum(summary["messages_stale"].values()):
        warnings.warn(f"{_n(n_stale, 'message was', 'messages were')} set aside as stale, unused (per topic "
                      f"{summary['messages_stale']}): a stream's time jumped back more than [episodes] restart = "
                      f"{spec.restart} s and came back in step with the clock, so it was no restart; the messages it "
                      "held meanwhile are not used" + _jump_hint(spec, summary["messages_stale"]), stacklevel=2)
    if summary.get("duplicate_clock_times"):
        warnings.warn(f"{_n(summary['duplicate_clock_times'], 'clock message repeats', 'clock messages repeat')} "
                      "the time of the one before them: each time is one step, and a stream's values at a repeated "
                      "time are its last message's there (a message published twice, or a clock too coarse for the "
                      "rate)", stacklevel=2)
    summary["filled_steps"] = {t: v for t, v in summary["filled_steps"].items() if v}
    if summary["filled_steps"]:
        warnings.warn(f"steps given a stream's fill value (missing = 'fill'), per topic: {summary['filled_steps']} "
                      "(if that is most steps, check the stream's time field against the clock's: a header stamp "
                      "in simulation time against log_time never aligns)", stacklevel=2)
    summary["late_messages"] = {t: v for t, v in summary["late_messages"].items() if v}
    if summary["late_messages"]:
        warnings.warn(f"{_n(sum(summary['late_messages'].values()), 'message', 'messages')} arrived more than "
                      f"clock.reorder_window = {spec.reorder_window} s after later ones in the file "
                      f"({summary['late_messages']}); steps before them were aligned without them. Raise "
                      "reorder_window.", stacklevel=2)
    _selector_misses(good)
    paths = [p for r in recordings for p in r]
    eps = [ep for r, _ in good for ep in r.episodes]
    _distinct_ids(eps, paths, "id_field" in spec.episode_fields)
    rejected = [ep for ep in eps if ep.reason]
    kept = [ep for ep in eps if not ep.reason]
    summary["transitions_assembled"] = int(sum(len(e.t) for e in eps))
    summary["rejected_episodes"] = [{"episode": e.ep, "transitions": len(e.t), "reason": e.reason} for e in rejected]
    if not kept:
        silent = sorted(t for r, _ in good for t, n in r.decoded.items() if n == 0)
        raise IngestError(
            f"no episode with at least one transition in {[str(p) for p in paths]}"
            + (f"; topics without any message: {silent}" if silent else "")
            + (f"; {summary.get('dropped_steps', 0)} steps dropped for missing values" if summary.get("dropped_steps")
               else "")
            + (f"; rejected episodes: {[e['reason'] for e in summary['rejected_episodes']][:3]}" if rejected else "")
            + (f"; skipped files: {summary['skipped_files']}" if summary["skipped_files"] else ""))
    import pyarrow as pa

    ds_all = _dataset(eps, spec, paths, summary, mark=bool(rejected))
    q_tables = []
    if rejected:
        # the dataset's rows are in (episode id, step) order, not the episodes' file order: each row
        # carries its episode's index into eps (a cut or incomplete episode, wherever it sorts)
        table = ds_all.table
        which = table.column(_EP_INDEX).to_numpy(zero_copy_only=False)
        table = table.drop_columns([_EP_INDEX])
        row_rejected = np.array([bool(e.reason) for e in eps])[which]
        if on_error == "quarantine":
            reasons = np.array([e.reason for e in eps], dtype=object)[which[row_rejected]]
            q_tables.append(table.filter(pa.array(row_rejected)).append_column(
                "reason", pa.array(list(reasons), pa.string())))
        ds = TransitionDataset(table.filter(pa.array(~row_rejected)), ds_all.info)
    else:
        row_rejected, ds = np.zeros(len(ds_all), bool), ds_all
    report = validate(ds)
    summary["doctor"] = report.summary()
    if not report.ok:
        if on_error == "fail":
            raise ValidationError(report.to_text(), report)
        ds, q = split_quarantine(ds, report)
        q_tables.append(q)
    quarantine = pa.concat_tables(q_tables) if q_tables else None
    summary["quarantined_rows"] = 0 if quarantine is None else quarantine.num_rows
    summary["dropped_rows"] = int(row_rejected.sum()) if on_error == "fail" else 0
    summary.update(episodes=ds.n_episodes, transitions=len(ds), per_source=ds.source_counts(),
                   repeated_episodes=len(warn_repeated(ds, ", ".join(map(str, paths[:2]))
                                                       + (", ..." if len(paths) > 2 else ""))))
    return ds, quarantine, summary


def _jump_hint(spec: McapSpec, topics: dict[str, int]) -> str:
    """Why a stream's time may jump back: a list read at [0] (select the element), else a
    stream stamped behind the clock."""
    streams = [st for st in (*spec.streams, spec.action_stream) if st.topic in topics]
    paths = [next(iter(p.values())) if isinstance(p, dict) else p for st in streams
             for p in (st.time, *st.fields.values())]  # a derived field's path too ({ yaw_of = path })
    if any("[0]" in p for p in paths):
        return ("; a list read at [0] whose first element changes from message to message (as /tf's transforms[0]) "
                "does this: select the element, e.g. transforms[child_frame_id=base_link] "
                "(docs/ingestion-spec.md, 'Field paths')")
    return ("; a stream stamped more than restart behind the clock does this (e.g. a pose stamped with the scan "
            "it was computed from, at a low rate): raise restart above that lag")


def _n(count: int, one: str, many: str) -> str:
    """``1 message was`` / ``3 messages were``."""
    return f"{count} {one if count == 1 else many}"


def _selector_misses(good: list[tuple[RecordingResult, list[Path]]]) -> None:
    """A field path's selector ``[key=value]`` that found its element in no message of a
    recording: an error if in none of them (a typo, most likely: the values seen are named),
    else a warning naming those recordings (that stream is then missing there)."""
    import warnings

    missed: dict[str, list[str]] = {}
    seen: dict[str, set[str]] = {}
    for res, rec in good:
        for place, values in res.selector_misses.items():
            missed.setdefault(place, []).append(", ".join(map(str, rec)))
            seen.setdefault(place, set()).update(values)
    for place, recs in missed.items():
        text = (f"{place}: no message has the element a selector [key=value] of its field paths picks (the "
                f"values seen: {sorted(seen[place])[:20]})")
        if len(recs) == len(good):
            raise IngestError(f"{text}; in {recs}")
        warnings.warn(f"{text}; in {recs} (the stream has no message there)", stacklevel=3)


def _distinct_ids(eps: list[EpisodeRows], paths: list[Path], given: bool) -> None:
    """One episode per id. Ids the logs give (``[episodes] id_field``) that name two
    episodes (two recordings numbering from the same id, an id reused in one file) are an
    error naming both; generated ids (two recordings of the same file name) get ``~k``."""
    seen: dict[str, EpisodeRows] = {}
    for e in eps:
        if e.ep in seen and not given:
            k = 1
            while f"{e.ep}~{k}" in seen:
                k += 1
            e.ep = f"{e.ep}~{k}"
        elif e.ep in seen:
            def at(x: EpisodeRows) -> str:
                lt = f" (log_time {int(x.log_time[0])})" if x.log_time is not None and len(x.log_time) else ""
                return f"{paths[int(x.file[0])]}{lt}" if len(x.file) else "?"

            raise IngestError(f"episode id {e.ep!r} names two episodes: in {at(seen[e.ep])} and in {at(e)}; give "
                              "each episode its own id (recordings that each number from the same id can be "
                              "ingested apart, or without [episodes] id_field, which numbers them per recording)")
        seen[e.ep] = e


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


#: A column of the assembled table (dropped before anything is written): each row's episode's
#: index in the list of assembled episodes, so that rejected episodes are found after the sort.
_EP_INDEX = "_episode_index"


def _dataset(eps: list[EpisodeRows], spec: McapSpec, paths: list[Path], summary: dict[str, Any],
             mark: bool = False) -> TransitionDataset:
    """Episodes -> dataset: action table, costs, provenance (``src_file`` and
    ``src_log_time``, the log_time of the message that made the step, per row); ``mark``: each
    row also carries its episode's index in ``eps`` (:data:`_EP_INDEX`)."""
    import pyarrow as pa

    cat = lambda k: np.concatenate([getattr(e, k) for e in eps])  # noqa: E731
    obs, nxt, aux, aux_next = cat("obs"), cat("next"), cat("aux"), cat("aux_next")
    lengths = np.array([len(e.t) for e in eps])
    raw_action = cat("act")
    commands: dict[str, Any] = {}
    if raw_action.ndim == 2:  # a vector action (several fields)
        action, atable = vector_actions(raw_action, spec)
    elif spec.action.type == "discrete":
        action, atable = map_discrete(raw_action, spec.action)
    elif not spec.action.exact and spec.action.low is None and spec.action.high is None and spec.action.units is None:
        action, atable = bin_continuous(raw_action, spec.action)  # as before: the same table
    else:
        action, atable = command_actions(raw_action, spec.action, spec.action.component_names(1), vector=False)
    if spec.action.type == "continuous":  # the exact commands, as logged
        commands = command_columns(raw_action, atable.dims)
    term = np.zeros(len(obs), bool)
    ends = np.cumsum(lengths) - 1
    term[ends] = [e.terminated for e in eps]
    trunc = np.zeros(len(obs), bool)
    trunc[ends] = ~term[ends]
    obs_names, aux_names = spec.obs_names, spec.aux_names
    units = {n: u for st in spec.streams for n, u in st.units.items()}

    def column(name: str, at: str = "step") -> np.ndarray:
        if name == "action" or name.startswith("action."):
            j = atable.dims.index(name[7:]) if name.startswith("action.") else 0
            if atable.continuous:  # the command as logged
                return commands[atable.command_columns[j]]
            return np.where(action >= 0, atable.values[np.maximum(action, 0), j], np.nan)
        if name in obs_names:
            return (nxt if at == "next" else obs)[:, obs_names.index(name)]
        return (aux_next if at == "next" else aux)[:, aux_names.index(name)]

    if spec.cost_field is not None:
        cost = column(spec.cost_field).copy()
    elif spec.reward_field is not None:
        cost = -column(spec.reward_field)
    else:
        cost = np.zeros(len(obs))
        for t in spec.cost_terms:
            x = column(t["field"], t.get("at", "step"))
            op, w = t.get("op", "abs"), float(t.get("weight", 1.0))
            cost += w * (np.abs(x) if op == "abs" else x * x if op == "square" else x)
    if spec.terminal_cost is not None:
        cost = np.where(term, spec.terminal_cost, cost)
    cost = cost + 0.0  # no -0.0
    info = DatasetInfo(
        features=tuple(Feature(n, unit=units.get(n, "")) for n in obs_names), action_table=atable, gamma=spec.gamma,
        horizon=spec.horizon,
        propensity_source="unknown", name=spec.name,
        provenance={"inputs": summary["files"], "spec": spec.raw, "package_version": __version__,
                    "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                    "generator": "offline-adp ingest mcap"},
    )
    ds = TransitionDataset.from_arrays(
        info, episode_id=np.repeat([e.ep for e in eps], lengths), step=np.concatenate([np.arange(n) for n in lengths]),
        obs=obs, action=action, cost=cost, next_obs=nxt, terminated=term, truncated=trunc,
        source=np.repeat([e.src for e in eps], lengths), t_ns=cat("t"),
        extra={"src_file": pa.DictionaryArray.from_arrays(pa.array(cat("file").astype(np.int32)),
                                                          pa.array([str(p) for p in paths])),
               "src_log_time": pa.array(cat("log_time").astype(np.int64)), **commands,
               **({_EP_INDEX: pa.array(np.repeat(np.arange(len(eps), dtype=np.int32), lengths))} if mark else {})},
    )
    return ds


def vector_actions(raw: np.ndarray, spec: McapSpec) -> tuple[np.ndarray, ActionTable]:
    """A vector action (one column per ``[action] fields`` component) -> action indices.

    ``discrete``: each command is matched to the table's ``vectors`` component-wise
    (within 1e-9, relative); unmatched commands get index -1 (the doctor reports them).
    ``continuous`` kept as logged (no ``edges``/``n_bins``): kind ``"continuous"``
    (:func:`~offline_adp.ingest.actions.command_actions`). ``continuous`` binned: each
    component is binned on its own (``edges`` or ``n_bins`` quantiles; beyond the outer
    edges into the end bins) and the action is the cell of the product table (index =
    row-major over the components); each cell's value is the mean command of the cell
    (``bin_value = "mean"``; its centre when empty) or its centre
    (:func:`~offline_adp.ingest.actions.bin_product`); bounds recorded when declared.
    """
    a = spec.action
    dims = tuple(a.dims or ())
    x = np.asarray(raw, dtype=np.float64)
    if a.type == "continuous":
        return command_actions(x, a, dims, vector=True, bins=spec.action_bins or None, infer_binned_bounds=False)
    table = np.asarray(a.vectors, dtype=np.float64)
    tol = 1e-9 * np.maximum(1.0, np.abs(table))
    idx = np.full(len(x), -1, np.int64)
    for k in range(len(table)):
        idx[(np.abs(x - table[k]) <= tol[k]).all(axis=1)] = k
    values = [tuple(float(v) for v in row) for row in table]
    names = list(a.names) if a.names else [",".join(f"{d}={v:g}" for d, v in zip(dims, row, strict=True))
                                              for row in values]
    if len(names) != len(values):
        raise IngestError(f"action.names has {len(names)} entries for {len(values)} actions")
    atable = ActionTable(actions=tuple(Action(str(n), v) for n, v in zip(names, values, strict=True)), dims=dims,
                         kind="discrete", units=(a.unit,) * len(dims) if a.unit else ())
    return idx.astype(np.int32), atable


def assemble(parts: Sequence[Iterable[Message]], spec: McapSpec, *, name: str = "memory", on_error: str = "fail",
             flush_every: int = 5000) -> RecordingResult:
    """Assemble one recording given as decoded messages in file order (one iterable per
    file part) — the streaming assembler without MCAP files, e.g. for tests.

    ``flush_every``: messages between flushes (the result never depends on it for
    messages no later in the file than ``reorder_window``)."""
    files = [Path(f"{name}.mcap")] if len(parts) == 1 else [Path(f"{name}_{i}.mcap") for i in range(len(parts))]
    rec = _Recording(files, spec, on_error, 0, flush_every=flush_every)
    for i, msgs in enumerate(parts):
        if i and spec.per_file:
            rec._new_epoch_everywhere()
        rec.feed(msgs, i)
    return rec.finish()
