"""Data commands: ``simulate``, ``ingest parquet|mcap``, ``mcap-info``, ``validate``, ``inspect``."""

from __future__ import annotations

import argparse
import json
import sys

from offline_adp.cli._common import _progress, _say, log
from offline_adp.progress import is_terminal


# ---------------------------------------------------------------------------- simulate
def cmd_simulate(args: argparse.Namespace) -> int:
    from offline_adp.simulate import parse_problem_options, simulate

    options = parse_problem_options(args.problem_options) or None
    on_step, close = _progress(args.quiet)
    try:
        ds = simulate(args.problem, args.demonstrations, args.exploration, seed=args.seed, horizon=args.horizon,
                      problem_options=options, on_step=on_step)
    finally:
        close()
    from offline_adp.simulate.write import write_simulated

    written = write_simulated(ds, args.out, args.format, overwrite=args.overwrite, seed=args.seed)
    counts = ds.source_counts()
    _say(args, f"simulated {ds.info.problem}: {ds.n_episodes} episodes, {len(ds)} transitions {counts}")
    for p in written:
        print(p)
    return 0


# ---------------------------------------------------------------------------- ingest
def cmd_ingest_parquet(args: argparse.Namespace) -> int:
    from offline_adp.ingest.parquet import ingest_parquet

    res = ingest_parquet(
        args.inputs,
        args.spec,
        args.out,
        on_error=args.on_error,
        overwrite=args.overwrite,
        progress=None if args.quiet else (lambda m: log.info("  %s", m)),
    )
    print(res.report.to_text())
    s = res.summary()
    from offline_adp.data.validate import refuse_all_quarantined

    refuse_all_quarantined(args.out, s)
    print(f"wrote {args.out}: {s['episodes']} episode{'' if s['episodes'] == 1 else 's'}, {s['transitions']} "
          f"transitions, per source {s['per_source']}")
    if s["quarantined_rows"]:
        print(f"quarantined {s['quarantined_episodes']} episodes ({s['quarantined_rows']} rows) to "
              f"{args.out}/quarantine/ with a reason per row")
    if s["dropped_last_rows"]:
        print(f"dropped {s['dropped_last_rows']} last rows of step-table episodes without a next state (see "
              "docs/ingestion-spec.md)")
    return 0


#: What each per-topic count of an MCAP ingest is (they partition the messages read).
MESSAGE_COUNTS = {
    "messages_used": "used (decoded and placed against the clock's steps)",
    "messages_skipped": "skipped (topics not in the spec, not decoded)",
    "messages_unselected": "unselected, unused (no element matched the spec's selectors, e.g. another /tf frame pair)",
    "messages_orphaned": "orphaned, unused (held for an epoch the clock never reached)",
    "messages_stale": "stale, unused (held after a jump back of their stream that proved no restart)",
    "messages_dropped_late": "dropped late, unused (came after their epoch was over)",
    "messages_undecodable": "undecodable, unused",
}


def _print_message_counts(s: dict) -> None:
    """Per file and per topic: read = used + skipped + unselected + orphaned + stale + dropped late + undecodable."""
    rows = [("file", "read", "used", "skipped", "unused", "recovered")]
    for f in s["files"]:
        rec = f.get("recovered")
        unused = sum(sum(f[k].values()) for k in ("messages_unselected", "messages_orphaned", "messages_stale",
                                                  "messages_dropped_late", "messages_undecodable"))
        rows.append((f["path"], *(str(sum(f[k].values())) for k in ("messages_read", "messages_used",
                                                                    "messages_skipped")), str(unused),
                     "-" if rec is None else f"{rec['messages']} msgs, damage: {rec['text'].split(', ', 1)[1]}"))
    width = [max(len(r[i]) for r in rows) for i in range(5)]
    for r in rows:
        print(f"  {r[0]:<{width[0]}}" + "".join(f"  {r[i]:>{width[i]}}" for i in range(1, 5)) + f"  {r[5]}")
    print("  messages per topic: read = used + skipped + unselected + orphaned + stale + dropped late + undecodable")
    print(f"    read: {s['messages_read']}")
    for k, text in MESSAGE_COUNTS.items():
        if s[k] or k == "messages_used":
            print(f"    {text}: {s[k]}")


def cmd_ingest_mcap(args: argparse.Namespace) -> int:
    from offline_adp.ingest.mcap import ingest_mcap, load_mcap_spec, resolve_sources

    spec = load_mcap_spec(args.spec)  # a regular file of bounded size (read through read_config_bytes)
    n_rec = len(resolve_sources(args.inputs, spec))
    bar = None
    if not args.quiet and n_rec > 1 and is_terminal():
        from tqdm import tqdm

        bar = tqdm(total=n_rec, unit="recording", desc="ingest mcap", file=sys.stderr)
    progress = (lambda done, total: bar.update(done - bar.n)) if bar is not None else None
    try:
        ds, s = ingest_mcap(args.inputs, spec, args.out, on_error=args.on_error, overwrite=args.overwrite,
                            jobs=args.jobs, progress=progress)
    finally:
        if bar is not None:
            bar.close()
    from offline_adp.data.validate import refuse_all_quarantined

    refuse_all_quarantined(args.out, s)
    print(f"doctor: {'OK' if s['doctor']['ok'] else s['doctor']}")
    _print_message_counts(s)
    print(f"wrote {args.out}: {s['episodes']} episode{'' if s['episodes'] == 1 else 's'}, {s['transitions']} "
          f"transitions, per source {s['per_source']}")
    notes = {"dropped_steps": "steps dropped for missing values (missing = 'drop_step')",
             "outside_episode_steps": "steps outside any start/end episode", "condition_steps":
             "steps under an end condition", "short_episodes": "episodes with fewer than 2 steps",
             "incomplete_episodes": "episodes without their end event", "episodes_lost_to_damage":
             "episodes that lost messages to damage", "restarts": "time-source restarts (episode boundaries)",
             "cut_episodes": "episodes the recording ends inside (cut)", "episode_splits":
             "episodes split at dropped steps",
             "gap_splits": "episodes started at a pause in the log (over [episodes] gap; raise it if the robot went "
             f"on), the longest {s.get('longest_gap_s', 0):.3g} s",
             "episodes_without_command": "episodes with a step without a command",
             "quarantined_rows": f"rows set aside with a reason in {args.out}/quarantine/",
             "dropped_rows": "rows of rejected episodes left out (on_error = fail)"}
    for k, text in notes.items():
        if s.get(k):
            print(f"  {text}: {s[k]}")
    for f in s.get("skipped_files", []):
        print(f"  skipped {', '.join(f['files'])}: {f['error']}")
    return 0


def cmd_mcap_info(args: argparse.Namespace) -> int:

    from offline_adp.ingest.mcap import mcap_info
    from offline_adp.ingest.mcap.info import info_inputs

    for path in info_inputs(args.files):
        info = mcap_info(path)
        if args.json:
            print(json.dumps(info, indent=2, default=str))
            continue
        rng = info.get("time_range_ns")
        print(f"{info['file']}: profile {info['profile'] or '-'}, library {info['library']!r}, summary "
              f"{info['summary']}, compression {info.get('compression', '?')}, {info['messages']} messages"
              + (f", log_time {rng[0] / 1e9:.3f} .. {rng[1] / 1e9:.3f} s" if rng else ""))
        if info.get("damage"):
            print(f"  DAMAGE: {info['damage']}")
        for topic, t in sorted(info["topics"].items()):
            rate = f"{t['rate_hz']} Hz" if t["rate_hz"] is not None else t["status"]
            extra = "".join(f", {t[k]} {k}" for k in ("restarts", "gaps") if t.get(k))
            if t.get("gaps_at"):  # where the pauses are (the gap rule may start an episode there)
                extra += " (" + ", ".join(f"+{g['after_s']:.1f} s for {g['length_s']:.3g} s" for g in t["gaps_at"]) \
                    + (", ..." if t["gaps"] > len(t["gaps_at"]) else "") + ")"
            print(f"  {topic:<32} {t['schema']:<40} {t['encoding']:<9} {t['messages']:>7} msgs  {rate}{extra}")
            if t["field_info"]:
                shown = [f"{x['path']} ({x['type']}: {x['sample']!r})" for x in t["field_info"][:40]]
                print("      fields: " + ", ".join(shown) + (" ..." if len(t["field_info"]) > 40 else ""))
            elif t["status"].startswith("not decodable"):
                print(f"      {t['status']}")
            if t.get("quaternions"):  # a heading is one feature; a quaternion's four flip sign together
                print("      quaternions (a heading in rad: yaw = { yaw_of = \"PATH\" }): "
                      + ", ".join(t["quaternions"][:8]) + (" ..." if len(t["quaternions"]) > 8 else ""))
            for where, counts in (t.get("list_values") or {}).items():  # [0] is not one thing in every message
                head, key = where.split("[].", 1)
                seen = ", ".join(f"{v} in {n}" for v, n in list(counts.items())[:8]) + (", ..." if len(counts) > 8
                                                                                          else "")
                twice = (t.get("list_values_repeated") or {}).get(where, [])
                pick = next((v for v in counts if v not in twice), None)
                how = (f"read one with {head}[{key}={pick}]" if pick is not None else
                       f"every value is in some message twice, so {key} cannot select one element")
                print(f"      {head}[0] is another element from message to message ({key} in the first "
                      f"{min(t['messages'], 2000)} messages: {seen}): {how}"
                      + (f" (twice in one message: {twice[:8]})" if twice else ""))
    return 0


# ---------------------------------------------------------------------------- validate / inspect
def cmd_validate(args: argparse.Namespace) -> int:
    from offline_adp.data.validate import validate_directory

    report = validate_directory(args.dataset)
    if args.json:
        print(json.dumps({**report.summary(), "findings": report.findings.head(args.max_findings).to_dict("records")},
                         default=str, indent=2))
    else:
        print(report.to_text(max_findings=args.max_findings))
    return 0 if report.ok else 1


def cmd_inspect(args: argparse.Namespace) -> int:
    from offline_adp.data.summary import dataset_summary, summary_text

    report = dataset_summary(args.dataset)
    print(json.dumps(report, indent=2) if args.json else summary_text(report))
    return 0
