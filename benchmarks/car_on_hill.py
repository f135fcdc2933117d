"""Car-on-the-hill replication of Ernst, Geurts & Wehenkel (2005), three ways, side by side.

Data: 1000 episodes of uniformly random actions from (p, s) = (-0.5, 0), each until
termination or 100 steps. FQI with extra-trees (50 trees, n_min = 2, all features),
gamma = 0.95, 50 iterations. Score: mean discounted return over the 289-state grid
(return = -cost). Modes:

(a) refit: the naive loop, a new forest every iteration;
(b) frozen: structure fitted on the first targets, 50 leaf re-averaging iterations,
    one restructuring on the converged targets, 50 more;
(c) warm_start: LightGBM, 10 new trees per iteration.

    python benchmarks/car_on_hill.py [--episodes 1000] [--iterations 50] [--modes refit frozen warm_start]
"""

from __future__ import annotations

import argparse
import time

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.envs.car_on_hill import score
from offline_adp.simulate import simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=1000)
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--modes", nargs="+", default=["refit", "frozen", "warm_start"])
    args = ap.parse_args()
    ds = simulate("car_on_hill", 0, args.episodes, seed=args.seed, horizon=100)
    print(f"data: {len(ds)} transitions in {ds.n_episodes} episodes (uniformly random actions from (-0.5, 0))")
    configs = {
        "refit": dict(mode="refit", regressor="extra_trees"),
        "frozen": dict(mode="frozen", regressor="extra_trees"),
        "warm_start": dict(mode="warm_start", regressor="lightgbm", regressor_params={"num_leaves": 63, "min_child_samples": 5}, trees_per_iteration=10),
    }
    results = []
    for name in args.modes:
        f = FittedQIteration(gamma=0.95, n_iterations=args.iterations, random_state=args.seed, **configs[name])
        c0, w0 = time.process_time(), time.perf_counter()
        f.fit(ds)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        sc = score(f.policy_)
        results.append((name, sc, cpu, wall, len(f.history_)))
        print(f"  {name:<11} score {sc:+.4f}  CPU {cpu:7.1f} s  wall {wall:6.1f} s  iterations {len(f.history_)}", flush=True)
    base = dict((r[0], r) for r in results).get("refit")
    print("\nmode         score    CPU s   CPU vs refit")
    for name, sc, cpu, wall, it in results:
        ratio = f"{cpu / base[2]:.3f}" if base else "-"
        print(f"{name:<11} {sc:+.4f} {cpu:8.1f}   {ratio}")


if __name__ == "__main__":
    main()
