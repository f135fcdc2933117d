"""Car-on-the-hill replication of Ernst, Geurts & Wehenkel (2005), three ways, side by side.

Data: 1000 episodes of uniformly random actions from (p, s) = (-0.5, 0), each until
termination or 100 steps. FQI with extra-trees (50 trees, n_min = 2, all features),
gamma = 0.95, 50 iterations. Score: mean discounted return over the 289-state grid
(return = -cost). Modes:

(a) refit: the naive loop, a new forest every iteration;
(b) frozen: structure fitted on the first targets, 50 leaf re-averaging iterations,
    one restructuring on the converged targets, 50 more;
(c) warm_start: LightGBM, 10 new trees per iteration;
(c') lightgbm_refit: LightGBM refitted every iteration (200 trees), the ceiling for (c).

Each mode runs once per seed (data and learner seeded alike), or once per learner seed
in ``--learner-seeds`` for every data seed; scores are averaged, and the frozen - refit
difference is reported with its standard error over the (data, learner) seed pairs: the
refit loop's own learner-seed spread is larger than the 0.01 tolerance, so one pair says
little.
``--data uniform`` replaces the episodes by 50k one-step transitions from states drawn
uniformly over [-1, 1] x [-3, 3] with random actions (the paper's second setting).

    python benchmarks/car_on_hill.py [--data episodes|uniform] [--episodes 1000] [--iterations 50] [--seeds 0 1]
    [--learner-seeds 0 1] [--modes ...]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.data.dataset import TransitionDataset
from offline_adp.envs.car_on_hill import CarOnHill, score
from offline_adp.simulate import simulate


def uniform_data(n: int, seed: int) -> TransitionDataset:
    """``n`` one-step transitions from (p, s) uniform on [-1, 1] x [-3, 3], random actions."""
    model = CarOnHill()
    rng = np.random.default_rng(seed)
    x = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-3, 3, n)])
    a = rng.integers(0, 2, n)
    r = model.step_seeded(x, a)
    return TransitionDataset.from_arrays(
        model.dataset_info(), episode_id=np.char.zfill(np.arange(n).astype(str), 7), step=np.zeros(n), obs=x, action=a,
        cost=r.costs, next_obs=r.next_states, terminated=r.terminated, truncated=~r.terminated,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=1000)
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--learner-seeds", type=int, nargs="+", default=None,
                    help="random_state values per data seed (default: the data seed itself)")
    ap.add_argument("--data", choices=["episodes", "uniform"], default="episodes")
    ap.add_argument("--uniform-size", type=int, default=50_000)
    ap.add_argument("--modes", nargs="+", default=["refit", "frozen", "warm_start", "lightgbm_refit"])
    args = ap.parse_args()
    configs = {
        "refit": dict(mode="refit", regressor="extra_trees"),
        "frozen": dict(mode="frozen", regressor="extra_trees"),
        "warm_start": dict(mode="warm_start", regressor="lightgbm",
                           regressor_params={"num_leaves": 63, "min_child_samples": 5}, trees_per_iteration=10),
        "lightgbm_refit": dict(mode="refit", regressor="lightgbm",
                               regressor_params={"n_estimators": 200, "num_leaves": 255, "min_child_samples": 2}),
    }
    results: dict[str, list[tuple[float, float]]] = {m: [] for m in args.modes}
    for seed in args.seeds:
        if args.data == "episodes":
            ds = simulate("car_on_hill", 0, args.episodes, seed=seed, horizon=100)
            print(f"seed {seed}: {len(ds)} transitions in {ds.n_episodes} episodes (uniformly random actions "
                  "from (-0.5, 0))")
        else:
            ds = uniform_data(args.uniform_size, seed)
            print(f"seed {seed}: {len(ds)} one-step transitions from uniformly drawn states and actions")
        for ls in args.learner_seeds if args.learner_seeds is not None else [seed]:
            for name in args.modes:
                f = FittedQIteration(gamma=0.95, n_iterations=args.iterations, random_state=ls, **configs[name])
                c0, w0 = time.process_time(), time.perf_counter()
                f.fit(ds)
                cpu, wall = time.process_time() - c0, time.perf_counter() - w0
                sc = score(f.policy_)
                results[name].append((sc, cpu))
                print(f"  learner seed {ls}: {name:<15} score {sc:+.4f}  CPU {cpu:7.1f} s  wall {wall:6.1f} s  "
                      f"iterations {len(f.history_)}", flush=True)
    base = results.get("refit")
    base_cpu = sum(c for _, c in base) if base else None
    print(f"\nmean over seeds {args.seeds}")
    print("mode             score     CPU s   CPU vs refit")
    for name, rs in results.items():
        sc = sum(r[0] for r in rs) / len(rs)
        cpu = sum(r[1] for r in rs)
        ratio = f"{cpu / base_cpu:.3f}" if base_cpu else "-"
        print(f"{name:<15} {sc:+.4f} {cpu:9.1f}   {ratio}")
    if base and len(base) > 1:
        for name, rs in results.items():
            if name == "refit":
                continue
            d = np.array([r[0] - b[0] for r, b in zip(rs, base, strict=True)])
            print(f"{name} - refit over {len(d)} seed pairs: {d.mean():+.4f} +- "
                  f"{d.std(ddof=1) / np.sqrt(len(d)):.4f} (s.e.)")


if __name__ == "__main__":
    main()
