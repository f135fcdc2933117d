"""CPU of the importance-sampling family's trajectory bootstrap (IS, WIS, PDIS, WPDIS, DR, WDR, MIS).

Synthetic logs of ``--episodes`` episodes of ``--horizon`` steps (lengths uniform in
``[horizon / 2, horizon]``), lognormal per-step ratios, costs, ``Q^`` and ``V^``; each family
is timed with ``time.process_time`` at ``--boot`` resamples (the evaluation's default 200), one
thread unless ``OMP/MKL/OPENBLAS_NUM_THREADS`` say otherwise. The estimates and intervals are
printed so two source trees can be compared side by side
(``PYTHONPATH=OTHER_TREE python benchmarks/ope_bootstrap.py``)::

    python benchmarks/ope_bootstrap.py --episodes 10000 --horizon 100
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=10_000)
    ap.add_argument("--horizon", type=int, default=100)
    ap.add_argument("--boot", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from offline_adp.evaluation import ope

    rng = np.random.default_rng(args.seed)
    T = args.horizon
    lengths = rng.integers(max(1, T // 2), T + 1, args.episodes)
    episode = np.repeat(np.arange(args.episodes), lengths)
    step = np.concatenate([np.arange(k) for k in lengths])
    n = len(episode)
    rho = np.exp(rng.normal(0.0, 0.02, n))
    cost = rng.normal(1.0, 1.0, n)
    q = cost + rng.normal(0.0, 0.5, n)
    v = q + rng.normal(0.0, 0.2, n)
    w_state = np.exp(rng.normal(0.0, 0.2, n))
    em = ope.EpisodeMatrix.build(episode, step, T)
    print(f"{args.episodes} episodes, {n} rows, horizon {T}, {args.boot} resamples", flush=True)
    runs = (("is/wis/pdis/wpdis", lambda: ope.importance_sampling_estimates(em, cost, rho, 0.99, n_boot=args.boot)),
            ("dr/wdr", lambda: ope.doubly_robust_estimates(em, cost, rho, q, v, 0.99, n_boot=args.boot)),
            ("mis", lambda: {"mis": ope.marginalised_is_estimate(em, cost, rho, w_state, 0.99, n_boot=args.boot)}))
    total = 0.0
    for name, fn in runs:
        c0 = time.process_time()
        res = fn()
        cpu = time.process_time() - c0
        total += cpu
        print(f"{name:<18} CPU {cpu:8.2f} s", flush=True)
        for k, r in res.items():
            print(f"    {k:<6} {r.estimate:+.12f}  [{r.interval[0]:+.12f}, {r.interval[1]:+.12f}]"
                  + (f"  vs logged [{r.vs_logged[0]:+.10f}, {r.vs_logged[1]:+.10f}]" if r.vs_logged else ""))
    print(f"{'total':<18} CPU {total:8.2f} s")


if __name__ == "__main__":
    main()
