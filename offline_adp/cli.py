"""``offline-adp``: a thin command line over the library's functions.

Every subcommand's ``--help`` ends with an example. Errors of our own types print one
clear message (no traceback) and exit with status 2; ``--traceback`` shows the stack.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from offline_adp._version import __version__
from offline_adp.errors import OfflineADPError
from offline_adp.progress import CLI_LOGGER, get_logger, is_terminal

#: The command line's own lines (progress, summaries): INFO records shown by default,
#: hidden by -q or --log-level WARNING (see offline_adp.progress.apply_logging_options).
log = get_logger(CLI_LOGGER)

FORMATS = ("dataset", "parquet", "csv", "mcap-json", "mcap-ros2")
#: The algorithm registry's names (offline_adp.algorithms.registry; a test keeps them equal).
ALGORITHM_NAMES = ("fqi", "fqe", "api", "cpi", "psdp")


def _progress(quiet: bool):
    """A step-progress callback: a tqdm bar on stderr when it is a terminal, unless quiet
    (in a log file the command's summary line says what was done)."""
    if quiet or not is_terminal():
        return None, lambda: None
    from tqdm import tqdm

    bar = tqdm(unit="step", desc="simulating", leave=False, file=sys.stderr)
    last = {"t": -1}

    def on_step(t: int) -> None:
        if t != last["t"]:
            last["t"] = t
            bar.update(1)

    return on_step, bar.close


def _positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (a usage error, exit 2, otherwise)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _say(args: argparse.Namespace, msg: str) -> None:
    """A progress or summary line on stderr (an INFO record of the CLI logger: -q hides it)."""
    if not getattr(args, "quiet", False):
        log.info("%s", msg)


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
    print(f"wrote {args.out}: {s['episodes']} episodes, {s['transitions']} transitions, per source {s['per_source']}")
    if s["quarantined_rows"]:
        print(f"quarantined {s['quarantined_episodes']} episodes ({s['quarantined_rows']} rows) to {args.out}/quarantine/ with a reason per row")
    if s["dropped_last_rows"]:
        print(f"dropped {s['dropped_last_rows']} last rows of step-table episodes without a next state (see docs/ingestion-spec.md)")
    return 0


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
    rows = [("file", "used", "skipped", "recovered")]
    for f in s["files"]:
        rec = f.get("recovered")
        rows.append((f["path"], str(sum(f["messages_used"].values())), str(sum(f["messages_skipped"].values())),
                     "-" if rec is None else f"{rec['messages']} msgs, damage: {rec['text'].split(', ', 1)[1]}"))
    width = [max(len(r[i]) for r in rows) for i in range(3)]
    for r in rows:
        print(f"  {r[0]:<{width[0]}}  {r[1]:>{width[1]}}  {r[2]:>{width[2]}}  {r[3]}")
    print(f"  messages used per topic: {s['messages_used']}")
    if s["messages_skipped"]:
        print(f"  messages skipped (topics not in the spec, not decoded): {s['messages_skipped']}")
    print(f"wrote {args.out}: {s['episodes']} episodes, {s['transitions']} transitions, per source {s['per_source']}")
    notes = {"dropped_steps": "steps dropped for missing values (missing = 'drop_step')",
             "outside_episode_steps": "steps outside any start/end episode", "condition_steps":
             "steps under an end condition", "short_episodes": "episodes with fewer than 2 steps",
             "incomplete_episodes": "episodes without their end event", "episodes_lost_to_damage":
             "episodes that lost messages to damage", "restarts": "time-source restarts (episode boundaries)",
             "cut_episodes": "episodes the recording ends inside (cut)", "episode_splits":
             "episodes split at dropped steps", "orphan_messages": "messages of an epoch without clock messages",
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
        print(f"{info['file']}: profile {info['profile'] or '-'}, library {info['library']!r}, summary {info['summary']}, "
              f"compression {info.get('compression', '?')}, {info['messages']} messages"
              + (f", log_time {rng[0] / 1e9:.3f} .. {rng[1] / 1e9:.3f} s" if rng else ""))
        if info.get("damage"):
            print(f"  DAMAGE: {info['damage']}")
        for topic, t in sorted(info["topics"].items()):
            rate = f"{t['rate_hz']} Hz" if t["rate_hz"] is not None else t["status"]
            extra = "".join(f", {t[k]} {k}" for k in ("restarts", "gaps") if t.get(k))
            print(f"  {topic:<32} {t['schema']:<40} {t['encoding']:<9} {t['messages']:>7} msgs  {rate}{extra}")
            if t["field_info"]:
                shown = [f"{x['path']} ({x['type']}: {x['sample']!r})" for x in t["field_info"][:40]]
                print("      fields: " + ", ".join(shown) + (" ..." if len(t["field_info"]) > 40 else ""))
            elif t["status"].startswith("not decodable"):
                print(f"      {t['status']}")
    return 0


# ---------------------------------------------------------------------------- validate / inspect
def cmd_validate(args: argparse.Namespace) -> int:
    from offline_adp.data.validate import validate_directory

    report = validate_directory(args.dataset)
    if args.json:
        print(json.dumps({**report.summary(), "findings": report.findings.head(args.max_findings).to_dict("records")}, default=str, indent=2))
    else:
        print(report.to_text(max_findings=args.max_findings))
    return 0 if report.ok else 1


def cmd_inspect(args: argparse.Namespace) -> int:
    from offline_adp.data.summary import dataset_summary, summary_text

    report = dataset_summary(args.dataset)
    print(json.dumps(report, indent=2) if args.json else summary_text(report))
    return 0


# ---------------------------------------------------------------------------- fit
def cmd_fit(args: argparse.Namespace) -> int:
    from offline_adp.algorithms.registry import get_algorithm
    from offline_adp.runs import fit_run, load_config

    params = load_config(args.config, args.algorithm)
    entry = get_algorithm(args.algorithm)
    caveat = getattr(entry.estimator_class(), "mode_caveat", None)
    if caveat is not None and caveat(params.get("mode")):
        log.warning("%s", caveat(params.get("mode")))
    bar = None
    total = params.get("horizon") or params.get("n_iterations", 50)
    if not args.quiet and entry.resumable and is_terminal():
        from tqdm import tqdm

        bar = tqdm(total=total, desc=f"fit {args.algorithm}", unit="it", file=sys.stderr)
    quarters = {max(1, (int(total) * q) // 4) for q in (1, 2, 3, 4)} if total else set()

    def on_iteration(row: dict) -> None:
        it = row.get("iteration")
        log.debug("fit %s iteration %s: sup|dQ| %.4g, Bellman residual %.4g, start value %.4g, %.2f s", args.algorithm, it,
                  *(float(row.get(k) if row.get(k) is not None else float("nan"))
                    for k in ("sup_dq", "bellman_residual", "start_value", "wall_time")))
        if bar is None and it in quarters:  # in a log: four lines, not one per iteration
            log.info("fit %s: iteration %s/%s, sup|dQ| %.4g", args.algorithm, it, total,
                     float(row.get("sup_dq") if row.get("sup_dq") is not None else float("nan")))
        if bar is not None:
            if bar.n == 0 and row["iteration"] > 1:
                bar.update(row["iteration"] - 1)  # resumed
            bar.set_postfix(residual=f"{row['bellman_residual']:.3g}", dq=f"{row['sup_dq']:.3g}", s=f"{row['wall_time']:.2f}")
            bar.update(1)

    try:
        est = fit_run(args.dataset, args.out, algorithm=args.algorithm, params=params or None, resume=args.resume,
                      on_iteration=on_iteration)
    finally:
        if bar is not None:
            bar.close()
    for line in fit_summary_lines(est, args.algorithm):
        print(line)
    print(f"{args.out}/model")
    return 0


def fit_summary_lines(est: object, algorithm: str) -> list[str]:
    """What ``fit`` prints: the last iteration's numbers, and the convergence verdict when there is one."""
    import pandas as pd

    hist = getattr(est, "history_", None)
    n = 0 if hist is None else len(hist)
    if isinstance(hist, pd.DataFrame) and n and {"sup_dq", "bellman_residual", "start_value"} <= set(hist.columns):
        h = hist.iloc[-1]
        mode = getattr(est, "mode_", None)
        how = f" ({mode} mode{', auto' if getattr(est, 'mode', None) == 'auto' else ''})" if mode else ""
        lines = [f"fitted {algorithm}{how}: {n} iterations, last sup|dQ| {h['sup_dq']:.4g}, Bellman residual "
                 f"{h['bellman_residual']:.4g}, mean start value {h['start_value']:.4g}"]
        from offline_adp.algorithms.fqi import structure_builds

        builds = structure_builds(hist)
        if builds:
            screened = any(b["screen"] is not None for b in builds)
            grown = [b["trees"] for b in builds if not b["constant"] and b["trees"]]
            early = (getattr(est, "early_build_trees", None) is not None and bool(grown)
                     and any(b["screen"] is None and not b["constant"] and (b["trees"] or 0) < max(grown)
                             for b in builds))  # an unscreened build grew fewer trees than another
            caveat = ("the screen" if screened else "") + (" and " if screened and early else "") + ("early builds" if early else "")
            by = sorted({b["builder"] for b in builds if b["builder"]})
            lines.append(f"tree structures: {len(builds)} built (iterations {', '.join(str(b['iteration']) for b in builds)}), "
                         f"trees {'/'.join('const' if b['constant'] else str(b['trees'] or '?') for b in builds)}"
                         + (f", grown by {' and '.join(by)}" if by else "")
                         + (f" ({caveat}: lost score on CartPole at gamma 0.95; compare with a fit that grows every"
                            " forest whole, docs/fqi-modes.md)" if caveat else ""))
    else:
        lines = [f"fitted {algorithm}: {n} history rows"]
        if isinstance(hist, pd.DataFrame) and n:
            lines.append(hist.tail(5).to_string(index=False))
    verdict = getattr(est, "verdict_", None)
    if verdict is not None:
        msg = getattr(est, "verdict_message_", "")
        lines.append(f"verdict: {verdict}" + (f" ({msg})" if msg else ""))
    return lines


def cmd_evaluate(args: argparse.Namespace) -> int:
    from offline_adp.evaluation.run import evaluate_run
    from offline_adp.evaluation.summary import summary_lines

    def say(msg: str) -> None:
        log.info("  %s", msg)

    from offline_adp.algorithms.registry import get_algorithm
    from offline_adp.config import parse_json_object

    fqe = get_algorithm("fqe").check_params(parse_json_object(args.fqe_params, "--fqe-params"), "--fqe-params") \
        if args.fqe_params else None
    m = evaluate_run(args.run, dataset=args.dataset, simulator=args.simulator, n_episodes=args.episodes,
                     n_boot=args.bootstrap, n_boot_fqe=args.fqe_bootstrap, fqe_params=fqe, horizon=args.horizon,
                     estimand=args.estimand, seed=args.seed, progress=say)
    for line in summary_lines(m):
        print(line)
    print(f"{args.run}/evaluation/metrics.json")
    return 0



def cmd_run(args: argparse.Namespace) -> int:
    from offline_adp.pipeline import run_pipeline

    def say(msg: str) -> None:
        log.info("%s", msg)

    overrides = {}
    for item in args.set or []:
        key, _, value = item.partition("=")
        if not _:
            raise OfflineADPError(f"--set {item!r}: expected KEY=VALUE, e.g. data.exploration=20")
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key] = value
    engine = None
    if args.engine or args.scheduler:
        engine = {"kind": args.engine or "dask", **({"address": args.scheduler} if args.scheduler else {})}
    run = run_pipeline(args.pipeline, out=args.out, runs_root=args.runs, from_stage=args.from_stage, force=args.force,
                       say=say, overrides=overrides, engine=engine)
    from offline_adp.data.rundir import read_json_file

    man = read_json_file(run / "manifest.json")
    for name, st in man["stages"].items():
        print(f"  {name:9s} {st.get('status')}{' (reused)' if st.get('reused') else ''}"
              + (f" {st['seconds']:.1f} s" if st.get("seconds") is not None and not st.get("reused") else ""))
    if (run / "metrics.json").exists():
        from offline_adp.evaluation.summary import summary_lines

        for line in summary_lines(read_json_file(run / "metrics.json")):
            print(line)
    print(run / "report.html" if (run / "report.html").exists() else run)
    return 0


def cmd_schema(args: argparse.Namespace) -> int:
    from offline_adp.schemas import schemas, write_schemas

    if args.write:
        for p in write_schemas(args.write):
            print(p)
        return 0
    all_ = schemas()
    if args.kind not in all_:
        raise OfflineADPError(f"schema {args.kind!r}: known kinds are {sorted(all_)}")
    print(json.dumps(all_[args.kind], indent=2, sort_keys=True))
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from offline_adp.evaluation.report import build_report

    path = build_report(args.run)
    print(path)
    return 0


# ---------------------------------------------------------------------------- export / annotate / convert
def cmd_export(args: argparse.Namespace) -> int:
    from offline_adp.data.io import locked_directory
    from offline_adp.deploy import export_run

    _file_output(args.out, "--out", "an ONNX file")
    with locked_directory(args.out, what="file"):  # the exporter's temporary: removed on failure (main)
        print(export_run(args.run, args.out, fmt=args.format, dataset=args.dataset, overwrite=args.overwrite,
                         input_dtype=args.input_dtype))
    return 0


def _file_output(path: str, flag: str, what: str) -> None:
    """A command's output that must be a file: an existing directory there is an error."""
    from pathlib import Path

    from offline_adp.errors import WriteError

    p = Path(path)
    if p.is_dir() and not p.is_symlink():
        raise WriteError(f"{flag} {p} is a directory; name {what} to write (e.g. {p / 'out'})")


def cmd_annotate(args: argparse.Namespace) -> int:
    from offline_adp.annotate import annotate_mcap

    s = annotate_mcap(args.run, args.log, args.out, spec=args.spec, dataset=args.dataset, overwrite=args.overwrite)
    _say(args, f"annotated {s['steps']} steps ({s['messages_copied']} log messages copied); policy agrees with the log "
         f"on {s['agreement']:.1%} of steps, {s['out_of_support']} steps out of support; topics {', '.join(s['topics'])}")
    print(s["out"])
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    from offline_adp.formats import convert

    if args.to_format == "d4rl":
        _file_output(args.out, "--out", "a .npz file")
    print(convert(args.source, args.out, from_format=args.from_format, to_format=args.to_format, overwrite=args.overwrite))
    return 0


# ---------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    fmt = argparse.RawDescriptionHelpFormatter
    p = argparse.ArgumentParser(
        prog="offline-adp",
        formatter_class=fmt,
        description="Offline approximate dynamic programming over logged robot and vehicle data.",
        epilog="example:\n  offline-adp simulate path_tracking --out data/pt && offline-adp inspect data/pt",
    )
    p.add_argument("--version", action="version", version=f"offline-adp {__version__}")
    p.add_argument("--traceback", action="store_true", help="show the full traceback on errors")
    p.epilog += "\n\nglobal options (before or after the subcommand): -v/--verbose, -q/--quiet, --log-level LEVEL"
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    from offline_adp.envs import PROBLEM_NAMES

    s = sub.add_parser(
        "simulate",
        help="log demonstrations + exploration on a reference problem",
        formatter_class=fmt,
        description="Write a logged dataset from a reference problem: demonstrations (a noisy expert) plus "
        "exploration (random actions), labelled by source, with logged propensities.",
        epilog="examples:\n"
        "  offline-adp simulate car_on_hill --exploration 1000 --demonstrations 0 --out data/coh\n"
        "  offline-adp simulate path_tracking --format parquet --out logs/pt.parquet\n"
        "  offline-adp simulate path_tracking --format mcap-ros2 --out logs/ros2/",
    )
    s.add_argument("problem", choices=PROBLEM_NAMES)
    s.add_argument("--out", required=True, help="dataset directory, raw table file, or MCAP directory")
    s.add_argument("--format", choices=FORMATS, default="dataset", help="output format (default: dataset)")
    s.add_argument("--demonstrations", type=int, default=100, help="demonstration episodes (default 100)")
    s.add_argument("--exploration", type=int, default=100, help="exploration episodes (default 100)")
    s.add_argument("--horizon", type=int, default=None, help="episode time limit (default: the problem's)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--problem-options", default=None, help='JSON keyword arguments, e.g. \'{"n_states": 30}\'')
    s.add_argument("--overwrite", action="store_true")
    s.add_argument("--quiet", "-q", action="store_true")
    s.set_defaults(func=cmd_simulate)

    ing = sub.add_parser("ingest", help="turn logs into a validated dataset directory")
    ingsub = ing.add_subparsers(dest="source_format", metavar="FORMAT", required=True)
    ip = ingsub.add_parser(
        "parquet",
        help="Parquet/CSV transition or step tables",
        formatter_class=fmt,
        description="Ingest Parquet or CSV tables through a TOML spec (docs/ingestion-spec.md); the dataset "
        "doctor runs at the end.",
        epilog="example:\n  offline-adp ingest parquet logs/*.parquet --spec logs/pt.spec.toml --out data/pt --on-error quarantine",
    )
    ip.add_argument("inputs", nargs="+", help="Parquet or CSV files")
    ip.add_argument("--spec", required=True, help="TOML ingestion spec")
    ip.add_argument("--out", required=True, help="dataset directory to write")
    ip.add_argument("--on-error", choices=("fail", "quarantine"), default=None, help="default: the spec's on_error (fail)")
    ip.add_argument("--overwrite", action="store_true")
    ip.add_argument("--quiet", "-q", action="store_true")
    ip.set_defaults(func=cmd_ingest_parquet)

    im = ingsub.add_parser(
        "mcap",
        help="MCAP logs (JSON, ROS 2 CDR, protobuf)",
        formatter_class=fmt,
        description="Ingest MCAP recordings through a TOML spec: a clock topic (or rate) defines the steps, streams "
        "are aligned to it (nearest, previous, linear; max_age), episodes come from an event topic, time gaps, time "
        "restarts or field conditions, the cost is a field, a negated reward or a declared weighted sum of terms. "
        "Files stream through bounded memory; parts of a split recording (NAME_0.mcap, NAME_1.mcap ...) form one "
        "recording. Use `offline-adp mcap-info` to find topics and field paths (docs/ingestion-spec.md).",
        epilog="example:\n  offline-adp ingest mcap logs/*.mcap --spec data/specs/path_tracking_mcap.toml --out data/pt "
        "--jobs 2",
    )
    im.add_argument("inputs", nargs="*", help="MCAP files or globs (default: the spec's [sources] files)")
    im.add_argument("--spec", required=True)
    im.add_argument("--out", required=True)
    im.add_argument("--on-error", choices=("fail", "quarantine"), default=None,
                    help="damaged files and doctor findings: fail (default: the spec's on_error) or keep what is sound")
    im.add_argument("--jobs", "-j", type=int, default=1, help="recordings ingested in parallel processes (output "
                    "order does not depend on it)")
    im.add_argument("--overwrite", action="store_true")
    im.add_argument("--quiet", "-q", action="store_true")
    im.set_defaults(func=cmd_ingest_mcap)

    mi = sub.add_parser(
        "mcap-info",
        help="what an MCAP file holds: topics, schemas, rates, field paths",
        formatter_class=fmt,
        description="Per file: profile, library, summary/index, compression, time range; per topic: schema, "
        "encoding, message count, rate and the field paths of the first decodable message.",
        epilog="example:\n  offline-adp mcap-info logs/run_0.mcap",
    )
    mi.add_argument("files", nargs="+")
    mi.add_argument("--json", action="store_true")
    mi.set_defaults(func=cmd_mcap_info)

    v = sub.add_parser(
        "validate",
        help="run the dataset doctor",
        formatter_class=fmt,
        description="Check every rule of the dataset format; each finding names file, row, episode, step and column. "
        "Exit status 1 if anything is found.",
        epilog="example:\n  offline-adp validate data/pt --max-findings 50",
    )
    v.add_argument("dataset")
    v.add_argument("--max-findings", type=int, default=20)
    v.add_argument("--json", action="store_true")
    v.set_defaults(func=cmd_validate)

    f = sub.add_parser(
        "fit",
        help="fit an algorithm on a dataset into a run directory",
        formatter_class=fmt,
        description="Fit an algorithm on a dataset directory: fqi (fitted Q-iteration), fqe (fitted Q evaluation of "
        "a saved policy), api (approximate policy iteration), cpi (conservative policy iteration), psdp (policy "
        "search by dynamic programming; needs a simulator). Parameters come from --config, a TOML file whose "
        "[<algorithm>] table holds the estimator's parameters (api/cpi: an [<algorithm>.fqe] sub-table for the "
        "evaluator; cpi/psdp: simulator = \"NAME\"; psdp: baseline_source, drop_features). fqi checkpoints every "
        "iteration; after Ctrl-C or a crash, --resume continues from the last completed iteration.",
        epilog="examples:\n  offline-adp fit data/pt --algorithm fqi --config fqi.toml --out runs/pt-fqi\n"
        "  offline-adp fit data/pt --algorithm psdp --config psdp.toml --out runs/pt-psdp\n\n"
        "with fqi.toml:\n  [fqi]\n  gamma = 0.95\n  n_iterations = 50\n  regressor = \"extra_trees\"\n"
        "  [fqi.regressor_params]\n  n_estimators = 50\n\n"
        "and psdp.toml:\n  [psdp]\n  simulator = \"path_tracking\"\n  horizon = 50\n  learner = \"regression\"\n"
        "  baseline_source = \"demonstration\"\n  drop_features = [\"s\"]",
    )
    f.add_argument("dataset")
    f.add_argument("--algorithm", default="fqi", choices=list(ALGORITHM_NAMES))
    f.add_argument("--config", default=None, help="TOML file with the algorithm's parameters")
    f.add_argument("--out", required=True, help="run directory")
    f.add_argument("--resume", action="store_true", help="continue an interrupted run in --out")
    f.add_argument("--quiet", "-q", action="store_true")
    f.set_defaults(func=cmd_fit)

    e = sub.add_parser(
        "evaluate",
        help="evaluate a run's policy: simulator rollouts, off-policy estimates, shift diagnostics",
        formatter_class=fmt,
        description="Evaluate the policy in RUN_DIR/model on the run's dataset: Monte-Carlo rollouts when a simulator "
        "is known (the dataset's reference problem or --simulator), the behaviour policy (logged propensities or a "
        "classifier), off-policy estimates with bootstrap intervals (FQE, IS, WIS, PDIS, WPDIS, DR, WDR, MIS), per-step "
        "density ratios with diagnostics, and the PSDP bound. Writes RUN_DIR/evaluation/metrics.json.",
        epilog="examples:\n  offline-adp evaluate runs/pt-fqi\n  offline-adp evaluate runs/pt-fqi --simulator none --dataset data/pt\n"
        "  offline-adp report runs/pt-fqi",
    )
    e.add_argument("run", help="run directory (from offline-adp fit)")
    e.add_argument("--dataset", default=None, help="dataset directory (default: the one the run was fitted on)")
    e.add_argument("--simulator", default=None, help="reference problem to roll out in, gym:ENV_ID (a registered gymnasium "
                   "environment; features by declared order, actions by the action table's values), or 'none' "
                   "(default: the dataset's problem)")
    e.add_argument("--episodes", type=_positive_int, default=500, help="rollout episodes (default 500)")
    e.add_argument("--bootstrap", type=int, default=200, help="bootstrap replicates for IS/DR/MIS (default 200)")
    from offline_adp.evaluation import FQE_BOOTSTRAP_DEFAULT

    e.add_argument("--fqe-bootstrap", type=int, default=FQE_BOOTSTRAP_DEFAULT,
                   help="FQE bootstrap replicates (default: 200 when cheap, else 50; 0: no interval)")
    e.add_argument("--estimand", choices=["finite", "infinite"], default="finite",
                   help="the value to estimate: over the logged horizon (default) or infinite-horizon discounted (FQE only)")
    e.add_argument("--fqe-params", default=None, help='JSON FittedQEvaluation parameters, e.g. \'{"mode": "refit"}\'')
    e.add_argument("--horizon", type=_positive_int, default=None, help="the evaluation horizon (default: the data's longest episode; with --simulator gym:ENV_ID the environment's "
                   "own time limit, e.g. 500 for CartPole-v1)")
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--quiet", "-q", action="store_true")
    e.set_defaults(func=cmd_evaluate)

    rp = sub.add_parser(
        "run",
        help="run a pipeline file (ingest -> validate -> fit -> evaluate -> report) into a run directory",
        formatter_class=fmt,
        description="Run the stages of a pipeline file into runs/<name>__<seed>__<timestamp>/ (or --out). A stage "
        "whose inputs and settings are unchanged is reused; an interrupted run continues from its last completed "
        "stage (FQI from its last checkpointed iteration). The manifest (manifest.json) records input fingerprints, "
        "the config hash, versions and per-stage status and timings. See offline_adp/pipeline.py for the file format.",
        epilog="examples:\n  offline-adp run pipelines/driving.toml\n  offline-adp run pipelines/driving.toml --from evaluate\n"
        "  offline-adp run pipelines/car_on_hill.toml --set data.exploration=200 --out runs/coh-small",
    )
    rp.add_argument("pipeline", help="pipeline TOML file")
    rp.add_argument("--out", default=None, help="run directory (default: continue the latest runs/<name>__<seed>__*)")
    rp.add_argument("--runs", default="runs", help="folder of run directories (default: runs)")
    rp.add_argument("--from", dest="from_stage", default=None, choices=["data", "validate", "fit", "evaluate", "report"],
                    help="recompute this stage and the ones after it")
    rp.add_argument("--force", action="store_true", help="start a fresh run directory, reusing nothing")
    rp.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a setting, e.g. evaluate.episodes=50")
    rp.add_argument("--engine", default=None, choices=["local", "dask"],
                    help="execution engine (default: the file's [engine], else local); dask needs the dask extra")
    rp.add_argument("--scheduler", default=None, metavar="ADDRESS",
                    help="an existing Dask scheduler, e.g. tcp://10.0.0.5:8786 (default: a LocalCluster on 127.0.0.1)")
    rp.add_argument("--quiet", "-q", action="store_true")
    rp.set_defaults(func=cmd_run)

    r = sub.add_parser(
        "report",
        help="write RUN_DIR/report/report.html with figures from an evaluated run",
        formatter_class=fmt,
        description="Build a single self-contained report.html (figures embedded, also saved as PNG in report/figures/) "
        "from RUN_DIR/evaluation/ and the fitted model.",
        epilog="example:\n  offline-adp evaluate runs/pt-fqi && offline-adp report runs/pt-fqi",
    )
    r.add_argument("run")
    r.set_defaults(func=cmd_report)

    sc = sub.add_parser(
        "schema",
        help="print the JSON Schema of a configuration file type (for editors checking TOML)",
        formatter_class=fmt,
        description="Print the JSON Schema of a pipeline file or a fit config, or write them all to a folder.",
        epilog="examples:\n  offline-adp schema pipeline > pipeline.schema.json\n  offline-adp schema --write docs/schemas",
    )
    sc.add_argument("kind", nargs="?", default="pipeline", help="pipeline | fit-config (default: pipeline)")
    sc.add_argument("--write", nargs="?", const="docs/schemas", default=None, metavar="DIR",
                    help="write every schema as DIR/NAME.schema.json (default DIR: docs/schemas)")
    sc.set_defaults(func=cmd_schema)

    cp = sub.add_parser(
        "compare",
        help="rank candidate policies (run directories) on the same logs, off-policy",
        formatter_class=fmt,
        description="Evaluate every run's policy on one dataset (reusing matching evaluations) and rank them by the "
        "most reliable off-policy estimate, with intervals, shift and convergence verdicts; with a simulator, score "
        "the ranking against the rollout truth (Spearman, Kendall, regret of the top pick).",
        epilog="examples:\n  offline-adp compare runs/fqi-a runs/fqi-b runs/api --json compare.json   # + compare.html\n"
        "  offline-adp compare runs/fqi-a runs/fqi-b --report cmp/report.html",
    )
    cp.add_argument("runs", nargs="+", help="run directories (at least two)")
    cp.add_argument("--dataset", default=None, help="dataset directory (default: the one the runs were fitted on)")
    cp.add_argument("--simulator", default=None, help="as for evaluate: a reference problem or 'none'")
    cp.add_argument("--estimator", default=None, help="rank by this estimator (default: the most reliable for all)")
    cp.add_argument("--episodes", type=_positive_int, default=300, help="rollout episodes per candidate (default 300)")
    cp.add_argument("--force", action="store_true", help="re-evaluate even when a matching evaluation exists")
    cp.add_argument("--json", default=None, metavar="FILE", help="also write the comparison as JSON")
    cp.add_argument("--report", default=None, metavar="FILE", help="HTML report to write (default: next to --json with "
                    ".html, else compare.html in the runs' common parent directory, e.g. runs/compare.html)")
    cp.add_argument("--quiet", "-q", action="store_true")

    def cmd_compare(args: argparse.Namespace) -> int:
        from offline_adp.evaluation.compare import cli as compare_cli

        return compare_cli(args)

    cp.set_defaults(func=cmd_compare)

    i = sub.add_parser(
        "inspect",
        help="summarise a dataset",
        formatter_class=fmt,
        description="Schema, counts per source, action coverage, episode lengths and cost statistics.",
        epilog="example:\n  offline-adp inspect data/pt --json",
    )
    i.add_argument("dataset")
    i.add_argument("--json", action="store_true")
    i.set_defaults(func=cmd_inspect)

    ex = sub.add_parser(
        "export",
        help="export a run's policy for deployment (ONNX)",
        formatter_class=fmt,
        description="Write the policy of RUN_DIR as an ONNX model: input `observation` (double, N x d, columns in the "
        "order of the feature names stored in the model metadata with their units; time-indexed policies also take "
        "`t`), outputs `action` (the action table's values), `action_index` and, for greedy policies, `q_values`. "
        "Stochastic policies (CPI mixtures) are refused. See docs/deploy.md.",
        epilog="example:\n  offline-adp export runs/pt-fqi --format onnx --out policy.onnx",
    )
    ex.add_argument("run", help="run directory (from offline-adp fit or run)")
    ex.add_argument("--format", default="onnx", choices=["onnx"])
    ex.add_argument("--out", required=True, help="file to write")
    ex.add_argument("--dataset", default=None, help="dataset for the feature names (default: the run's)")
    ex.add_argument("--input-dtype", default="float64", choices=["float64", "float32"],
                    help="element type of the `observation` input (float32: what robot stacks usually publish)")
    ex.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    ex.set_defaults(func=cmd_export)

    an = sub.add_parser(
        "annotate",
        help="write a copy of an MCAP log with the policy's actions, Q-gap, density ratio and support along it",
        formatter_class=fmt,
        description="Ingest LOG with the run's MCAP spec (from its dataset's provenance, or --spec) and write OUT: every "
        "message of LOG plus JSON topics (with JSON schemas) at each logged step's time: /offline_adp/action (policy vs "
        "logged action), /offline_adp/q_gap, /offline_adp/density_ratio, /offline_adp/support (out-of-support flag). "
        "Open OUT in Foxglove to plot them on the log's timeline.",
        epilog="example:\n  offline-adp annotate runs/pt-fqi --log logs/demonstration.mcap --out annotated.mcap",
    )
    an.add_argument("run", help="run directory")
    an.add_argument("--log", required=True, help="MCAP log to annotate")
    an.add_argument("--out", required=True, help="annotated MCAP file to write")
    an.add_argument("--spec", default=None, help="MCAP ingestion spec (default: the one the run's dataset was ingested with)")
    an.add_argument("--dataset", default=None, help="the run's dataset (default: from the run)")
    an.add_argument("--overwrite", action="store_true")
    an.set_defaults(func=cmd_annotate)

    cv = sub.add_parser(
        "convert",
        help="convert datasets between our format, D4RL arrays, Minari and the LeRobot layout",
        formatter_class=fmt,
        description="Read SOURCE (--from: a dataset directory, a D4RL .npz, a local Minari dataset id or directory; "
        "nothing is downloaded) and write OUT (--to: a dataset directory, a D4RL .npz, a Minari dataset id under "
        "MINARI_DATASETS_PATH, a LeRobot-layout directory). Transitions are kept exactly. See docs/formats.md.",
        epilog="examples:\n  offline-adp convert data/pt --to minari --out offline_adp/pt-v0\n"
        "  offline-adp convert logs/hopper.npz --from d4rl --out data/hopper",
    )
    cv.add_argument("source")
    cv.add_argument("--from", dest="from_format", default="dataset", choices=["dataset", "d4rl", "minari"])
    cv.add_argument("--to", dest="to_format", default="dataset", choices=["dataset", "d4rl", "minari", "lerobot"])
    cv.add_argument("--out", required=True)
    cv.add_argument("--overwrite", action="store_true")
    cv.set_defaults(func=cmd_convert)

    from offline_adp.progress import add_logging_options

    add_logging_options(p)  # -v/-q/--log-level on the top level and on every subcommand
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from offline_adp.progress import capturing_warnings

    with capturing_warnings() as caught:
        try:
            return _run(args)
        finally:
            caught.report(log)  # the package's warnings once each; the libraries' in one line


def _run(args: argparse.Namespace) -> int:
    """Run the parsed command; our errors as one line and exit status 2."""
    try:
        from offline_adp.progress import apply_logging_options

        apply_logging_options(args)
        return int(args.func(args))
    except OfflineADPError as exc:
        if args.traceback:
            raise
        print(f"offline-adp {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head` and the like
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except MemoryError:
        if args.traceback:
            raise
        print(f"offline-adp {args.command}: error: out of memory; use smaller settings (episodes, bootstrap "
              "replicates, horizon) or a machine with more memory", file=sys.stderr)
        return 2
    except OSError as exc:  # read-only location, full disk, a file or folder in the way: one line, exit 2
        if args.traceback:
            raise
        from offline_adp.errors import os_error_message

        print(f"offline-adp {args.command}: error: {os_error_message(exc, _output_of(args))}", file=sys.stderr)
        return 2


def _output_of(args: argparse.Namespace) -> str | None:
    """The path a command writes (for an OSError that names none)."""
    for name in ("out", "json", "run", "write"):
        value = getattr(args, name, None)
        if isinstance(value, str):
            return value
    return None


if __name__ == "__main__":
    sys.exit(main())
