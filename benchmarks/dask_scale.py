"""One-machine scale check of the Dask engine: FQI with LightGBM, local multi-thread vs
Dask 2 workers x 1 thread, at 1M and 4M transitions.

Data: uniformly random car-on-the-hill states and actions, one step each (the
"uniform" setting of Ernst et al.), saved as a dataset directory (500k-row parts).
Timed: the second FQI iteration on each side (its targets need the batched prediction of
Q_1), after the data is loaded (local: read into memory; Dask: read and spread over the
workers).
Reported: seconds per iteration, the Dask/local ratio (target < 1.2), and the peak RSS of
each worker process; the same for the warm-start mode (10 new trees per iteration from
cached predictions; timed: the mean of iterations 2-5).

    python benchmarks/dask_scale.py [--sizes 1000000 4000000]
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.io import read_dataset
from offline_adp.engines.dask import DistributedFQI, EngineConfig, dask_client
from offline_adp.envs import CarOnHill

PARAMS = {"n_estimators": 100, "num_leaves": 31, "learning_rate": 0.1}


def make(n: int, path: Path) -> None:
    rng = np.random.default_rng(0)
    prob = CarOnHill(horizon=None)
    x = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-3, 3, n)])
    a = rng.integers(0, 2, n)
    r = prob.step_seeded(x, a)
    ids = np.char.zfill(np.arange(n).astype(str), 8)
    TransitionDataset.from_arrays(prob.dataset_info(), episode_id=ids, step=np.zeros(n), obs=x, action=a, cost=r.costs,
                                  next_obs=r.next_states, terminated=r.terminated, truncated=~r.terminated).save(path)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1_000_000, 4_000_000])
    args = ap.parse_args()
    print(f"{'transitions':>12s} {'mode':>10s} {'local s/it':>10s} {'dask s/it':>10s} {'ratio':>6s}  worker peak RSS (MB)")
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sizes:
            path = Path(tmp) / f"coh{n}"
            make(n, path)
            ds = read_dataset(path)
            est = FittedQIteration(gamma=0.95, regressor="lightgbm", regressor_params=PARAMS, n_iterations=2).fit(ds)
            local = {"refit": float(est.history_["wall_time"].iloc[1])}  # the second iteration: targets need a prediction
            est = FittedQIteration(gamma=0.95, regressor="lightgbm", regressor_params=PARAMS, n_iterations=5,
                                   mode="warm_start", trees_per_iteration=10).fit(ds)
            local["warm_start"] = float(est.history_["wall_time"].iloc[1:].mean())
            del ds, est
            for mode, n_it in (("refit", 2), ("warm_start", 5)):
                with dask_client(EngineConfig(kind="dask", n_workers=2, threads_per_worker=1, memory_limit="10GiB")) as client:
                    marks: list[float] = []
                    t0 = time.perf_counter()
                    DistributedFQI(gamma=0.95, n_iterations=n_it, lgbm_params=PARAMS, warm_start=mode == "warm_start",
                                   trees_per_iteration=10).fit(
                        client, path, on_iteration=lambda k, marks=marks: marks.append(time.perf_counter()))
                    dask_it = (marks[-1] - marks[0]) / (n_it - 1)  # iterations 2.. (data already spread)
                    first = marks[0] - t0
                    rss = client.run(peak_rss_mb)
                print(f"{n:12d} {mode:>10s} {local[mode]:10.2f} {dask_it:10.2f} {dask_it / local[mode]:6.2f}  "
                      + ", ".join(f"{v:.0f}" for v in rss.values())
                      + f"   (dask first iteration incl. load+spread {first:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
