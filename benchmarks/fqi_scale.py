"""Scale benchmark: fitted Q-iteration on 100k and 1M transitions (4-dim state, 3 actions).

Synthetic linear-Gaussian system x' = 0.95 x + B[a] + 0.1 noise, cost |x|^2 + 0.1 a^2
(a in {-1, 0, 1}), episodes of 100 steps from x0 ~ N(0, I) under uniformly random actions.
Each (size, mode, threads) runs 50 iterations in a fresh subprocess so that peak RSS is its
own; per-iteration time is the median of the iterations. Wall, CPU (every thread) and peak
RSS are those of the fit alone.

The learned greedy policy is then scored on the system itself: ``--eval-episodes``
rollouts from x0 ~ N(0, I) over ``--eval-horizon`` steps (gamma^200 = 3.5e-5: the
discounted infinite-horizon cost up to that), against reference controllers run on the
same start states and noise (common random numbers): ``nothing`` (a = 0 always),
``lookahead`` (the one-step rule argmin_a 0.1 a^2 + |0.95 x + B[a]|^2: the expected next
state's cost) and ``behaviour`` (uniformly random actions: the data's logging policy).
Reported: mean discounted cost with its standard error over rollouts, and the learned
policy's paired difference to ``lookahead`` (negative: the learned policy is cheaper).

Threads: the extra-trees and LightGBM fits take ``regressor_params = {n_jobs = k}``; each
setting of ``--threads`` (default 1 and 2) is a separate run.

    python benchmarks/fqi_scale.py [--sizes 100000 1000000] [--modes default warm_start ...] [--iterations 50|auto]
                                   [--threads 1 2] [--eval-episodes 1000] [--eval-horizon 200]

Modes: ``default`` (``FittedQIteration``'s defaults: ``mode="auto"``, i.e. frozen extra-trees grown
fully, each structure on at most 131,072 rows; ``--iterations auto``: its ``n_iterations`` too),
``default100`` (the same with 100 trees), ``warm_start`` (LightGBM, 10 trees an iteration), ``frozen``
(extra-trees, ``min_samples_leaf=20``, the default structure schedule), ``frozen_sub`` (the same with
each tree grown on 1/8 of the rows, ``structure_max_samples=0.125``), ``refit_lightgbm``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

CHILD = textwrap.dedent(
    """
    import json, resource, sys, time
    import numpy as np
    from offline_adp import TransitionDataset, DatasetInfo, Feature, ActionTable
    from offline_adp.algorithms.fqi import FittedQIteration, structure_builds
    n, mode, iters, threads = int(sys.argv[1]), sys.argv[2], sys.argv[3], int(sys.argv[4])
    iters = iters if iters == "auto" else int(iters)
    eval_episodes, eval_horizon, gamma = int(sys.argv[5]), int(sys.argv[6]), 0.95
    rng = np.random.default_rng(0)
    T = 100; E = n // T; n = E * T
    B = np.array([[-0.1, 0, 0, 0], [0, 0, 0, 0], [0.1, 0, 0.05, 0]])
    x = np.empty((E, T + 1, 4)); x[:, 0] = rng.normal(size=(E, 4))
    a = rng.integers(0, 3, size=(E, T))
    for t in range(T):
        x[:, t + 1] = 0.95 * x[:, t] + B[a[:, t]] + 0.1 * rng.normal(size=(E, 4))
    obs, nxt = x[:, :-1].reshape(n, 4), x[:, 1:].reshape(n, 4)
    act = a.reshape(n)
    cost = (obs ** 2).sum(1) + 0.1 * (act - 1) ** 2
    info = DatasetInfo(features=tuple(Feature(f"x{i}") for i in range(4)),
                       action_table=ActionTable.from_values([-1.0, 0.0, 1.0]))
    ep = np.repeat(np.char.zfill(np.arange(E).astype(str), 7), T)
    ds = TransitionDataset.from_arrays(info, episode_id=ep, step=np.tile(np.arange(T), E), obs=obs, action=act,
                                       cost=cost, next_obs=nxt, terminated=np.zeros(n, bool),
                                       truncated=np.tile(np.arange(T) == T - 1, E))
    del x, obs, nxt
    cfg = {
        "default": {},
        "default100": dict(regressor_params={"n_estimators": 100}),  # the default with a 100-tree forest
        "sklearn_builder": dict(tree_builder="sklearn"),  # the default with scikit-learn growing the structures
        "warm_start": dict(mode="warm_start", regressor="lightgbm", trees_per_iteration=10),
        "frozen": dict(mode="frozen", regressor="extra_trees", regressor_params={"min_samples_leaf": 20}),
        "frozen_sub": dict(mode="frozen", regressor="extra_trees", regressor_params={"min_samples_leaf": 20},
                           structure_max_samples=0.125),
        "refit_lightgbm": dict(mode="refit", regressor="lightgbm"),
    }[mode]
    cfg["regressor_params"] = {**cfg.get("regressor_params", {}), "n_jobs": threads}
    f = FittedQIteration(gamma=gamma, n_iterations=iters, **cfg)
    c0, w0 = time.process_time(), time.perf_counter()
    f.fit(ds)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    # VmHWM: this process's own peak (ru_maxrss carries over exec from the forked parent)
    peak = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM:")) / 2**20
    it = f.history_["wall_time"].to_numpy()
    del ds

    # score on the system: the same start states and noise for every controller
    values = np.array([-1.0, 0.0, 1.0])
    erng = np.random.default_rng(12345)
    x0 = erng.normal(size=(eval_episodes, 4))
    noise = 0.1 * erng.normal(size=(eval_horizon, eval_episodes, 4))
    behaviour_actions = erng.integers(0, 3, size=(eval_horizon, eval_episodes))

    def lookahead(x, t):
        nxt = 0.95 * x[:, None, :] + B[None, :, :]  # (m, action, 4): the expected next state
        return np.argmin(0.1 * values[None, :] ** 2 + (nxt ** 2).sum(2), axis=1)

    controllers = {
        "learned": lambda x, t: f.policy_.act_index(x, t),
        "lookahead": lookahead,
        "nothing": lambda x, t: np.full(len(x), 1),
        "behaviour": lambda x, t: behaviour_actions[t],
    }
    scores = {}
    for name, ctl in controllers.items():
        x, total = x0.copy(), np.zeros(eval_episodes)
        for t in range(eval_horizon):
            a = np.asarray(ctl(x, t), dtype=np.int64)
            total += gamma ** t * ((x ** 2).sum(1) + 0.1 * values[a] ** 2)
            x = 0.95 * x + B[a] + noise[t]
        scores[name] = total
    se = lambda v: float(v.std(ddof=1) / np.sqrt(len(v)))
    diff = scores["learned"] - scores["lookahead"]
    print(json.dumps({"n": n, "mode": mode, "threads": threads, "iterations": len(it), "wall_s": wall, "cpu_s": cpu,
                      "median_iter_s": float(np.median(it)), "max_iter_s": float(it.max()), "peak_rss_gib": peak,
                      "start_value": float(f.history_["start_value"].iloc[-1]),
                      "trees": [b["trees"] for b in structure_builds(f.history_)],
                      "cost": {k: [float(v.mean()), se(v)] for k, v in scores.items()},
                      "learned_minus_lookahead": [float(diff.mean()), se(diff)]}))
    """
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    ap.add_argument("--modes", nargs="+", default=["default"])
    ap.add_argument("--iterations", type=lambda v: v if v == "auto" else int(v), default=50,
                    help="a count, or auto (the default fit's n_iterations)")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2],
                    help="n_jobs of the fit's regressor, one run each")
    ap.add_argument("--eval-episodes", type=int, default=1000)
    ap.add_argument("--eval-horizon", type=int, default=200)
    args = ap.parse_args()
    here = Path(__file__).resolve().parent
    env = dict(os.environ, PYTHONPATH=str(here.parent))
    print(f"{'n':>9} {'mode':<15} {'thr':>3} {'iters':>5} {'wall s':>8} {'CPU s':>8} {'median it s':>11} "
          f"{'max it s':>9} "
          f"{'peak RSS GiB':>12}  discounted cost over {args.eval_episodes} rollouts of {args.eval_horizon} steps "
          "(mean +- s.e.)")
    for mode in args.modes:
        for n in args.sizes:
            for threads in args.threads:
                out = subprocess.run([sys.executable, "-c", CHILD, str(n), mode, str(args.iterations), str(threads),
                                      str(args.eval_episodes), str(args.eval_horizon)],
                                     check=True, capture_output=True, text=True, env=env, cwd=here)
                r = json.loads(out.stdout.strip().splitlines()[-1])
                cost = "  ".join(f"{k} {m:.3f}+-{e:.3f}" for k, (m, e) in r["cost"].items())
                d, de = r["learned_minus_lookahead"]
                print(f"{r['n']:>9} {r['mode']:<15} {r['threads']:>3} {r['iterations']:>5} {r['wall_s']:>8.1f} "
                      f"{r['cpu_s']:>8.1f} "
                      f"{r['median_iter_s']:>11.3f} {r['max_iter_s']:>9.3f} {r['peak_rss_gib']:>12.2f}  {cost}  "
                      f"learned-lookahead {d:+.3f}+-{de:.3f}"
                      + (f"   trees per build {'/'.join(map(str, r['trees']))}" if r.get("trees") else ""), flush=True)


if __name__ == "__main__":
    main()
