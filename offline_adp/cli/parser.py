"""The ``offline-adp`` argument parser: every subcommand, its options and its example."""

from __future__ import annotations

import argparse

from offline_adp._version import __version__
from offline_adp.cli._common import (
    ALGORITHM_NAMES,
    FORMATS,
    OneLineParser,
    _positive_int,
    _rates,
    add_settings_options,
)
from offline_adp.cli.data_commands import (
    cmd_ingest_mcap,
    cmd_ingest_parquet,
    cmd_inspect,
    cmd_mcap_info,
    cmd_simulate,
    cmd_validate,
)
from offline_adp.cli.export_commands import cmd_annotate, cmd_convert, cmd_distill, cmd_export
from offline_adp.cli.fit_commands import cmd_evaluate, cmd_fit, cmd_report, cmd_run, cmd_schema


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
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)

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
        epilog="example:\n  offline-adp ingest parquet logs/*.parquet --spec logs/pt.spec.toml --out data/pt "
        "--on-error quarantine",
    )
    ip.add_argument("inputs", nargs="+", help="Parquet or CSV files")
    ip.add_argument("--spec", required=True, help="TOML ingestion spec")
    ip.add_argument("--out", required=True, help="dataset directory to write")
    ip.add_argument("--on-error", choices=("fail", "quarantine"), default=None,
                    help="default: the spec's on_error (fail)")
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
        epilog="example:\n  offline-adp ingest mcap logs/*.mcap --spec data/specs/path_tracking_mcap.toml "
        "--out data/pt --jobs 2",
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
        "evaluator; cpi/psdp: simulator = \"NAME\"; psdp: baseline_source, drop_features). fqi checkpoints as it "
        "iterates (the first and last iteration, between them at most 5% of its CPU); after Ctrl-C or a crash, "
        "--resume continues from the last checkpoint to the same result. --holdout FRACTION keeps that share of "
        "whole episodes out of the fit (chosen by the fit's random_state, listed in run.json's 'holdout'); "
        "`offline-adp evaluate` then reads the policy on them, which the fit did not see.",
        epilog="examples:\n  offline-adp fit data/pt --algorithm fqi --config fqi.toml --out runs/pt-fqi\n"
        "  offline-adp fit data/pt --algorithm fqi --holdout 0.3 --out runs/pt-fqi-ho  "
        "# evaluate on the other 30%\n"
        "  offline-adp fit data/pt --algorithm psdp --config psdp.toml --out runs/pt-psdp\n\n"
        "with fqi.toml (the defaults written out; n_iterations = \"auto\" fits to convergence):\n  [fqi]\n"
        "  gamma = 0.95\n  n_iterations = \"auto\"\n  regressor = \"extra_trees\"\n"
        "  [fqi.regressor_params]\n  n_estimators = 50\n\n"
        "and psdp.toml:\n  [psdp]\n  simulator = \"path_tracking\"\n  horizon = 50\n  learner = \"regression\"\n"
        "  baseline_source = \"demonstration\"\n  drop_features = [\"s\"]",
    )
    f.add_argument("dataset")
    f.add_argument("--algorithm", default="fqi", choices=list(ALGORITHM_NAMES))
    f.add_argument("--config", default=None, help="TOML file with the algorithm's parameters")
    f.add_argument("--out", required=True, help="run directory")
    f.add_argument("--resume", action="store_true", help="continue an interrupted run in --out")
    f.add_argument("--holdout", type=float, default=None, metavar="FRACTION",
                   help="fraction of whole episodes, in [0, 1), kept out of the fit for `evaluate` (default 0: "
                   "none; each side keeps at least 2 episodes)")
    f.add_argument("--quiet", "-q", action="store_true")
    f.set_defaults(func=cmd_fit)

    e = sub.add_parser(
        "evaluate",
        help="evaluate a run's policy: simulator rollouts, off-policy estimates, shift diagnostics",
        formatter_class=fmt,
        description="Evaluate the policy in RUN_DIR/model on the run's dataset (only the episodes `fit --holdout` "
        "kept out of the fit, when it did; else the fit's own episodes, and the verdict says FQE-based readings may "
        "read optimistic there): Monte-Carlo rollouts when a simulator "
        "is known (the dataset's reference problem or --simulator), the behaviour policy (logged propensities or a "
        "classifier), off-policy estimates with bootstrap intervals (FQE, IS, WIS, PDIS, WPDIS, DR, WDR, "
        "MIS), per-step density ratios with diagnostics, and the PSDP bound. Writes RUN_DIR/evaluation/metrics.json.",
        epilog="examples:\n  offline-adp evaluate runs/pt-fqi\n  offline-adp evaluate runs/pt-fqi --simulator none "
        "--dataset data/pt\n  offline-adp report runs/pt-fqi",
    )
    e.add_argument("run", help="run directory (from offline-adp fit)")
    e.add_argument("--dataset", default=None, help="dataset directory (default: the one the run was fitted on; on "
                   "that one a run fitted with --holdout is evaluated on its held-out episodes, other logs whole)")
    add_settings_options(e)  # --simulator, --episodes, --bootstrap, ... --seed: the settings' model
    e.add_argument("--quiet", "-q", action="store_true")
    e.set_defaults(func=cmd_evaluate)

    rp = sub.add_parser(
        "run",
        help="run a pipeline file (ingest -> validate -> fit -> evaluate -> report) into a run directory",
        formatter_class=fmt,
        description="Run the stages of a pipeline file into runs/<name>__<seed>__<timestamp>/ (or --out). A stage "
        "whose inputs, settings and code are unchanged is reused; an interrupted run continues from its last "
        "completed stage (FQI from its last checkpointed iteration). The manifest (manifest.json) records input "
        "fingerprints, the config hash, versions and per-stage status and timings. The file format: `offline-adp "
        "schema pipeline` (paths in the file are relative to the file's own directory).",
        epilog="examples:\n  offline-adp run pipelines/driving.toml\n  offline-adp run pipelines/driving.toml "
        "--from evaluate\n  offline-adp run pipelines/car_on_hill.toml --set data.exploration=200 --out runs/coh-small",
    )
    rp.add_argument("pipeline", help="pipeline TOML file")
    rp.add_argument("--out", default=None, help="run directory (default: continue the latest runs/<name>__<seed>__*)")
    rp.add_argument("--runs", default="runs", help="folder of run directories (default: runs)")
    rp.add_argument("--from", dest="from_stage", default=None, choices=["data", "validate", "fit", "evaluate",
                                                                        "report"],
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
        description="Build a single self-contained report.html (figures embedded, also saved as PNG in "
        "report/figures/) from RUN_DIR/evaluation/ and the fitted model.",
        epilog="example:\n  offline-adp evaluate runs/pt-fqi && offline-adp report runs/pt-fqi",
    )
    r.add_argument("run")
    r.set_defaults(func=cmd_report)

    sc = sub.add_parser(
        "schema",
        help="print the JSON Schema of a configuration file type (for editors checking TOML)",
        formatter_class=fmt,
        description="Print the JSON Schema of a pipeline file or a fit config, or write them all to a folder.",
        epilog="examples:\n  offline-adp schema pipeline > pipeline.schema.json\n  offline-adp schema --write "
        "docs/schemas",
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
        epilog="examples (the README's tour fits runs/pt-fqi and runs/pt-fqi5):\n  offline-adp compare runs/pt-fqi "
        "runs/pt-fqi5 --json compare.json   # + compare.html\n  offline-adp compare runs/pt-fqi runs/pt-fqi5 --report "
        "cmp/report.html",
    )
    cp.add_argument("runs", nargs="+", help="run directories (at least two)")
    cp.add_argument("--dataset", default=None, help="dataset directory (default: the one the runs were fitted on)")
    cp.add_argument("--estimator", default=None, help="rank by this estimator (default: the most reliable for all)")
    add_settings_options(cp, {"episodes": 300})  # as for evaluate, 300 rollout episodes per candidate
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

    di = sub.add_parser(
        "distill",
        help="distill a run's continuous greedy policy into a compact tree ensemble (to deploy and export)",
        formatter_class=fmt,
        description="Fit extra trees from the state to the greedy command of RUN_DIR (FQI over continuous commands) at "
        "its dataset's logged states, weighted by how much the choice matters there, clipped to the action table's "
        "bounds; write OUT, a run directory whose policy offline_adp.load_policy(OUT) returns and `offline-adp export "
        "OUT` writes to ONNX. Logs the fit: mean |distilled - greedy| per component. See docs/deploy.md.",
        epilog="example (the README tour's continuous car, step 6b):\n  offline-adp distill runs/car --out "
        "runs/car-distilled --max-rate 0.5\n  offline-adp export runs/car-distilled --out car-distilled.onnx "
        "--input-dtype float32",
    )
    di.add_argument("run",
                    help="run directory of a continuous greedy policy (FQI with commands=auto on exact commands)")
    di.add_argument("--out", required=True, help="run directory to write")
    di.add_argument("--dataset", default=None, help="dataset whose logged states to fit on (default: the run's)")
    di.add_argument("--n-estimators", type=_positive_int, default=50, help="trees (default 50)")
    di.add_argument("--min-samples-leaf", type=_positive_int, default=5, help="rows per leaf at least (default 5)")
    di.add_argument("--max-rate", type=_rates, default=None, metavar="R[,R...]",
                    help="rate limit: largest |u_t - u_(t-1)| per step, one value or one per component (saved with the "
                         "policy and in the ONNX metadata; applied by act(obs, previous=u_prev))")
    di.add_argument("--seed", type=int, default=0, help="random state of the forest")
    di.add_argument("--overwrite", action="store_true", help="replace OUT if it is a distilled run")
    di.set_defaults(func=cmd_distill)

    an = sub.add_parser(
        "annotate",
        help="write a copy of an MCAP log with the policy's actions, Q-gap, density ratio and support along it",
        formatter_class=fmt,
        description="Ingest LOG with the run's MCAP spec (from its dataset's provenance, or --spec) and "
        "write OUT: every message of LOG plus JSON topics (with JSON schemas) at each logged step's time: "
        "/offline_adp/action (policy vs "
        "logged action), /offline_adp/q_gap, /offline_adp/density_ratio, /offline_adp/support (out-of-support flag); "
        "a policy over continuous commands: /offline_adp/command (policy vs logged command), /offline_adp/q_gap and "
        "/offline_adp/support (its command against those logged nearby). "
        "Open OUT in Foxglove to plot them on the log's timeline.",
        epilog="example (the README's tour):\n  offline-adp annotate runs/pt-fqi --log logs/ros2/demonstration.mcap "
        "--spec data/specs/path_tracking_mcap.toml --out annotated.mcap   # --spec: a run fitted on a table",
    )
    an.add_argument("run", help="run directory")
    an.add_argument("--log", required=True, help="MCAP log to annotate")
    an.add_argument("--out", required=True, help="annotated MCAP file to write")
    an.add_argument("--spec", default=None,
                    help="MCAP ingestion spec (default: the one the run's dataset was ingested with)")
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
