"""Output commands: ``export`` (ONNX), ``distill`` (a continuous policy for export), ``annotate`` (MCAP),
``convert`` (dataset formats)."""

from __future__ import annotations

import argparse

from offline_adp.cli._common import _file_output, _say


# ---------------------------------------------------------------------------- export / annotate / convert
def cmd_export(args: argparse.Namespace) -> int:
    from offline_adp.data.files import locked_directory
    from offline_adp.data.rundir import check_outside_run
    from offline_adp.deploy import export_run

    _file_output(args.out, "--out", "an ONNX file")
    check_outside_run(args.run, args.out)  # before the lock makes the output's folder
    with locked_directory(args.out, what="file"):  # the exporter's temporary: removed on failure (main)
        print(export_run(args.run, args.out, fmt=args.format, dataset=args.dataset, overwrite=args.overwrite,
                         input_dtype=args.input_dtype))
    return 0


def cmd_distill(args: argparse.Namespace) -> int:
    from offline_adp.deploy import distill_run

    r = distill_run(args.run, args.out, dataset=args.dataset, n_estimators=args.n_estimators,
                    min_samples_leaf=args.min_samples_leaf, max_rate=args.max_rate, random_state=args.seed,
                    overwrite=args.overwrite)
    comps = r["components"]

    def per(v: list[float]) -> str:
        return ", ".join(f"{c} {x:.4g}" for c, x in zip(comps, v, strict=True))

    _say(args, f"distilled the greedy policy into {r['n_estimators']} trees on {r['rows']} logged states: "
         f"mean |distilled - greedy| {per(r['mean_abs_diff'])} (max {per(r['max_abs_diff'])}"
         + ("" if r["heldout_mean_abs_diff"] is None else f"; on held-out states {per(r['heldout_mean_abs_diff'])}")
         + "); mean step change "
         f"greedy {per(r['mean_step_change']['greedy'])}, distilled {per(r['mean_step_change']['distilled'])}"
         + ("" if r["q_increase"] is None else f"; mean Q increase {r['q_increase']:.4g}")
         + ("" if r["max_rate"] is None
            else f"; max rate {per(r['max_rate'])} per step (applied by act(previous=...))"))
    print(r["out"])
    return 0


def cmd_annotate(args: argparse.Namespace) -> int:
    from offline_adp.annotate import annotate_mcap

    s = annotate_mcap(args.run, args.log, args.out, spec=args.spec, dataset=args.dataset, overwrite=args.overwrite)
    agrees = ("" if s["agreement"] is None  # continuous commands: the differences are on /offline_adp/command
              else f"policy agrees with the log on {s['agreement']:.1%} of steps, ")
    _say(args, f"annotated {s['steps']} steps ({s['messages_copied']} log messages copied); {agrees}"
         f"{s['out_of_support']} steps out of support; topics {', '.join(s['topics'])}")
    print(s["out"])
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    from offline_adp.formats import convert

    if args.to_format == "d4rl":
        _file_output(args.out, "--out", "a .npz file")
    print(convert(args.source, args.out, from_format=args.from_format, to_format=args.to_format,
                  overwrite=args.overwrite))
    return 0
