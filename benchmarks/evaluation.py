"""Evaluation of a 100k-transition path_tracking dataset: OPE + density ratios with bootstrap.

Fits an FQI policy (frozen-structure fast path; not timed), then times
``evaluate_run`` from logs only and with the simulator (rollouts + classifier ratios),
reporting wall time per stage and in total. Target: under 2 minutes on 2 cores.

    python benchmarks/evaluation.py [--transitions 100000] [--fqe-bootstrap N]
    python benchmarks/evaluation.py --tabular   # FQE bootstrap replicates on a tabular MDP:
                                                # vectorised (all at once) vs one refit each
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from offline_adp.evaluation.run import evaluate_run
from offline_adp.runs import fit_run
from offline_adp.simulate import simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--transitions", type=int, default=100_000)
    ap.add_argument("--fqe-bootstrap", type=int, default=None, help="default: the evaluation's replicate floor")
    ap.add_argument("--tabular", action="store_true", help="time the tabular FQE replicates instead")
    ap.add_argument("--bootstrap", type=int, default=200)
    ap.add_argument("--episodes", type=int, default=500, help="rollout episodes with the simulator")
    args = ap.parse_args()
    if args.tabular:
        return tabular_replicates()
    n_ep = max(2, args.transitions // 110)  # exploration episodes often leave the road early
    ds = simulate("path_tracking", n_ep // 2, n_ep - n_ep // 2, seed=0)
    with tempfile.TemporaryDirectory() as tmp:
        ds.save(Path(tmp) / "ds")
        t0 = time.perf_counter()
        fit_run(Path(tmp) / "ds", Path(tmp) / "run", params={"mode": "frozen", "n_iterations": 40})
        print(f"dataset: {len(ds)} transitions, {n_ep} episodes; FQI fit {time.perf_counter() - t0:.1f} s "
              "(not counted)")
        for sim in ("none", "path_tracking"):
            marks: list[tuple[str, float]] = []
            t0 = time.perf_counter()
            m = evaluate_run(Path(tmp) / "run", simulator=sim, n_episodes=args.episodes, n_boot=args.bootstrap,
                             n_boot_fqe=args.fqe_bootstrap, progress=lambda s,
                             marks=marks: marks.append((s, time.perf_counter())))
            total = time.perf_counter() - t0
            stages: dict[str, float] = {}
            for (name, t), (_, t_next) in zip(marks, marks[1:] + [("end", t0 + total)], strict=True):
                key = "FQE bootstrap" if name.startswith("FQE bootstrap") else name
                stages[key] = stages.get(key, 0.0) + t_next - t
            print(f"\nsimulator={sim}: total {total:.1f} s (target < 120 s)")
            for k, v in stages.items():
                print(f"  {k:45s} {v:6.1f} s")
            f = m["ope"]["fqe"]
            print(f"  FQE {f['estimate']:.3f} [{f['interval'][0]:.3f}, {f['interval'][1]:.3f}]"
                  + (f"; rollout truth {m['rollout']['policy']['mean_discounted_cost']:.3f}" if "rollout" in m else ""))


def tabular_replicates(n_episodes: int = 1000, n_boot: int = 200, horizon: int = 10) -> None:
    """200 trajectory-bootstrap replicates of time-indexed tabular FQE, 30 states x 3 actions."""
    import numpy as np

    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.envs.tabular import TabularMDP
    from offline_adp.evaluation import ope
    from offline_adp.evaluation.fqe_interval import tabular_fqe_replicates
    from offline_adp.policies import EpsilonPolicy, TabularPolicy
    from offline_adp.simulate import collect

    mdp = TabularMDP(30, 3, horizon=horizon, gamma=0.9, seed=3)
    opt = TabularPolicy(mdp.optimal().policy, 3)
    pib, pi = EpsilonPolicy(opt, 0.8), EpsilonPolicy(opt, 0.3)
    ds = collect(mdp, pib, n_episodes, np.random.default_rng(0), horizon=horizon)
    a = ds.arrays()
    em = ope.EpisodeMatrix.build(a.episode, a.step, horizon)
    W = np.array([c[em.row_episode] for c in ope.bootstrap_counts(em.n_episodes, n_boot, 0)])
    t0 = time.perf_counter()
    fast = tabular_fqe_replicates(a.obs, a.action, a.cost, a.next_obs, a.terminated, a.step == 0, pi, 3, horizon, 0.9,
                                  W)
    t_fast = time.perf_counter() - t0
    k = 20
    t0 = time.perf_counter()
    for w in W[:k]:
        FittedQEvaluation(policy=pi, horizon=horizon, gamma=0.9, regressor="tabular", action_encoding="per_action").fit(
            ds, sample_weight=w)
    t_refit = (time.perf_counter() - t0) / k * n_boot
    print(f"{len(a)} transitions, {n_boot} replicates: vectorised {t_fast:.2f} s, refits {t_refit:.1f} s "
          f"(extrapolated from {k}), x{t_refit / t_fast:.0f}; replicate sd {fast.std():.4f}")


if __name__ == "__main__":
    main()
