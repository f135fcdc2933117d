"""``offline-adp fit`` against the same fit through the Python API, and ``load_policy`` of
the model it wrote (issue #44): CPU seconds (user + sys of a fresh process) and peak RSS.

Data: 50,000 random-play CartPole-v1 transitions (``benchmarks/fqi_suite.py``'s
collector, seed 0), gamma 0.99. For each ``--iterations`` setting (a number, or ``auto``:
the default ``FittedQIteration``):

- ``cli``: ``python -m offline_adp fit DATA --config fit.toml --out RUN -q`` (checkpoints,
  model, hashes, run.json), the whole process;
- ``api``: a process that reads the dataset and runs ``FittedQIteration(...).fit(ds)``
  (no checkpoint, nothing saved), the whole process;
- ``load``: a process that runs ``offline_adp.load_policy(RUN)`` (the model the cli arm
  wrote) then ``act_index`` on 1,000 states: CPU of the load call, of the first act, and
  the process's peak RSS.

Each source tree given (``--trees``, default this checkout) is measured in turn, arm by
arm, in the same session, so a base commit's checkout gives the "before" column::

    git worktree add /tmp/base 177e19e
    nice -n 10 python benchmarks/cli_overhead.py --trees /tmp/base . --iterations 50 auto

Run one at a time on a quiet machine: the numbers are CPU seconds, but other jobs still
disturb caches and the kernel's share.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent

API = """
import json, sys, time
from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.data.dataset import read_dataset
params = json.loads(sys.argv[2])
ds = read_dataset(sys.argv[1])
c = time.process_time()
est = FittedQIteration(**params).fit(ds)
print(json.dumps({"fit_cpu": time.process_time() - c, "iterations": len(est.history_)}))
"""

LOAD = """
import json, resource, sys, time, warnings
warnings.simplefilter("ignore")
c0 = time.process_time()
import offline_adp
import numpy as np
c1 = time.process_time()
policy = offline_adp.load_policy(sys.argv[1])
c2 = time.process_time()
X = np.random.default_rng(0).normal(size=(1000, 4)) * 0.1
policy.act_index(X, 0)
c3 = time.process_time()
print(json.dumps({"import": c1 - c0, "load": c2 - c1, "first_act": c3 - c2,
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""

MAKE_DATA = """
import sys
sys.path.insert(0, sys.argv[2])
from fqi_suite import gym_dataset
gym_dataset("CartPole-v1", 50_000, 0).save(sys.argv[1], overwrite=True)
"""


def child(cmd: list[str], tree: Path) -> tuple[float, str]:
    """Run ``cmd`` with ``tree`` first on the path; its user + sys CPU seconds and stdout."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run(cmd, env=env, cwd=tree, capture_output=True, text=True)
    if out.returncode:
        sys.exit(f"{' '.join(cmd)} failed:\n{out.stderr[-3000:]}")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), out.stdout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trees", nargs="+", type=Path, default=[HERE.parent], help="source trees to measure, in turn")
    ap.add_argument("--iterations", nargs="+", default=["50", "auto"], help="n_iterations settings (auto: the default)")
    ap.add_argument("--data", type=Path, help="dataset directory (made here when missing)")
    ap.add_argument("--work", type=Path, help="where runs are written (default: a temporary folder)")
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="cli_overhead_"))
    work.mkdir(parents=True, exist_ok=True)
    data = args.data or work / "cartpole"
    if not (data / "meta" / "info.json").exists():
        child([sys.executable, "-c", MAKE_DATA, str(data), str(HERE)], args.trees[-1].resolve())
    rows = []
    for it in args.iterations:
        params = {} if it == "auto" else {"n_iterations": int(it)}
        cfg = work / f"fit-{it}.toml"
        cfg.write_text("[fqi]\n" + "".join(f"{k} = {v}\n" for k, v in params.items()))
        for tree in (t.resolve() for t in args.trees):
            run = work / f"run-{it}-{abs(hash(str(tree)))}"
            shutil.rmtree(run, ignore_errors=True)
            cli, _ = child([sys.executable, "-m", "offline_adp", "fit", str(data), "--config", str(cfg), "--out",
                            str(run),
                            "-q"], tree)
            status = json.loads((run / "run.json").read_text())
            api, out = child([sys.executable, "-c", API, str(data), json.dumps(params)], tree)
            api_fit = json.loads(out.strip().splitlines()[-1])
            _, out = child([sys.executable, "-c", LOAD, str(run)], tree)
            load = json.loads(out.strip().splitlines()[-1])
            size = sum(f.stat().st_size for f in (run / "model").glob("q.*"))
            rows.append({"tree": str(tree), "iterations": f"{it} ({status.get('iterations')})", "cli_cpu": cli,
                         "cli_fit_cpu": status.get("fit_cpu_seconds"), "api_cpu": api,
                         "api_fit_cpu": api_fit["fit_cpu"],
                         "ratio": cli / api, "load_cpu": load["load"], "first_act_cpu": load["first_act"],
                         "load_rss_mb": load["rss_mb"], "model_mb": size / 1e6})
            print(json.dumps(rows[-1]), flush=True)
    head = ("tree", "iterations", "cli CPU-s", "(fit)", "api CPU-s", "(fit)", "cli/api", "load_policy CPU-s",
            "first act", "peak RSS MB", "model MB")
    print("\n| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for r in rows:
        print(f"| {r['tree']} | {r['iterations']} | {r['cli_cpu']:.2f} | {r['cli_fit_cpu']:.2f} | {r['api_cpu']:.2f} | "
              f"{r['api_fit_cpu']:.2f} | {r['ratio']:.2f} | {r['load_cpu']:.2f} | {r['first_act_cpu']:.3f} | "
              f"{r['load_rss_mb']:.0f} | {r['model_mb']:.1f} |")


if __name__ == "__main__":
    main()
