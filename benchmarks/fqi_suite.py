"""FQI quality-and-cost suite: every mode on every problem, side by side in one run.

Problems (score: higher is better):

- ``car_on_hill``: Ernst et al. (2005): 1000 random episodes from (-0.5, 0) (<= 100
  steps), gamma 0.95, 50 iterations; score = mean discounted return over the 289-state
  grid. The score swings 0.12-0.30 with the data seed alone: use several ``--data-seeds``.
- ``CartPole-v1``, ``Acrobot-v1``, ``MountainCar-v0`` (gymnasium): logs of uniformly random
  actions, each held 1-8 steps (:func:`offline_adp.envs.gym.record_random_log`), 50,000
  transitions (MountainCar: episodes of up to 2000 steps, else the log holds no goal), gamma
  0.99; score = mean undiscounted return of the greedy policy in
  gymnasium over 20 fixed episode seeds (random play: ~22 / -500 / -200).
- ``path_tracking``: 50 demonstration + 150 exploration episodes, gamma 0.95; score =
  minus the mean discounted cost of 200 rollouts in the simulator.

Learner: extra-trees, 50 trees, ``min_samples_split=2`` (the registry default). For every
(problem, mode): the score's mean and spread (std) over ``--learner-seeds``, the fit's
CPU seconds (``time.process_time``), and the CPU ratio to ``refit`` measured in the same
run. The monitor only warns; every fit's verdict is printed.

    nice -n 10 python benchmarks/fqi_suite.py --quick          # minutes: 10k transitions, fewer iterations
    nice -n 10 python benchmarks/fqi_suite.py [--problems ...] [--modes refit frozen warm_start] \
        [--learner-seeds 0 1 2] [--data-seeds 0] [--transitions 50000] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import numpy as np

from offline_adp.algorithms.fqi import FittedQIteration, structure_builds
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.errors import DivergenceWarning
from offline_adp.trees import builder as extra_trees

GYM = {"CartPole-v1": 100, "Acrobot-v1": 100, "MountainCar-v0": 200}  # iterations (MountainCar: goal info travels far)
MODES = {
    "default": {},  # FittedQIteration's defaults (mode="auto": frozen, one structure per 12.5 iterations)
    "refit": {"mode": "refit"},
    "sklearn_builder": {"tree_builder": "sklearn"},  # the default with scikit-learn growing the structures
    "frozen": {"mode": "frozen"},  # the default schedule
    "frozen2": {"mode": "frozen", "n_structures": 2},
    # each structure grown on 1/8 of the rows (bootstrap), leaves averaged over all rows
    "frozen_sub": {"mode": "frozen", "n_structures": 4, "structure_max_samples": 0.125},
    # 10 builds: 7 cheap (1/8 of the rows), the last 3 on all rows
    "frozen_hybrid": {"mode": "frozen", "n_structures": 10, "structure_max_samples": [0.125] * 7 + [1.0] * 3},
    "warm_start": {"mode": "warm_start"},
    # opt-in tree savings (docs/fqi-modes.md): the screen, and early builds of 10 trees
    "screened": {"screen_trees": 10},
    "early": {"early_build_trees": 10},
}


def gym_dataset(env_id: str, n: int, seed: int) -> TransitionDataset:
    from offline_adp.envs.gym import record_random_log

    # MountainCar's 200-step limit: random play reaches the goal 0-2 times in 50k transitions (nothing to
    # learn); episodes of up to 2000 steps reach it ~25 times. Scoring keeps gymnasium's own limit.
    log = record_random_log(env_id, n, seed=seed, **({"max_episode_steps": 2000} if env_id == "MountainCar-v0" else {}))
    d = log["obs"].shape[1]
    n_act = int(log["action"].max()) + 1
    info = DatasetInfo(features=tuple(Feature(f"o{j}") for j in range(d)),
                       action_table=ActionTable.from_values(np.arange(n_act, dtype=float)), gamma=0.99, name=env_id)
    term = log["terminated"].astype(bool)
    return TransitionDataset.from_arrays(
        info, episode_id=np.char.zfill(log["episode"].astype(int).astype(str), 6), step=log["step"], obs=log["obs"],
        action=log["action"].astype(int), cost=-log["reward"], next_obs=log["next_obs"], terminated=term,
        truncated=log["truncated"].astype(bool) & ~term)


def gym_score(env_id: str, policy, n_episodes: int = 20) -> float:
    """Mean return of ``policy`` over episodes seeded 10_000 + i, all stepped together."""
    return float(gym_returns(env_id, policy, n_episodes).mean())


def gym_returns(env_id: str, policy, n_episodes: int = 20) -> np.ndarray:
    """The return of each of ``n_episodes`` episodes seeded 10_000 + i, all stepped together."""
    import gymnasium

    envs = [gymnasium.make(env_id) for _ in range(n_episodes)]
    obs = np.array([e.reset(seed=10_000 + i)[0] for i, e in enumerate(envs)], dtype=np.float64)
    ret, alive = np.zeros(n_episodes), np.ones(n_episodes, bool)
    t = 0
    while alive.any():
        idx = np.flatnonzero(alive)
        acts = policy.act_index(obs[idx], t)
        for j, i in enumerate(idx):
            o, r, term, trunc, _ = envs[i].step(int(acts[j]))
            obs[i], ret[i] = o, ret[i] + r
            alive[i] = not (term or trunc)
        t += 1
    return ret


def problem(name: str, n: int, data_seed: int, quick: bool):
    """(dataset, gamma, iterations, score function)."""
    if name == "car_on_hill":
        from offline_adp.envs.car_on_hill import score
        from offline_adp.simulate import simulate

        ds = simulate("car_on_hill", 0, 300 if quick else 1000, seed=data_seed, horizon=100)
        return ds, 0.95, 50, score
    if name == "path_tracking":
        from offline_adp.envs import make_problem
        from offline_adp.rollout import rollout
        from offline_adp.simulate import simulate

        ds = simulate("path_tracking", 15 if quick else 50, 45 if quick else 150, seed=data_seed, horizon=100)
        model = make_problem("path_tracking")
        return ds, 0.95, 50, lambda pi: -rollout(model, pi, 200, np.random.default_rng(123), horizon=100,
                                                 gamma=0.95).mean
    ds = gym_dataset(name, n, data_seed)
    iters = GYM[name] if not quick else GYM[name] // 2
    return ds, 0.99, iters, lambda pi: gym_score(name, pi, 10 if quick else 20)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problems", nargs="+", default=["car_on_hill", *GYM, "path_tracking"])
    ap.add_argument("--modes", nargs="+", default=["refit", "default", "warm_start"], choices=list(MODES))
    ap.add_argument("--learner-seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--data-seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--transitions", type=int, default=50_000)
    ap.add_argument("--trees", type=int, default=50)
    ap.add_argument("--action-encoding", default="joint", choices=["joint", "per_action"])
    ap.add_argument("--quick", action="store_true",
                    help="10k transitions, 20 trees, half the iterations, 2 learner seeds")
    ap.add_argument("--gamma", type=float, default=None,
                    help="override each problem's gamma (e.g. 0.95 for a held-out check)")
    ap.add_argument("--iterations", type=int, default=None, help="override each problem's iteration count")
    ap.add_argument("--json", default=None, help="write every fit's numbers here")
    args = ap.parse_args()
    if args.quick:
        args.transitions, args.trees, args.learner_seeds = 10_000, 20, args.learner_seeds[:2]
    records = []
    # the compiled tree builder's one-off compile (or on-disk cache load) is not a fit's cost
    print(f"tree builder kernel: compiled/loaded in {extra_trees.warm_up():.1f} CPU-s (once per machine, then cached)",
          flush=True)
    for name in args.problems:
        for ds_seed in args.data_seeds:
            ds, gamma, iters, score = problem(name, args.transitions, ds_seed, args.quick)
            gamma = args.gamma if args.gamma is not None else gamma
            iters = args.iterations if args.iterations is not None else iters
            print(f"\n{name} (data seed {ds_seed}): {len(ds)} transitions, {ds.n_episodes} episodes, gamma {gamma}, "
                  f"{iters} iterations", flush=True)
            for mode in args.modes:
                for ls in args.learner_seeds:
                    f = FittedQIteration(gamma=gamma, n_iterations=iters, random_state=ls,
                                         action_encoding=args.action_encoding,
                                         regressor_params={"n_estimators": args.trees}, **MODES[mode])
                    with warnings.catch_warnings(record=True) as caught:
                        warnings.simplefilter("always", DivergenceWarning)
                        warnings.simplefilter("ignore", UserWarning)
                        c0, w0 = time.process_time(), time.perf_counter()
                        f.fit(ds)
                        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
                    sc = score(f.policy_)
                    flagged = any(issubclass(w.category, DivergenceWarning) for w in caught)
                    rec = {"problem": name, "data_seed": ds_seed, "mode": mode, "learner_seed": ls, "score": sc,
                           "cpu_s": cpu,
                           "wall_s": wall, "iterations": len(f.history_), "verdict": f.verdict_, "flagged": flagged,
                           "builds": [[b["iteration"], "const" if b["constant"] else b["trees"]]
                                      for b in structure_builds(f.history_)]}
                    records.append(rec)
                    if args.json:  # after every fit: a long run keeps what it measured
                        with open(args.json, "w") as fh:
                            json.dump(records, fh, indent=1)
                    trees = "/".join(str(t) for _, t in rec["builds"])
                    print(
                        f"  {mode:<11} seed {ls}: score {sc:+9.3f}  CPU {cpu:7.1f} s  wall {wall:6.1f} s  "
                        f"{f.verdict_}{' (FLAGGED)' if flagged else ''}{f'  trees per build {trees}' if trees else ''}",
                        flush=True,
                    )
    print("\nproblem         mode        score mean   spread(std)   CPU s (mean)   CPU / refit   flags")
    for name in args.problems:
        ref = [r["cpu_s"] for r in records if r["problem"] == name and r["mode"] == "refit"]
        for mode in args.modes:
            rs = [r for r in records if r["problem"] == name and r["mode"] == mode]
            s = np.array([r["score"] for r in rs])
            cpu = float(np.mean([r["cpu_s"] for r in rs]))
            ratio = f"{cpu / np.mean(ref):.3f}" if ref else "-"
            print(f"{name:<15} {mode:<11} {s.mean():+10.3f}   {s.std(ddof=1) if len(s) > 1 else 0.0:10.3f}   "
                  f"{cpu:12.1f}   {ratio:>11}   {sum(r['flagged'] for r in rs)}")


if __name__ == "__main__":
    main()
