"""``load_policy`` of a saved run and the policy's first acts, in fresh processes, for one
or more source trees side by side (issue #44: "``load_policy`` of the default CartPole model
under 1 CPU-s").

Each repeat runs one fresh process per source tree, in turn (so the trees share the
machine's state): ``import offline_adp`` (not counted in ``load``), then
``offline_adp.load_policy(RUN)`` (``load``: CPU seconds of the call), then ``act_index`` on
one state (``act1``) and on 1,000 states (``act1000``), then 200 one-state acts
(``loop200``), and the process's peak RSS. The run is any ``offline-adp fit`` output, e.g.
the one ``benchmarks/cli_overhead.py --work DIR`` writes::

    git worktree add /tmp/base 3493eb5
    python benchmarks/load_policy.py RUN --trees /tmp/base . --repeats 5
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

CHILD = """
import json, resource, sys, time, warnings
warnings.simplefilter("ignore")
import numpy as np
import offline_adp
c = time.process_time
t0 = c()
policy = offline_adp.load_policy(sys.argv[1])
t1 = c()
d = int(sys.argv[2])
rng = np.random.default_rng(0)
policy.act_index(rng.normal(size=(1, d)) * 0.1, 0)
t2 = c()
policy.act_index(rng.normal(size=(1000, d)) * 0.1, 0)
t3 = c()
for _ in range(200):
    policy.act_index(rng.normal(size=(1, d)) * 0.1, 0)
t4 = c()
print(json.dumps({"load": t1 - t0, "act1": t2 - t1, "act1000": t3 - t2, "loop200": t4 - t3,
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "numba": "numba" in sys.modules}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a run directory (model/ inside)")
    ap.add_argument("--trees", nargs="+", type=Path, default=[HERE.parent], help="source trees to measure, in turn")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--state-dim", type=int, default=4, help="width of the states acted on (CartPole: 4)")
    args = ap.parse_args()
    rows: dict[str, list[dict]] = {str(t): [] for t in args.trees}
    for _ in range(args.repeats):
        for tree in args.trees:
            env = {**os.environ, "PYTHONPATH": str(tree.resolve())}
            out = subprocess.run([sys.executable, "-c", CHILD, str(args.run), str(args.state_dim)], env=env,
                                 cwd=tree, capture_output=True, text=True)
            if out.returncode:
                sys.exit(f"{tree}: {out.stderr[-3000:]}")
            rows[str(tree)].append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(tree, rows[str(tree)][-1], flush=True)
    print("\ntree | load CPU-s (median, min-max) | act 1 | act 1000 | 200 one-state acts | peak RSS MB | "
          "numba imported")
    for tree, rs in rows.items():
        cols = []
        for k in ("load", "act1", "act1000", "loop200"):
            v = [r[k] for r in rs]
            cols.append(f"{statistics.median(v):.3f} ({min(v):.3f}-{max(v):.3f})")
        print(f"{tree} | {' | '.join(cols)} | {statistics.median(r['rss_mb'] for r in rs):.0f} | {rs[-1]['numba']}")


if __name__ == "__main__":
    main()
