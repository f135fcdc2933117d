"""Scale benchmark: fitted Q-iteration on 100k and 1M transitions (4-dim state, 3 actions).

Synthetic linear-Gaussian system x' = 0.95 x + B[a] + noise, cost |x|^2 + 0.1 a^2, episodes
of 100 steps. Each (size, mode) runs 50 iterations in a fresh subprocess so that peak
RSS is its own; per-iteration time is the median of the iterations.

    python benchmarks/fqi_scale.py [--sizes 100000 1000000] [--modes warm_start frozen frozen_sub] [--iterations 50]

Modes: ``default`` (``FittedQIteration``'s defaults: ``mode="auto"``, i.e. frozen extra-trees grown
fully, each structure on at most 131,072 rows), ``warm_start`` (LightGBM, 10 trees an iteration), ``frozen`` (extra-trees,
``min_samples_leaf=20``, the default structure schedule), ``frozen_sub`` (the same with
each tree grown on 1/8 of the rows, ``structure_max_samples=0.125``), ``refit_lightgbm``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import textwrap

CHILD = textwrap.dedent(
    """
    import json, resource, sys, time
    import numpy as np
    from offline_adp import TransitionDataset, DatasetInfo, Feature, ActionTable
    from offline_adp.algorithms.fqi import FittedQIteration, structure_builds
    n, mode, iters = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
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
    info = DatasetInfo(features=tuple(Feature(f"x{i}") for i in range(4)), action_table=ActionTable.from_values([-1.0, 0.0, 1.0]))
    ep = np.repeat(np.char.zfill(np.arange(E).astype(str), 7), T)
    ds = TransitionDataset.from_arrays(info, episode_id=ep, step=np.tile(np.arange(T), E), obs=obs, action=act, cost=cost,
                                       next_obs=nxt, terminated=np.zeros(n, bool), truncated=np.tile(np.arange(T) == T - 1, E))
    del x, obs, nxt
    cfg = {
        "default": {},
        "sklearn_builder": dict(tree_builder="sklearn"),  # the default with scikit-learn growing the structures
        "warm_start": dict(mode="warm_start", regressor="lightgbm", trees_per_iteration=10),
        "frozen": dict(mode="frozen", regressor="extra_trees", regressor_params={"min_samples_leaf": 20}),
        "frozen_sub": dict(mode="frozen", regressor="extra_trees", regressor_params={"min_samples_leaf": 20},
                           structure_max_samples=0.125),
        "refit_lightgbm": dict(mode="refit", regressor="lightgbm"),
    }[mode]
    f = FittedQIteration(gamma=0.95, n_iterations=iters, **cfg)
    c0, w0 = time.process_time(), time.perf_counter()
    f.fit(ds)
    wall = time.perf_counter() - w0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    it = f.history_["wall_time"].to_numpy()
    print(json.dumps({"n": n, "mode": mode, "iterations": len(it), "wall_s": wall, "cpu_s": time.process_time() - c0,
                      "median_iter_s": float(np.median(it)), "max_iter_s": float(it.max()), "peak_rss_gib": peak,
                      "start_value": float(f.history_["start_value"].iloc[-1]),
                      "trees": [b["trees"] for b in structure_builds(f.history_)]}))
    """
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    ap.add_argument("--modes", nargs="+", default=["default"])
    ap.add_argument("--iterations", type=int, default=50)
    args = ap.parse_args()
    print(f"{'n':>9} {'mode':<15} {'iters':>5} {'wall s':>8} {'CPU s':>8} {'median it s':>11} {'max it s':>9} {'peak RSS GiB':>12}")
    for mode in args.modes:
        for n in args.sizes:
            out = subprocess.run([sys.executable, "-c", CHILD, str(n), mode, str(args.iterations)], check=True, capture_output=True, text=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            print(f"{r['n']:>9} {r['mode']:<15} {r['iterations']:>5} {r['wall_s']:>8.1f} {r['cpu_s']:>8.1f} {r['median_iter_s']:>11.3f} "
                  f"{r['max_iter_s']:>9.3f} {r['peak_rss_gib']:>12.2f}"
                  + (f"   trees per build {'/'.join(map(str, r['trees']))}" if r.get("trees") else ""), flush=True)


if __name__ == "__main__":
    main()
