"""By hand: the default FQI mode (frozen extra-trees) on a 2-worker Dask LocalCluster over
~10M logged transitions, with every process's peak RSS (issue #33: no process above 6 GiB).

Data: random-action car-on-the-hill episodes of up to 100 steps from uniform start states
(vectorised over episodes; whole episodes, about ``--rows`` transitions), saved as a
dataset directory once (``--data``, reused when it exists). Fit:
``FittedQIteration(gamma=0.95, n_iterations=..., regressor_params={"n_jobs": 1})`` through
``DaskFit`` on ``EngineConfig(kind="dask", n_workers=2, threads_per_worker=1)``. Printed per
iteration: elapsed wall, the structure, sup|dQ| and the peak RSS (VmHWM) of the client
(which hosts the scheduler) and of each worker; at the end a JSON line.

    python benchmarks/dask_10m.py [--rows 10000000] [--data /tmp/ds10m] [--iterations 20|auto]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from dask_scale import tree_cpu  # this directory is on the path when the script runs

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.data.dataset import TransitionDataset
from offline_adp.engines.dask import DaskFit, EngineConfig, dask_client
from offline_adp.envs import CarOnHill


def make(n_target: int, out: Path) -> None:
    prob = CarOnHill(horizon=None)
    rng = np.random.default_rng(0)
    E = int(n_target / 16.0)  # random play ends an episode after ~17 steps
    x = np.column_stack([rng.uniform(-1, 1, E), rng.uniform(-3, 3, E)])
    alive = np.ones(E, bool)
    cols: dict[str, list[np.ndarray]] = {k: [] for k in ("ep", "step", "obs", "a", "c", "nxt", "term", "trunc")}
    for t in range(100):
        idx = np.flatnonzero(alive)
        if not len(idx):
            break
        a = rng.integers(0, 2, len(idx))
        r = prob.step_seeded(x[idx], a)
        for k, v in (("ep", idx), ("step", np.full(len(idx), t)), ("obs", x[idx].copy()), ("a", a), ("c", r.costs),
                     ("nxt", r.next_states), ("term", r.terminated), ("trunc", ~r.terminated & (t == 99))):
            cols[k].append(v)
        x[idx] = r.next_states
        alive[idx[r.terminated]] = False
    c = {k: np.concatenate(v) for k, v in cols.items()}
    order = np.lexsort((c["step"], c["ep"]))
    c = {k: v[order] for k, v in c.items()}
    if len(order) > n_target:  # whole episodes only
        keep = c["ep"] < c["ep"][n_target - 1]
        c = {k: v[keep] for k, v in c.items()}
    TransitionDataset.from_arrays(prob.dataset_info(), episode_id=np.char.zfill(c["ep"].astype(str), 7), step=c["step"],
                                  obs=c["obs"], action=c["a"], cost=c["c"], next_obs=c["nxt"], terminated=c["term"],
                                  truncated=c["trunc"]).save(out)


def peak_gib() -> float:
    """This process's own peak RSS (VmHWM), GiB."""
    return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM:")) / 2**20


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=int, default=10_000_000)
    ap.add_argument("--data", type=Path, default=Path("/tmp/ds10m"))
    ap.add_argument("--iterations", default="20", help="an integer, or auto")
    args = ap.parse_args()
    if not args.data.exists():
        t = time.perf_counter()
        make(args.rows, args.data)
        print(f"data: {args.data} written in {time.perf_counter() - t:.0f} s", flush=True)
    n_it = "auto" if args.iterations == "auto" else int(args.iterations)
    est = FittedQIteration(gamma=0.95, n_iterations=n_it, regressor_params={"n_jobs": 1})
    t0, c0 = time.perf_counter(), tree_cpu()
    with dask_client(EngineConfig(kind="dask", n_workers=2, threads_per_worker=1, memory_limit="8GiB")) as client:
        for row in DaskFit(client).fit_iter(est, args.data):
            w = client.run(peak_gib)
            print(f"it {row['iteration']:3d}  {time.perf_counter() - t0:7.1f} s  structure {row.get('structure')}  "
                  f"sup_dq {row['sup_dq']:.4g}  peak RSS GiB: client {peak_gib():.2f}, workers "
                  + ", ".join(f"{v:.2f}" for v in sorted(w.values())), flush=True)
        wall, cpu = time.perf_counter() - t0, tree_cpu() - c0
        workers = sorted(client.run(peak_gib).values())
    print(json.dumps({"wall_s": wall, "cpu_s": cpu,
                      "iterations": len(est.history_), "mode": est.mode_, "client_peak_gib": peak_gib(),
                      "worker_peak_gib": workers, "verdict": est.verdict_message_}), flush=True)


if __name__ == "__main__":
    main()
