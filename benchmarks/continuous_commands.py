"""Continuous commands against bins, side by side on the same logs (issue #41).

For each problem the same log is fitted twice with FQI's defaults: once over the exact
logged commands (``commands="continuous"``: the minimum over the commands logged at the
nearest logged states) and once over the action table's bins (``commands="binned"``).
Reported per arm: the score, the fit's CPU seconds (``time.process_time``, this process),
and command smoothness (mean ``|u_t - u_{t-1}|`` per step over the scored episodes).

Problems:

- ``Pendulum-v1``: random play (uniform torque in [-2, 2], each held 1-8 steps,
  :func:`offline_adp.envs.gym.record_random_log`), 50,000 transitions, gamma 0.99; the bins
  are 11 equal-width torque bins (representative: the mean logged torque in each);
  score = mean return over 100 episodes seeded 10_000 + i.
- ``MountainCarContinuous-v0``: random play with episodes of up to 2000 steps (so the log
  holds goal-reaching episodes), 50,000 transitions, gamma 0.99, 11 bins; score = mean
  return over 100 episodes (gymnasium's 999-step limit).

    nice -n 10 python benchmarks/continuous_commands.py [--problems Pendulum-v1] \
        [--transitions 50000] [--episodes 100] [--seeds 0] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from gym_returns import returns  # noqa: E402

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import ACTION_VALUE_PREFIX, Action, ActionTable, DatasetInfo, Feature
from offline_adp.errors import DivergenceWarning

PROBLEMS = {"Pendulum-v1": {}, "MountainCarContinuous-v0": {"max_episode_steps": 2000}}


def command_dataset(log: dict[str, np.ndarray], low: np.ndarray, high: np.ndarray, n_bins: int, name: str,
                    gamma: float = 0.99) -> TransitionDataset:
    """A dataset of a random-play log with continuous commands: the exact commands in
    ``action_value.<dim>`` and, as the ``action`` column, ``n_bins`` equal-width bins per
    component (one-component commands only here), each represented by its mean command."""
    u = np.asarray(log["action"], np.float64).reshape(len(log["reward"]), -1)
    if u.shape[1] != 1:
        raise SystemExit("this benchmark bins one-component commands only")
    edges = np.linspace(low[0], high[0], n_bins + 1)
    idx = np.clip(np.searchsorted(edges, u[:, 0], side="right") - 1, 0, n_bins - 1)
    reps = [float(u[idx == b, 0].mean()) if (idx == b).any() else float((edges[b] + edges[b + 1]) / 2)
            for b in range(n_bins)]
    table = ActionTable(actions=tuple(Action(f"u={r:.3g}#{b}", (r,)) for b, r in enumerate(reps)), dims=("u",),
                        kind="continuous", bin_edges=tuple(float(e) for e in edges),
                        low=tuple(float(x) for x in low), high=tuple(float(x) for x in high))
    d = log["obs"].shape[1]
    info = DatasetInfo(features=tuple(Feature(f"o{j}") for j in range(d)), action_table=table, gamma=gamma, name=name)
    term = log["terminated"].astype(bool)
    return TransitionDataset.from_arrays(
        info, episode_id=np.char.zfill(log["episode"].astype(int).astype(str), 6), step=log["step"], obs=log["obs"],
        action=idx, cost=-log["reward"], next_obs=log["next_obs"], terminated=term,
        truncated=log["truncated"].astype(bool) & ~term, extra={ACTION_VALUE_PREFIX + "u": u[:, 0]})


def run(env_id: str, n: int, seed: int, n_episodes: int, arms: dict[str, dict]) -> list[dict]:
    import gymnasium

    from offline_adp.envs.gym import record_random_log

    space = gymnasium.make(env_id).action_space
    log = record_random_log(env_id, n, seed=seed, **PROBLEMS[env_id])
    ds = command_dataset(log, np.asarray(space.low, np.float64), np.asarray(space.high, np.float64), 11, env_id)
    out = []
    for arm, params in arms.items():
        est = FittedQIteration(random_state=seed, **params)
        c0 = time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DivergenceWarning)
            est.fit(ds)
        cpu = time.process_time() - c0
        pol = est.policy_
        if est.commands_ == "continuous":
            def command(x, t, pol=pol):
                return pol.commands(x, t)
        else:
            values = ds.info.action_table.values

            def command(x, t, pol=pol, values=values):
                return values[pol.act_index(x, t)]
        r, smooth = returns(env_id, command, n_episodes)
        row = {"problem": env_id, "seed": seed, "arm": arm, "score": float(r.mean()),
               "score_se": float(r.std() / np.sqrt(len(r))),
               "cpu_s": cpu, "smoothness": smooth, "iterations": len(est.history_), "verdict": est.verdict_}
        print(json.dumps(row), flush=True)
        out.append(row)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problems", nargs="+", default=list(PROBLEMS))
    ap.add_argument("--transitions", type=int, default=50_000)
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--n-candidates", type=int, default=8)
    ap.add_argument("--n-representatives", type=int, default=16,
                    help="the continuous arm's representative commands of the log (0: the neighbours' alone)")
    ap.add_argument("--json")
    a = ap.parse_args()
    arms = {"continuous": {"commands": "continuous", "n_candidates": a.n_candidates,
                           "n_representatives": a.n_representatives}, "binned_11": {"commands": "binned"}}
    rows = [r for p in a.problems for s in a.seeds for r in run(p, a.transitions, s, a.episodes, arms)]
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
