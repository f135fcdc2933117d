"""path_tracking with continuous commands: the exact commands against their coarse bins (issue #41).

For each command mode of path_tracking (problem option ``commands``: ``continuous`` =
steering only, ``steer_accel`` = steering + longitudinal acceleration) one log is
simulated (``--demonstrations`` Stanley-driver episodes with unquantised Gaussian steering
noise, ``--exploration`` episodes of uniform commands, horizon 100, like
``benchmarks/fqi_suite.py``'s path_tracking) and fitted twice with FQI on the same logs:

- ``continuous``: ``commands="continuous"``, Q(x, u) on the exact logged commands, the
  greedy command the minimum over the commands logged at the ``--n-candidates`` nearest
  logged states and the log's ``--n-representatives`` representative commands;
- ``binned``: ``commands="binned"``, the action table's coarse bins (steering: the seven
  commands -0.3..0.3 rad; steer_accel: those x {-2, 0, 2} m/s^2), each row's command
  replaced by its bin.

Each arm is fitted ``--learner-seeds`` times on the same logs (learner seeds ``seed + 1000 j``):
fits of different learner seeds differ by more than the rollouts' noise (per fit, 0.1-0.3
apart), so one fit per arm decides nothing. Each greedy policy is rolled out in the problem's
simulator (:func:`offline_adp.rollout.rollout`, ``--episodes`` episodes, same start states and
seed for every arm and fit; the binned policy steps its bins' representative commands, the
continuous one its commands). Reported per arm: the mean over fits of the mean discounted cost
(lower is better) with its standard error **across fits**, each fit's cost, failures (left
the road, summed over fits), the fit's CPU seconds (``time.process_time``, mean per fit), and
smoothness: mean ``|u_t - u_{t-1}|`` per step, per command component. The paired difference
continuous - binned of the per-episode costs averaged over fits is printed too (its standard
error is over episodes only, so it understates the fit-to-fit spread). The demonstrator
(stochastic) and its noise-free Stanley controller are rolled out too, as references.

Measured (50 + 150 episodes, horizon 100, 50 iterations x 50 trees, 200 rollouts; mean
discounted cost +- se across fits; mean |du| steering). Defaults (8 neighbours + 16
representatives), 8 learner seeds, data seeds 0/1/2: continuous 3.108 +- 0.042 / 3.740 +- 0.047
/ 3.173 +- 0.037 against binned 3.220 +- 0.054 / 3.902 +- 0.054 / 3.224 +- 0.035. With 16
neighbours + 16 representatives:

- continuous steering, 8 learner seeds, data seeds 0/1/2: continuous 3.120 +- 0.030 /
  3.673 +- 0.042 / 3.186 +- 0.048 against binned 3.220 +- 0.054 / 3.902 +- 0.054 / 3.224 +- 0.035
  (lower on all three; on seed 2 by less than a standard error); |du| 0.119/0.123/0.122 against
  0.126/0.129/0.142; failures 0/2/0 of 1600 episodes against 0/1/0.
- before the representatives (the neighbours' commands alone, one fit per arm): 3.128/4.067/3.538
  against 3.271/3.662/3.128; with the action table's 7 bins as the extra candidates instead
  (8 fits, seed 1): 4.011 +- 0.070 against 3.902 +- 0.054.
- steer_accel: see docs/continuous-commands.md (4 learner seeds).
- references: demonstrator 5.49 (steering) / 5.74 (steer_accel); its noise-free Stanley
  controller 5.14 / 5.33.

    nice -n 10 python benchmarks/continuous_path_tracking.py [--modes continuous steer_accel] \
        [--demonstrations 50] [--exploration 150] [--episodes 200] [--seeds 0 1 2] \
        [--learner-seeds 8] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import numpy as np

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.envs import make_problem
from offline_adp.errors import DivergenceWarning
from offline_adp.policies import attach_signature
from offline_adp.rollout import rollout
from offline_adp.simulate import simulate

HORIZON = 100
GAMMA = 0.95


class _Controller:
    """The demonstrator's noise-free controller (its ``commands``) as a deterministic
    continuous policy."""

    continuous = True

    def __init__(self, behaviour) -> None:
        self.behaviour = behaviour

    def commands(self, obs, t=0):
        return self.behaviour.commands(obs, t)


def score(model, policy, n_episodes: int, seed: int) -> dict:
    """Mean discounted cost over ``n_episodes`` rollouts and the mean |u_t - u_{t-1}| per
    component (commands of indices: the action table's values)."""
    values = model.action_table.values
    last: dict[str, np.ndarray] = {}
    jumps: list[np.ndarray] = []

    def on_step(t, idx, xs, a, r):
        u = np.asarray(a, np.float64)
        u = values[u.astype(np.int64)] if u.ndim == 1 else u
        if t > 0:
            jumps.append(np.abs(u - last["u"][idx]))
        full = last.get("u", np.zeros((n_episodes, u.shape[1]))).copy()
        full[idx] = u
        last["u"] = full

    res = rollout(model, policy, n_episodes, np.random.default_rng(seed), horizon=HORIZON, gamma=GAMMA, on_step=on_step)
    j = np.concatenate(jumps) if jumps else np.zeros((0, values.shape[1]))
    return {"costs": res.discounted_cost, "mean_discounted_cost": res.mean,
            "se": float(res.discounted_cost.std(ddof=1) / np.sqrt(len(res.discounted_cost))),
            "failures": int(res.terminated.sum()),
            "smoothness": [float(x) for x in j.mean(axis=0)]}


def run(mode: str, args: argparse.Namespace) -> list[dict]:
    ds = simulate("path_tracking", args.demonstrations, args.exploration, seed=args.seed, horizon=HORIZON,
                  problem_options={"commands": mode})
    model = make_problem("path_tracking", commands=mode)
    dims = list(model.action_table.dims)
    print(f"\npath_tracking commands={mode}: {len(ds)} transitions, {ds.n_episodes} episodes, dims {dims}", flush=True)
    rows = []

    def report(arm: str, sc: dict, cpu: float | None = None, extra: dict | None = None) -> None:
        row = {"mode": mode, "seed": args.seed, "arm": arm, **{k: v for k, v in sc.items() if k != "costs"},
               "cpu_s": cpu, **(extra or {})}
        rows.append(row)
        sm = ", ".join(f"{d} {s:.4f}" for d, s in zip(dims, sc["smoothness"], strict=True))
        print(f"  {arm:<22} cost {sc['mean_discounted_cost']:7.3f} +- {sc['se']:.3f}  failures {sc['failures']:3d}  "
              f"CPU {'-' if cpu is None else f'{cpu:6.1f} s'}  mean|du| {sm}", flush=True)

    demo = model.demonstrator()
    report("demonstrator", score(model, demo, args.episodes, 123))
    report("stanley (noise-free)", score(model, _Controller(demo), args.episodes, 123))
    costs = {}
    for arm, params in (("continuous", {"commands": "continuous", "n_candidates": args.n_candidates,
                                        "n_representatives": args.n_representatives}),
                        ("binned", {"commands": "binned"})):
        per_fit, cpu = [], 0.0
        for ls in range(args.learner_seeds):  # fits of other learner seeds on the same logs
            est = FittedQIteration(gamma=GAMMA, n_iterations=args.iterations, random_state=args.seed + 1000 * ls,
                                   regressor_params={"n_estimators": args.trees}, **params)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DivergenceWarning)
                c0 = time.process_time()
                est.fit(ds)
                cpu += time.process_time() - c0
            per_fit.append(score(model, attach_signature(est.policy_, ds), args.episodes, 123))
        sc = {"costs": np.mean([p["costs"] for p in per_fit], axis=0),  # per episode, averaged over the fits
              "failures": int(sum(p["failures"] for p in per_fit)),
              "smoothness": list(np.mean([p["smoothness"] for p in per_fit], axis=0))}
        sc["per_fit"] = [p["mean_discounted_cost"] for p in per_fit]
        sc["mean_discounted_cost"] = float(np.mean(sc["per_fit"]))  # = the per-episode average's mean
        # the standard error ACROSS fits: fits of other learner seeds on the same logs differ by more than
        # the rollouts' own noise (per fit, sd ~0.1-0.3 against an episode se of ~0.1 / sqrt(200))
        sc["se"] = float(np.std(sc["per_fit"], ddof=1) / np.sqrt(len(per_fit))) if len(per_fit) > 1 else float("nan")
        costs[arm] = sc["costs"]
        report(arm, sc, cpu / len(per_fit), {"iterations": len(est.history_), "verdict": est.verdict_,
                                             "commands": est.commands_})
        print(f"    per fit: {', '.join(f'{c:.3f}' for c in sc['per_fit'])}", flush=True)
    d = costs["continuous"] - costs["binned"]
    paired = {"mode": mode, "seed": args.seed, "arm": "continuous - binned (paired)",
              "mean_difference": float(d.mean()),
              "se": float(d.std(ddof=1) / np.sqrt(len(d)))}
    rows.append(paired)
    print(f"  continuous - binned: {paired['mean_difference']:+.3f} +- {paired['se']:.3f} (paired)", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--modes", nargs="+", default=["continuous", "steer_accel"], choices=["continuous", "steer_accel"])
    ap.add_argument("--demonstrations", type=int, default=50)
    ap.add_argument("--exploration", type=int, default=150)
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--trees", type=int, default=50)
    ap.add_argument("--n-candidates", type=int, default=8)
    ap.add_argument("--n-representatives", type=int, default=16,
                    help="the continuous arm's representative commands of the log (0: the neighbours' alone)")
    ap.add_argument("--learner-seeds", type=int, default=4,
                    help="fits per arm on the same logs (learner seeds seed + 1000 j); costs averaged per episode")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="data (and learner) seeds")
    ap.add_argument("--json")
    a = ap.parse_args()
    rows = []
    for seed in a.seeds:
        a.seed = seed
        for mode in a.modes:
            rows += run(mode, a)
        if a.json:
            with open(a.json, "w") as f:
                json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
