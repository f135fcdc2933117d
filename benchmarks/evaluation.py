"""Evaluation of a 100k-transition path_tracking dataset: OPE + density ratios with bootstrap.

Fits an FQI policy (frozen-structure fast path; not timed), then times
``evaluate_run`` from logs only and with the simulator (rollouts + classifier ratios),
reporting wall time per stage and in total. Target: under 2 minutes on 2 cores.

    python benchmarks/evaluation.py [--transitions 100000] [--fqe-bootstrap 5]
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
    ap.add_argument("--fqe-bootstrap", type=int, default=5)
    ap.add_argument("--bootstrap", type=int, default=200)
    ap.add_argument("--episodes", type=int, default=500, help="rollout episodes with the simulator")
    args = ap.parse_args()
    n_ep = max(2, args.transitions // 110)  # exploration episodes often leave the road early
    ds = simulate("path_tracking", n_ep // 2, n_ep - n_ep // 2, seed=0)
    with tempfile.TemporaryDirectory() as tmp:
        ds.save(Path(tmp) / "ds")
        t0 = time.perf_counter()
        fit_run(Path(tmp) / "ds", Path(tmp) / "run", params={"mode": "frozen", "n_iterations": 40})
        print(f"dataset: {len(ds)} transitions, {n_ep} episodes; FQI fit {time.perf_counter() - t0:.1f} s (not counted)")
        for sim in ("none", "path_tracking"):
            marks: list[tuple[str, float]] = []
            t0 = time.perf_counter()
            m = evaluate_run(Path(tmp) / "run", simulator=sim, n_episodes=args.episodes, n_boot=args.bootstrap,
                             n_boot_fqe=args.fqe_bootstrap, progress=lambda s, marks=marks: marks.append((s, time.perf_counter())))
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


if __name__ == "__main__":
    main()
