"""``n_iterations="auto"`` against a fixed 200-iteration fit on gymnasium tasks (issue #34).

50,000 random-play transitions per task (``benchmarks/fqi_suite.py``'s logs: MountainCar
episodes of up to 2,000 steps, else its log holds no goal), gamma 0.99, the default
``FittedQIteration`` (frozen structures) with ``n_iterations="auto"`` and with 200; score:
mean undiscounted return of the greedy policy over 20 episodes seeded 10_000 + i at
gymnasium's own time limit, with its standard error; the fit's CPU seconds, iterations and
convergence verdict.

    nice -n 10 python benchmarks/fqi_auto_iterations.py [--envs MountainCar-v0 CartPole-v1 Acrobot-v1] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from fqi_suite import gym_dataset, gym_returns  # noqa: E402

from offline_adp.algorithms.fqi import FittedQIteration  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--envs", nargs="+", default=["MountainCar-v0", "CartPole-v1", "Acrobot-v1"])
    ap.add_argument("--seed", type=int, default=0, help="data and learner seed")
    args = ap.parse_args()
    for env in args.envs:
        ds = gym_dataset(env, 50_000, args.seed)
        for label, kw in (("auto", {}), ("200", {"n_iterations": 200})):
            c0 = time.process_time()
            est = FittedQIteration(random_state=args.seed, **kw).fit(ds)
            cpu = time.process_time() - c0
            r = gym_returns(env, est.policy_)
            m, se = float(r.mean()), float(r.std(ddof=1) / np.sqrt(len(r)))
            print(json.dumps({"env": env, "n_iterations": label, "score": round(m, 1), "se": round(se, 1),
                              "cpu_s": round(cpu, 1), "iterations": len(est.history_), "verdict": est.verdict_}),
                  flush=True)


if __name__ == "__main__":
    main()
