"""Approximate policy iteration against fitted Q-iteration through the CLI (issue #44).

The logs: ``offline-adp simulate path_tracking --seed SEED`` for each of ``--seeds`` (the
defaults: 100 demonstration and 100 exploration episodes, ~22,000 transitions). Every arm
is an ``offline-adp fit`` of that dataset in its own process, with a config file holding only the
arm's parameters (``{}``: the CLI defaults). CPU: the whole process's (user + sys,
``os.wait4``: imports, reading, the fit, writing the model) and the fit's own
(``fit_cpu_seconds`` in run.json); memory: the process's peak resident set. Policy cost:
the saved policy's mean discounted cost over ``--episodes`` rollouts in the path_tracking
simulator (start states and noise from seed 0, the same for every arm; lower is better),
with its standard error, and its difference to ``--reference``'s (paired: the same start
states and noise), with the paired standard error; the problem's demonstrator on the same
episodes for scale. For API runs: the fraction of the states where its evaluations read the
policy (the data's next states and start states) whose greedy action changed at each iteration
(``changed`` in ``model/history.csv``) and the fit's verdict (run.json).

    nice -n 10 python benchmarks/api_cost.py [--arm fqi=fqi:'{}' --arm api=api:'{}' ...] \
        [--arm api_old@OTHER_TREE=api:'{}'] [--seeds 11 12 13] [--episodes 500] [--out DIR]

An arm is ``NAME[@SOURCE_TREE]=ALGORITHM:JSON`` (SOURCE_TREE: another checkout holding
``offline_adp``, e.g. the code before a change). The arms run one after the other; the
table at the end gives each arm's CPU as a multiple of ``--reference``'s (default ``fqi``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ARMS = {"fqi": (None, "fqi", {}), "api": (None, "api", {})}


def _env(source: str | None) -> dict[str, str]:
    """The environment of a child importing ``offline_adp`` from ``source`` (default: this checkout)."""
    env = os.environ.copy()
    env["PYTHONPATH"] = os.pathsep.join([str(Path(source or Path(__file__).resolve().parent.parent).resolve()),
                                         env.get("PYTHONPATH", "")])
    return env


def simulate(seed: int, path: Path) -> Path:
    if not (path / "meta" / "info.json").exists():
        subprocess.run([sys.executable, "-m", "offline_adp", "-q", "simulate", "path_tracking", "--seed", str(seed),
                        "--out", str(path), "--overwrite"], env=_env(None), check=True, stdout=subprocess.DEVNULL)
    return path


def cli_fit(dataset: Path, run: Path, algorithm: str, params: dict, source: str | None) -> dict:
    """``offline-adp fit`` in a child process; its CPU (user + sys), peak RSS and run.json."""
    import shutil

    if run.exists():
        shutil.rmtree(run)
    run.parent.mkdir(parents=True, exist_ok=True)
    cfg = run.parent / (run.name + ".toml")
    lines = [f"[{algorithm}]"] + [f"{k} = {json.dumps(v)}" for k, v in params.items() if not isinstance(v, dict)]
    for k, v in params.items():  # sub-tables (api's [api.fqe])
        if isinstance(v, dict):
            lines += [f"[{algorithm}.{k}]"] + [f"{kk} = {json.dumps(vv)}" for kk, vv in v.items()]
    cfg.write_text("\n".join(lines) + "\n")
    cmd = [sys.executable, "-m", "offline_adp", "-q", "fit", str(dataset), "--algorithm", algorithm, "--config",
           str(cfg), "--out", str(run)]
    proc = subprocess.Popen(cmd, env=_env(source), cwd=run.parent, stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(cmd)} failed")
    meta = json.loads((run / "run.json").read_text())
    return {"process_cpu_s": usage.ru_utime + usage.ru_stime, "max_rss_gib": usage.ru_maxrss / 2**20, **meta}


def policy_cost(run: Path, dataset: Path, episodes: int) -> tuple[np.ndarray, float]:
    """The saved policy's discounted cost per episode, and the demonstrator's mean."""
    from offline_adp.data.dataset import read_dataset
    from offline_adp.deploy import load_run_policy
    from offline_adp.envs import problem_for_dataset
    from offline_adp.rollout import rollout

    ds = read_dataset(dataset)
    problem = problem_for_dataset("path_tracking", ds.info)
    pol = load_run_policy(run, dataset)
    r = rollout(problem, pol, episodes, np.random.default_rng(0))
    d = rollout(problem, problem.demonstrator(), episodes, np.random.default_rng(0))
    return r.discounted_cost, d.mean


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--arm", action="append", default=[], help="NAME[@SOURCE_TREE]=ALGORITHM:JSON (repeatable)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[11], help="the logs' seeds (offline-adp simulate --seed)")
    ap.add_argument("--episodes", type=int, default=500)
    ap.add_argument("--reference", default="fqi")
    ap.add_argument("--out", default=None, help="where the dataset and runs go (default: a temporary directory)")
    ap.add_argument("--json", default=None, help="append every fit's record here (JSON lines)")
    args = ap.parse_args()
    arms = ARMS
    if args.arm:
        arms = {}
        for a in args.arm:
            name, spec = a.split("=", 1)
            name, _, source = name.partition("@")
            algorithm, _, params = spec.partition(":")
            arms[name] = (source or None, algorithm, json.loads(params or "{}"))
    root = (Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="api_cost_"))).resolve()
    records = []
    for seed in args.seeds:
        ds = simulate(seed, root / "data" / f"path_tracking-s{seed}")
        costs = {}
        for name, (source, algorithm, params) in arms.items():
            run = root / "runs" / f"s{seed}-{name}"
            fit = cli_fit(ds, run, algorithm, params, source)
            costs[name], demo = policy_cost(run, ds, args.episodes)
            c = costs[name]
            rec = {"seed": seed, "arm": name, "algorithm": algorithm, "params": params, "source": source,
                   "process_cpu_s": round(fit["process_cpu_s"], 1),
                   "fit_cpu_s": round(fit.get("fit_cpu_seconds", 0), 1),
                   "max_rss_gib": round(fit["max_rss_gib"], 2), "cost": round(float(c.mean()), 4),
                   "se": round(float(c.std(ddof=1) / np.sqrt(len(c))), 4), "demonstrator": round(demo, 4),
                   "iterations": fit.get("iterations"), "verdict": fit.get("verdict"),
                   "verdict_message": fit.get("verdict_message")}
            if args.reference in costs:  # paired over the same start states and noise
                d = c - costs[args.reference]
                rec["minus_reference"] = [round(float(d.mean()), 4), round(float(d.std(ddof=1) / np.sqrt(len(d))), 4)]
            if algorithm in ("api", "cpi"):
                import pandas as pd

                h = pd.read_csv(run / "model" / "history.csv")
                rec["changed"] = [round(float(x), 3) for x in h["changed"]] if "changed" in h else None
            print(json.dumps(rec), flush=True)
            records.append(rec)
            if args.json:
                with open(args.json, "a") as fh:
                    fh.write(json.dumps(rec) + "\n")
    print(table(records, args.reference))


def table(records: list[dict], reference: str) -> str:
    lines = [f"| log seed | arm | policy cost (+- s.e.) | minus {reference}'s (paired s.e.) | process CPU-s "
             f"| fit CPU-s | process CPU / {reference}'s | peak RSS GiB | iterations | verdict |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        ref = next((x for x in records if x["arm"] == reference and x["seed"] == r["seed"]), None)
        ratio = f"{r['process_cpu_s'] / ref['process_cpu_s']:.2f}" if ref else "-"
        diff = r.get("minus_reference")
        diff = f"{diff[0]:+.3f} ({diff[1]:.3f})" if diff and r["arm"] != reference else "-"
        lines.append(f"| {r['seed']} | {r['arm']} | {r['cost']:.3f} +- {r['se']:.3f} | {diff} "
                     f"| {r['process_cpu_s']:.1f} | {r['fit_cpu_s']:.1f} | {ratio} | {r['max_rss_gib']:.2f} "
                     f"| {r['iterations']} | {r['verdict']} |")
    for seed in dict.fromkeys(r["seed"] for r in records):
        demo = next(r["demonstrator"] for r in records if r["seed"] == seed)
        lines.append(f"\nlog seed {seed}: the demonstrator on the same episodes: {demo:.3f}")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
