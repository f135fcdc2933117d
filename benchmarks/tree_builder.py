"""The compiled extra-trees builder against scikit-learn's, side by side in one run.

Data: car-on-the-hill (Ernst et al. 2005; 1000 random episodes, ~56k transitions), the
joint inputs (position, speed, action) and the targets fitted Q-iteration builds its
second structure on (iteration 13: ``c + gamma (1 - terminal) min_a Q_12(x', a)``, from a
12-iteration fit). Both grow 50 fully grown trees (``min_samples_split=2``,
``max_features=1.0``) on one thread; CPU seconds are ``time.process_time()``. The
compiled kernel is compiled (or loaded from numba's cache) before timing.

    python benchmarks/tree_builder.py [--trees 50] [--repeats 3] [--data-seed 0]
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from sklearn.ensemble import ExtraTreesRegressor

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.simulate import simulate
from offline_adp.trees import builder as extra_trees


def car_targets(seed: int) -> tuple[np.ndarray, np.ndarray]:
    ds = simulate("car_on_hill", 0, 1000, seed=seed, horizon=100)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        f = FittedQIteration(gamma=0.95, n_iterations=12, random_state=0).fit(ds)
    a = ds.arrays()
    X = f._encoder.pairs(a.obs, a.action)
    y = a.cost + 0.95 * (1.0 - a.terminated) * f.q_function_.values(a.next_obs).min(axis=1)
    return X, y


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trees", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--data-seed", type=int, default=0)
    args = ap.parse_args()
    X, y = car_targets(args.data_seed)
    print(f"car-on-the-hill: {len(X)} rows x {X.shape[1]} inputs; kernel ready in {extra_trees.warm_up():.1f} CPU-s")
    reg = ExtraTreesRegressor(n_estimators=args.trees, min_samples_split=2, max_features=1.0, n_jobs=1, random_state=0)
    params = extra_trees.native_params(reg, len(X), X.shape[1])
    assert params is not None
    for r in range(args.repeats):
        t = time.process_time()
        forest = reg.set_params(random_state=r).fit(X, y)
        sk = time.process_time() - t
        t = time.process_time()
        grown = extra_trees.grow_trees(X, y, None, params.__class__(**{**params.__dict__, "random_state": r}))
        ours = time.process_time() - t
        nodes_sk = np.mean([e.tree_.node_count for e in forest.estimators_])
        nodes_ours = np.mean([len(g.left) for g in grown])
        print(f"repeat {r}: scikit-learn {sk:.2f} CPU-s ({nodes_sk:.0f} nodes a tree), compiled {ours:.2f} CPU-s "
              f"({nodes_ours:.0f} nodes a tree): {ours / sk:.2f} of scikit-learn's CPU", flush=True)


if __name__ == "__main__":
    main()
