"""One-machine scale check of the Dask engine: FQI with LightGBM, local vs Dask
2 workers x 1 thread.

Data: uniformly random car-on-the-hill states and actions, one step each (the
"uniform" setting of Ernst et al.), saved as a dataset directory (500k-row parts).
Timed, on each side: iterations 2..K (their targets need the batched prediction of
Q_{k-1}), after the data is loaded (local: read into memory; Dask: read and spread over
the workers, i.e. the first iteration). Reported per iteration: wall seconds and CPU
seconds (the Dask side counts this process, i.e. client and scheduler, plus every worker
and nanny process), the Dask/local wall ratio (target < 1.2), the workers' peak RSS; for
the refit mode (``--iterations``, default 3) and the warm-start mode (10 new trees per
iteration from cached predictions, ``--warm-iterations``, default 5).

The default mode (``--modes frozen``: ``FittedQIteration()``, frozen extra-trees,
``n_iterations="auto"``) is run whole, each run in a child process: locally, then on a
LocalCluster of 1, 2 and 4 workers x 1 thread (``--workers``). Reported per run: wall and
CPU seconds of the fit (CPU of every process: client, scheduler, workers, nannies), peak
RSS of each process (the client's: the child's), the iterations, the car-on-the-hill
score of the greedy policy (Ernst et al.'s 289-state grid) and a hash of Q on that grid
(equal hashes: the same Q bit for bit).

    python benchmarks/dask_scale.py [--sizes 1000000 4000000] [--modes refit warm_start frozen] [--no-local]
                                    [--data uniform|episodes] [--workers 1 2 4]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.data.dataset import TransitionDataset, read_dataset
from offline_adp.engines.dask import DistributedFQI, EngineConfig, dask_client
from offline_adp.envs import CarOnHill

PARAMS = {"n_estimators": 100, "num_leaves": 31, "learning_rate": 0.1}


def make_episodes(n: int, path: Path) -> None:
    """Logged episodes instead (``--data episodes``): random-action car-on-the-hill episodes
    of up to 100 steps from the package's simulator, about ``n`` transitions; most rows
    continue the previous one and 1-2% start an episode."""
    from offline_adp.simulate import simulate

    simulate("car_on_hill", 0, max(1, n // 52), seed=0, horizon=100).save(path)


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


def tree_cpu() -> float:
    """CPU seconds of this process and all its live descendants (Dask workers, nannies)."""
    me = psutil.Process()
    total = sum(me.cpu_times()[:2])
    for p in me.children(recursive=True):
        try:
            total += sum(p.cpu_times()[:2])
        except psutil.NoSuchProcess:
            pass
    return total


def frozen_child(path: str, workers: int) -> None:
    """One default-mode fit (``workers`` 0: in this process), its numbers as a JSON line."""
    from offline_adp.engines.dask import DaskFit
    from offline_adp.envs.car_on_hill import score, score_grid

    est = FittedQIteration(gamma=0.95, regressor_params={"n_jobs": 1})  # the default fit, one thread a process
    t0, c0 = time.perf_counter(), tree_cpu()
    if workers == 0:
        est.fit(read_dataset(path))
        rss = {}
    else:
        with dask_client(EngineConfig(kind="dask", n_workers=workers, threads_per_worker=1,
                                      memory_limit="10GiB")) as client:
            for _ in DaskFit(client).fit_iter(est, path):
                pass
            wall, cpu = time.perf_counter() - t0, tree_cpu() - c0  # before the workers go
            rss = client.run(peak_rss_mb)
    if workers == 0:
        wall, cpu = time.perf_counter() - t0, tree_cpu() - c0
    q = est.q_function_.values(score_grid())
    print(json.dumps({"wall": wall, "cpu": cpu, "client_rss": peak_rss_mb(), "worker_rss": sorted(rss.values()),
                      "iterations": len(est.history_), "score": score(est.policy_),
                      "q_hash": hashlib.sha256(q.tobytes()).hexdigest()[:10]}), flush=True)


def frozen(n: int, path: Path, workers: list[int], local: bool) -> None:
    for w in ([0] if local else []) + workers:
        out = subprocess.run([sys.executable, __file__, "--child", str(path), str(w)], capture_output=True, text=True,
                             check=True).stdout.strip().splitlines()[-1]
        r = json.loads(out)
        where = "local" if w == 0 else f"dask x{w}"
        print(f"{n:12d} {'frozen':>10s} {where:>8s} wall {r['wall']:7.1f} s  cpu {r['cpu']:7.1f} s  "
              f"it {r['iterations']:3d}  score {r['score']:.4f}  Q {r['q_hash']}  peak RSS MB: client "
              f"{r['client_rss']:.0f}" + (", workers " + ", ".join(f"{v:.0f}" for v in r["worker_rss"]) if w else ""),
              flush=True)


def main() -> None:
    if len(sys.argv) == 4 and sys.argv[1] == "--child":
        frozen_child(sys.argv[2], int(sys.argv[3]))
        return
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1_000_000, 4_000_000])
    ap.add_argument("--modes", nargs="+", default=["refit", "warm_start"], choices=["refit", "warm_start", "frozen"])
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4], help="cluster sizes of the frozen mode")
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--warm-iterations", type=int, default=5)
    ap.add_argument("--no-local", action="store_true", help="time the Dask side only")
    ap.add_argument("--data", choices=["uniform", "episodes"], default="uniform",
                    help="one-step transitions from uniform states (every row starts an episode), or logged episodes")
    args = ap.parse_args()
    print(f"{'transitions':>12s} {'mode':>10s} {'local s/it':>10s} {'cpu/it':>7s} {'dask s/it':>10s} {'cpu/it':>7s} "
          f"{'ratio':>6s}  worker peak RSS (MB)")
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sizes:
            path = Path(tmp) / f"coh{n}"
            (make if args.data == "uniform" else make_episodes)(n, path)
            if "frozen" in args.modes:
                frozen(n, path, args.workers, not args.no_local)
            lgbm = [m for m in args.modes if m != "frozen"]
            if not lgbm:
                continue
            ds = read_dataset(path)
            local = {mode: (float("nan"), float("nan")) for mode in lgbm}
            for mode in [] if args.no_local else lgbm:
                n_it = args.iterations if mode == "refit" else args.warm_iterations
                est = FittedQIteration(gamma=0.95, regressor="lightgbm", regressor_params=PARAMS, n_iterations=n_it,
                                       mode=mode, trees_per_iteration=10).fit(ds)
                h = est.history_.iloc[1:]  # iterations 2..: targets need a prediction
                local[mode] = (float(h["wall_time"].mean()), float(h["cpu_time"].mean()))
            del ds
            for mode in lgbm:
                n_it = args.iterations if mode == "refit" else args.warm_iterations
                with dask_client(EngineConfig(kind="dask", n_workers=2, threads_per_worker=1,
                                              memory_limit="10GiB")) as client:
                    marks: list[tuple[float, float]] = []
                    t0 = time.perf_counter()
                    DistributedFQI(gamma=0.95, n_iterations=n_it, lgbm_params=PARAMS, warm_start=mode == "warm_start",
                                   trees_per_iteration=10).fit(
                        client, path, on_iteration=lambda k,
                        marks=marks: marks.append((time.perf_counter(), tree_cpu())))
                    dask_it = (marks[-1][0] - marks[0][0]) / (n_it - 1)  # iterations 2.. (data already spread)
                    dask_cpu = (marks[-1][1] - marks[0][1]) / (n_it - 1)
                    first = marks[0][0] - t0
                    rss = client.run(peak_rss_mb)
                lw, lc = local[mode]
                print(f"{n:12d} {mode:>10s} {lw:10.2f} {lc:7.2f} {dask_it:10.2f} {dask_cpu:7.2f} {dask_it / lw:6.2f}  "
                      + ", ".join(f"{v:.0f}" for v in rss.values())
                      + f"   (dask first iteration incl. load+spread {first:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
