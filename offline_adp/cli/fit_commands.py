"""Learning commands: ``fit``, ``evaluate``, ``run`` (pipelines), ``schema``, ``report``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from offline_adp.cli._common import log
from offline_adp.errors import InvalidArgumentError, UnknownNameError
from offline_adp.progress import is_terminal, log_milestone


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
    total = params.get("horizon") or params.get("n_iterations")
    total = total if isinstance(total, int) else None  # "auto" (the default): the fit decides when it is done
    if not args.quiet and entry.resumable and is_terminal():
        from tqdm import tqdm

        bar = tqdm(total=total, desc=f"fit {args.algorithm}", unit="it", file=sys.stderr)

    def on_iteration(row: dict) -> None:
        it = row.get("iteration")
        log.debug("fit %s iteration %s: sup|dQ| %.4g, Bellman residual %.4g, start value %.4g, %.2f s", args.algorithm,
                  it,
                  *(float(row.get(k) if row.get(k) is not None else float("nan"))
                    for k in ("sup_dq", "bellman_residual", "start_value", "wall_time")))
        if bar is None and log_milestone(it, total):  # in a log: a few lines, not one per iteration
            log.info("fit %s: iteration %s%s, sup|dQ| %.4g", args.algorithm, it, f"/{total}" if total else "",
                     float(row.get("sup_dq") if row.get("sup_dq") is not None else float("nan")))
        if bar is not None:
            if bar.n == 0 and row["iteration"] > 1:
                bar.update(row["iteration"] - 1)  # resumed
            bar.set_postfix(residual=f"{row['bellman_residual']:.3g}", dq=f"{row['sup_dq']:.3g}",
                            s=f"{row['wall_time']:.2f}")
            bar.update(1)

    try:
        est = fit_run(args.dataset, args.out, algorithm=args.algorithm, params=params or None, resume=args.resume,
                      on_iteration=on_iteration, holdout=args.holdout)
    finally:
        if bar is not None:
            bar.close()
    for line in fit_summary_lines(est, args.algorithm, Path(args.out) / "model"):
        print(line)
    held = json.loads((Path(args.out) / "run.json").read_text()).get("holdout")
    if held:
        print(f"held out of the fit: {held['episodes']} of {held['of']} episodes (run.json 'holdout'); "
              "`offline-adp evaluate` reads the policy on them")
    print(f"{args.out}/model")
    return 0


def fit_summary_lines(est: object, algorithm: str, model_dir: Path | None = None) -> list[str]:
    """What ``fit`` prints: the last iteration's numbers, the convergence verdict when there
    is one, and the size of the model's arrays in ``model_dir`` (``q.npz``, ``policy.npz``)."""
    import pandas as pd

    hist = getattr(est, "history_", None)
    n = 0 if hist is None else len(hist)
    if isinstance(hist, pd.DataFrame) and n and {"sup_dq", "bellman_residual", "start_value"} <= set(hist.columns):
        h = hist.iloc[-1]
        mode = getattr(est, "mode_", None)
        how = f" ({mode} mode{', auto' if getattr(est, 'mode', None) == 'auto' else ''})" if mode else ""
        lines = [f"fitted {algorithm}{how}: {n} iterations, last sup|dQ| {h['sup_dq']:.4g}, Bellman residual "
                 f"{h['bellman_residual']:.4g}, mean start Q {h['start_value']:.4g} (the fit's own reading, "
                 "not the policy's cost: `offline-adp evaluate` estimates that)"]
        from offline_adp.algorithms.fqi import structure_builds

        builds = structure_builds(hist)
        if builds:
            screened = any(b["screen"] is not None for b in builds)
            grown = [b["trees"] for b in builds if not b["constant"] and b["trees"]]
            early = (isinstance(getattr(est, "early_build_trees", None), int) and bool(grown)  # opt-in counts only
                     and any(b["screen"] is None and not b["constant"] and (b["trees"] or 0) < max(grown)
                             for b in builds))  # an unscreened build grew fewer trees than another
            caveat = ("the screen" if screened else "") + (" and " if screened and early
                                                           else "") + ("early builds" if early else "")
            by = sorted({b["builder"] for b in builds if b["builder"]})
            its = [str(b["iteration"]) for b in builds]
            trees = ["const" if b["constant"] else str(b["trees"] or "?") for b in builds]
            if len(builds) > 12:  # the first and last few; the history holds every build
                its, trees = its[:6] + ["..."] + its[-3:], trees[:6] + ["..."] + trees[-3:]
            lines.append(f"tree structures: {len(builds)} built (iterations {', '.join(its)}), "
                         f"trees {'/'.join(trees)}"
                         + (f", grown by {' and '.join(by)}" if by else "")
                         + (f" ({caveat}: can cost score; compare with a fit that grows every"
                            " forest whole, docs/fqi-modes.md)" if caveat else ""))
    else:
        lines = [f"fitted {algorithm}: {n} history rows"]
        if isinstance(hist, pd.DataFrame) and n:
            lines.append(hist.tail(5).to_string(index=False))
    verdict = getattr(est, "verdict_", None)
    if verdict is not None:
        msg = getattr(est, "verdict_message_", "")
        lines.append(f"verdict: {verdict}" + (f" ({msg})" if msg else ""))
    for f in ("q.npz", "policy.npz") if model_dir is not None else ():
        if (Path(model_dir) / f).is_file():
            lines.append(f"model: {Path(model_dir) / f} {(Path(model_dir) / f).stat().st_size / 1e6:.1f} MB")
    return lines


def _colour() -> bool:
    """Colour the verdict's outcome word: on a terminal, unless NO_COLOR is set."""
    import os
    import sys

    return bool(getattr(sys.stdout, "isatty", lambda: False)()) and not os.environ.get("NO_COLOR")


def cmd_evaluate(args: argparse.Namespace) -> int:
    from offline_adp.evaluation.run import evaluate_run
    from offline_adp.evaluation.summary import summary_lines

    def say(msg: str) -> None:
        log.info("  %s", msg)

    from offline_adp.evaluation.settings import EvaluationSettings

    m = evaluate_run(args.run, settings=EvaluationSettings.of_arguments(args), dataset=args.dataset, progress=say)
    for line in summary_lines(m, colour=_colour()):
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
            raise InvalidArgumentError(f"--set {item!r}: expected KEY=VALUE, e.g. data.exploration=20")
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key] = value
    engine = None
    if args.engine or args.scheduler:
        engine = {"kind": args.engine or "dask", **({"address": args.scheduler} if args.scheduler else {})}
    run = run_pipeline(args.pipeline, out=args.out, runs_root=args.runs, from_stage=args.from_stage, force=args.force,
                       say=say, overrides=overrides, engine=engine)
    from offline_adp.data.files import read_json_file

    man = read_json_file(run / "manifest.json")
    for name, st in man["stages"].items():
        print(f"  {name:9s} {st.get('status')}{' (reused)' if st.get('reused') else ''}"
              + (f" {st['seconds']:.1f} s" if st.get("seconds") is not None and not st.get("reused") else ""))
    if (run / "metrics.json").exists():
        from offline_adp.evaluation.summary import read_metrics, summary_lines

        for line in summary_lines(read_metrics(run / "metrics.json"), colour=_colour()):
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
        raise UnknownNameError(f"schema {args.kind!r}: known kinds are {sorted(all_)}")
    print(json.dumps(all_[args.kind], indent=2, sort_keys=True))
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from offline_adp.evaluation.report import build_report

    path = build_report(args.run)
    print(path)
    return 0
