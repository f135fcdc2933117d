"""FQI, API, CPI and PSDP side by side on car-on-the-hill and path tracking.

For each problem and algorithm: the score (car-on-hill: Ernst et al.'s 289-state grid
score, higher is better; path tracking: mean discounted cost over H-step episodes from
the start distribution and mean |cross-track error|, lower is better), CPU time, and
the simulator steps used for learning (0 for algorithms that learn from logs only;
evaluation rollouts are not counted). Path tracking also shows the demonstrator.

    python benchmarks/compare_algorithms.py [--problems car_on_hill path_tracking] [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from offline_adp.algorithms.api import ApproximatePolicyIteration
from offline_adp.algorithms.cpi import ConservativePolicyIteration
from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.algorithms.psdp import PSDP, IteratedPSDP
from offline_adp.envs import CarOnHill, PathTracking
from offline_adp.envs.car_on_hill import score as coh_score
from offline_adp.rollout import rollout
from offline_adp.simulate import simulate


def timed(fn):
    c0 = time.process_time()
    out = fn()
    return out, time.process_time() - c0


def car_on_hill(quick: bool) -> list[tuple]:
    ds = simulate("car_on_hill", 0, 300 if quick else 1000, seed=0, horizon=100)
    model = CarOnHill(horizon=100)
    its = 20 if quick else 50
    fqe = FittedQEvaluation(gamma=0.95, n_iterations=its, mode="frozen")
    rows = []
    fqi, cpu = timed(lambda: FittedQIteration(gamma=0.95, n_iterations=its, mode="frozen").fit(ds))
    rows.append(("FQI (extra-trees, frozen)", coh_score(fqi.policy_), cpu, 0))
    api, cpu = timed(lambda: ApproximatePolicyIteration(fqe, n_iterations=3 if quick else 5).fit(ds))
    rows.append(("API (FQE, frozen)", coh_score(api.policy_), cpu, 0))
    # deterministic start
    cpi, cpu = timed(lambda: ConservativePolicyIteration(fqe, n_iterations=3 if quick else 5, model=model,
                                                         n_eval_episodes=1,
                                                         step_sizes=(0.25, 0.5, 1.0)).fit(ds))
    rows.append(("CPI (line search, rollouts)", coh_score(cpi.policy_), cpu, cpi.simulator_steps_))

    def uniform_states(t: int, n: int, rng: np.random.Generator) -> np.ndarray:
        return np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-3, 3, n)])

    T = 30 if quick else 50
    psdp, cpu = timed(lambda: PSDP(horizon=T, n_samples=500 if quick else 2000, n_rollouts=1, classifier="extra_trees",
                                   gamma=0.95).fit(model, uniform_states))
    rows.append((f"PSDP (T={T}, mu_t uniform)", coh_score(psdp.policy_), cpu, psdp.simulator_steps_))
    return rows


def path_tracking(quick: bool) -> list[tuple]:
    H = 50
    ds = simulate("path_tracking", 60 if quick else 150, 60 if quick else 150, seed=0, horizon=200)
    model = PathTracking(horizon=H)
    rng_eval = 12345

    def evaluate(policy):
        res = rollout(model, policy, 300, np.random.default_rng(rng_eval), horizon=H, gamma=0.95)
        r2 = rollout(model, policy, 300, np.random.default_rng(rng_eval), horizon=H, gamma=1.0)
        return res.mean, float((r2.total_cost / np.maximum(r2.length, 1)).mean()), int(res.terminated.sum())

    its = 20 if quick else 50
    rows = []
    demo = model.demonstrator()
    rows.append(("demonstrator", *evaluate(demo), 0.0, 0))
    fqi, cpu = timed(lambda: FittedQIteration(gamma=0.95, n_iterations=its, mode="frozen").fit(ds))
    rows.append(("FQI (extra-trees, frozen)", *evaluate(fqi.policy_), cpu, 0))
    fqe = FittedQEvaluation(gamma=0.95, n_iterations=its, mode="frozen")
    api, cpu = timed(lambda: ApproximatePolicyIteration(fqe, n_iterations=3, initial_policy=demo).fit(ds))
    rows.append(("API (FQE, frozen; from demonstrator)", *evaluate(api.policy_), cpu, 0))
    cpi, cpu = timed(lambda: ConservativePolicyIteration(fqe, n_iterations=3, initial_policy=demo,
                                                         step_sizes=(0.25, 0.5, 1.0)).fit(ds))
    rows.append(("CPI (line search, FQE estimates)", *evaluate(cpi.policy_), cpu, 0))
    demos = ds.filter_source("demonstration")
    psdp_proto = PSDP(horizon=H, n_samples=300, n_rollouts=1, gamma=0.95, learner="regression", regressor="extra_trees",
                      learner_params={"n_estimators": 20, "min_samples_leaf": 2, "n_jobs": 1},
                      feature_map=drop_progress)
    psdp, cpu = timed(lambda: psdp_proto.fit(model, demos))
    rows.append(("PSDP (regression; mu_t = logged demos)", *evaluate(psdp.policy_), cpu, psdp.simulator_steps_))
    cls_proto = PSDP(horizon=H, n_samples=300, n_rollouts=1, gamma=0.95, feature_map=drop_progress)
    it, cpu = timed(lambda: IteratedPSDP(cls_proto, n_rounds=2 if quick else 3, n_eval_episodes=200).fit(model, demo))
    rows.append(("iterated PSDP (classif.; from demonstr.)", *evaluate(it.policy_), cpu,
                 int(it.history_["simulator_steps"].sum())))
    return rows


def drop_progress(obs: np.ndarray) -> np.ndarray:
    """PSDP's view of a path-tracking state: everything but the progress ``s``."""
    return obs[:, 1:]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problems", nargs="+", default=["car_on_hill", "path_tracking"])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    if "car_on_hill" in args.problems:
        print("car-on-the-hill: score on the 289-state grid (higher is better)")
        print(f"  {'algorithm':<38} {'score':>8} {'CPU s':>8} {'sim steps':>10}")
        for name, sc, cpu, steps in car_on_hill(args.quick):
            print(f"  {name:<38} {sc:>+8.4f} {cpu:>8.1f} {steps:>10}", flush=True)
    if "path_tracking" in args.problems:
        print("path tracking: 50-step episodes, 300 rollouts (lower is better)")
        print(f"  {'algorithm':<38} {'disc. cost':>10} {'cost/step':>9} {'failures':>8} {'CPU s':>8} {'sim steps':>10}")
        for name, dc, cps, fails, cpu, steps in path_tracking(args.quick):
            print(f"  {name:<38} {dc:>10.3f} {cps:>9.4f} {fails:>8} {cpu:>8.1f} {steps:>10}", flush=True)


if __name__ == "__main__":
    main()
