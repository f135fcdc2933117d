"""Coverage of FQE's labelled interval against exact dynamic programming on tabular logs: the
policy evaluated on the logs it was fitted on, and on episodes held out of its fit
(``offline-adp fit --holdout FRACTION``).

For each seed: ``simulate tabular`` (30 demonstration + 30 exploration episodes), a
20-iteration 10-tree FQI fitted on every episode and one with ``--holdout FRACTION``, each
evaluated with ``evaluate --simulator none --bootstrap 50`` (the held-out run on its held-out
episodes). The truth is the exact finite-horizon value of the run's greedy policy
(:func:`offline_adp.dp.policy_evaluation_finite`) averaged over the evaluated episodes'
start states. Printed per run: FQE's estimate, its interval and level, whether it covers
the truth; then per kind the coverage of the labelled intervals, how often FQE read low,
and the mean error and width.

Measured 2026-11-29 (10 seeds, fraction 0.3): on the fit's own logs 7 of 10 labelled 95%
intervals covered (all 3 misses low; 9 of 10 read low; mean error -0.127, width 0.42); on
the held-out episodes 9 of 10 (1 miss high; 4 of 10 low; mean error +0.135, width 0.90).

    python benchmarks/holdout_coverage.py [--seeds 10] [--fraction 0.3] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from offline_adp import dp
from offline_adp.artifacts import load_index_policy
from offline_adp.data.dataset import TransitionDataset, read_dataset
from offline_adp.data.holdout import held_out_episodes
from offline_adp.envs.tabular import TabularMDP
from offline_adp.evaluation import shift

FIT = "[fqi]\nn_iterations = 20\nregressor = \"extra_trees\"\n[fqi.regressor_params]\nn_estimators = 10\n"


def cli(*args: object) -> None:
    p = subprocess.run([sys.executable, "-m", "offline_adp", *map(str, args)], capture_output=True, text=True)
    if p.returncode:
        sys.exit(f"offline-adp {' '.join(map(str, args))}: exit {p.returncode}\n{p.stderr[-2000:]}")


def truth(run: Path, ds: TransitionDataset) -> float:
    """The exact T-step value of the run's policy, mean over the episodes' start states."""
    mdp = TabularMDP(**(ds.info.provenance.get("problem_options") or {}))
    pol = load_index_policy(run / "model")
    a = ds.arrays()
    horizon = int(a.step.max() + 1)
    v = dp.policy_evaluation_finite(mdp.P, mdp.C, shift.policy_table(pol, mdp.n_states, horizon), horizon,
                                    ds.info.gamma).V[0]
    return float(v[a.obs[a.step == 0, 0].astype(int)].mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--fraction", type=float, default=0.3)
    ap.add_argument("--work", default=None, help="keep the datasets and runs here (default: a temporary directory)")
    args = ap.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="holdout_coverage_"))
    work.mkdir(parents=True, exist_ok=True)
    (work / "fqi.toml").write_text(FIT)
    rows: dict[str, list[dict]] = {"in_sample": [], "held_out": []}
    for s in range(args.seeds):
        d = work / f"data_{s}"
        if not d.exists():
            cli("simulate", "tabular", "--out", d, "--demonstrations", 30, "--exploration", 30, "--seed", s, "-q")
        full = read_dataset(d)
        for kind, extra in (("in_sample", []), ("held_out", ["--holdout", args.fraction])):
            run = work / f"run_{kind}_{s}"
            shutil.rmtree(run, ignore_errors=True)
            cli("fit", d, "--out", run, "--config", work / "fqi.toml", "-q", *extra)
            cli("evaluate", run, "--simulator", "none", "--bootstrap", 50, "-q")
            m = json.loads((run / "evaluation" / "metrics.json").read_text())
            info = json.loads((run / "run.json").read_text())
            ds = held_out_episodes(full, info["holdout"], str(run)) if kind == "held_out" else full
            t, f = truth(run, ds), m["ope"]["fqe"]
            row = {"seed": s, "kind": kind, "truth": t, "estimate": f["estimate"], "interval": f["interval"],
                   "level": f["level"], "covers": bool(f["interval"][0] <= t <= f["interval"][1]),
                   "low": bool(f["estimate"] < t)}
            print(json.dumps(row), flush=True)
            rows[kind].append(row)
    for kind, rs in rows.items():
        lab = [r for r in rs if r["level"]]
        err = np.array([r["estimate"] - r["truth"] for r in rs])
        width = np.mean([r["interval"][1] - r["interval"][0] for r in rs])
        print(f"{kind}: labelled {len(lab)}/{len(rs)}, covered {sum(r['covers'] for r in lab)}/{len(lab)}, read low "
              f"{sum(r['low'] for r in rs)}/{len(rs)}, mean error {err.mean():+.3f}, mean width {width:.3f}")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
