"""Benchmark: the logging policy evaluated on its own logs, over many data seeds (issue #42).

On the logging policy's own weights (``ope.ON_POLICY_ESS_FRACTION``) WDR leads the headline
with its paired difference from the logged cost as the verdict against the behaviour. This
checks both against a precise truth, as the coverage suite's rows cannot (their truth from
300-2000 rollouts is as wide as the interval it checks): for each data seed, the coverage
suite's logs (:func:`ope_coverage.logs_and_problem`) and the evaluation a user gets
(:func:`ope_coverage.evaluate_candidates`, the ``exploration`` candidate, which is the logging
policy), then

- whether the headline interval holds the truth (``--truth`` rollouts of the same policy in
  the same simulator and horizon, once per problem), and its width over the value range;
- the logs-only verdict against the behaviour: the policy *is* the behaviour, so any side
  other than "not distinguishable" is wrong at the rate the interval's level allows.

    PYTHONPATH=. python benchmarks/onpolicy_dr_coverage.py --problems cartpole car_on_hill \\
        --seeds 1 30 [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np


def truth_of(problem: str, size: str, n: int) -> tuple[float, float]:
    """The logging policy's value and its Monte-Carlo standard error from ``n`` rollouts."""
    from benchmarks.ope_coverage import FIT, SIZES, logs_and_problem
    from offline_adp.rollout import rollout

    _ds, sim, fixed = logs_and_problem(problem, "tiny", 0)
    H = SIZES[size][problem][3]
    res = rollout(sim, fixed["exploration"], n, np.random.default_rng(10_000), horizon=H,
                  gamma=FIT[problem]["gamma"])
    return float(res.mean), float(res.discounted_cost.std(ddof=1) / np.sqrt(n))


def main(argv: list[str] | None = None) -> int:
    from benchmarks.ope_coverage import evaluate_candidates

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--problems", nargs="+", default=["cartpole", "car_on_hill"])
    ap.add_argument("--seeds", nargs=2, type=int, default=[1, 30], metavar=("FIRST", "LAST"))
    ap.add_argument("--size", default=None, help="default: medium for cartpole, small for car_on_hill")
    ap.add_argument("--truth", type=int, default=40_000)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    out: dict[str, Any] = {}
    for problem in args.problems:
        size = args.size or ("small" if problem == "car_on_hill" else "medium")
        truth, se = truth_of(problem, size, args.truth)
        print(f"{problem} ({size}): truth {truth:.4f} +- {se:.4f} ({args.truth} rollouts)", flush=True)
        rows = []
        for seed in range(args.seeds[0], args.seeds[1] + 1):
            r = evaluate_candidates(problem, size, seed, ["exploration"], say=lambda *_: None)[0]
            iv = r["logs_only_headline"]["interval"] if r["logs_only_headline"] else None
            row = {"seed": seed, "headline": (r["logs_only_headline"] or {}).get("name"), "interval": iv,
                   "covers": iv is not None and iv[0] <= truth <= iv[1],
                   "width_over_range": (r["logs_only_headline"] or {}).get("width_over_range"),
                   "verdict_logs_only": r["verdict_logs_only"]["performance"],
                   "verdict_with_simulator": r["verdict"]["performance"], "behaviour_logged": r["behaviour_logged"]}
            rows.append(row)
            print(f"  seed {seed:3d}: {row['headline']} {iv} covers {row['covers']}  width/range "
                  f"{row['width_over_range']}  logs-only {row['verdict_logs_only']}", flush=True)
        covered = sum(r["covers"] for r in rows)
        wrong = sum(r["verdict_logs_only"] in ("better", "worse") for r in rows)
        widths = [r["width_over_range"] for r in rows if r["width_over_range"] is not None]
        print(f"{problem}: headline covers {covered}/{len(rows)}; median width / range "
              f"{np.median(widths) if widths else float('nan'):.4f}; logs-only verdict claims a side for the "
              f"behaviour itself on {wrong}/{len(rows)}; headlines {sorted({r['headline'] for r in rows}, key=str)}")
        out[problem] = {"truth": truth, "truth_se": se, "rows": rows, "covered": covered, "n": len(rows),
                        "claimed_a_side": wrong}
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, ".")
    raise SystemExit(main())
