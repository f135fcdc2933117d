"""Where two car-on-the-hill policies part, and whether the logs saw it (issue #44).

For each data seed (``simulate("car_on_hill", 0, 1000, seed=s, horizon=100)``, as in
``fqi_vs_mushroom.py``) this fits the library's default FQI (the joint encoding), the
frozen mode with per-action structures, and optionally mushroom-rl's FQI (its own venv,
through ``fqi_vs_mushroom.run_mushroom``). For every pair (the default against each other)
it follows both greedy policies from each of the 289 score states, in the true simulator,
until their actions first differ, and reads the logs around that state: how many logged
rows of each action lie within ``--radius`` (in units of the state ranges, position over
[-1, 1] and speed over [-3, 3]).

The 289-state score difference between the two is then split exactly (a sum over start
states) into the part decided at states where the logs hold rows of both actions nearby
("on the data") and the part decided where they hold none of one action or the other ("off
the data": the policies there extrapolate). States where the two never differ add nothing.

    python benchmarks/car_on_hill_divergence.py --data-seeds 0 1 2 3 4 [--no-mushroom] [--json out.json]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):  # one thread, before numpy loads
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

GAMMA = 0.95
SCALE = np.array([2.0, 6.0])  # the state ranges: position [-1, 1], speed [-3, 3]


def follow(policy_a, policy_b, starts: np.ndarray, max_steps: int = 400) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Discounted returns of ``policy_a`` from ``starts`` (true simulator), and the first state
    on its path where ``policy_b`` would act otherwise (NaN where it never does)."""
    from offline_adp.envs.car_on_hill import CarOnHill

    prob = CarOnHill(horizon=None)
    x = starts.astype(np.float64).copy()
    alive = np.ones(len(x), bool)
    ret = np.zeros(len(x))
    part = np.full_like(x, np.nan)
    disc = 1.0
    for _ in range(max_steps):
        idx = np.flatnonzero(alive)
        if not len(idx):
            break
        a = policy_a.actions(x[idx], 0)
        b = policy_b.actions(x[idx], 0)
        first = (a != b) & np.isnan(part[idx, 0])
        part[idx[first]] = x[idx[first]]
        r = prob.step_seeded(x[idx], a)
        ret[idx] += disc * (-r.costs)
        x[idx] = r.next_states
        alive[idx[r.terminated]] = False
        disc *= GAMMA
    return ret, part, alive


def support(obs: np.ndarray, action: np.ndarray, at: np.ndarray, radius: float) -> np.ndarray:
    """Logged rows of each action within ``radius`` (scaled state units) of each state: (n, 2)."""
    from scipy.spatial import cKDTree

    out = np.zeros((len(at), 2), np.int64)
    ok = ~np.isnan(at[:, 0])
    for k in (0, 1):
        tree = cKDTree(obs[action == k] / SCALE)
        out[ok, k] = [len(v) for v in tree.query_ball_point(at[ok] / SCALE, radius)]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--learner-seed", type=int, default=0)
    ap.add_argument("--radius", type=float, nargs="+", default=[0.025, 0.05], help="scaled state units (default "
                    "0.025 and 0.05: 0.05 and 0.1 in position, 0.15 and 0.3 in speed)")
    ap.add_argument("--mushroom-python", default="/work/mr/venv/bin/python")
    ap.add_argument("--no-mushroom", action="store_true")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from fqi_vs_mushroom import mushroom_available, run_mushroom

    from offline_adp.algorithms.fqi import FittedQIteration
    from offline_adp.envs.car_on_hill import score_grid
    from offline_adp.policies import GreedyPolicy
    from offline_adp.simulate import simulate

    use_mr = not args.no_mushroom and mushroom_available(args.mushroom_python) is None
    grid = score_grid()
    records = []
    for s in args.data_seeds:
        ds = simulate("car_on_hill", 0, 1000, seed=s, horizon=100)
        a = ds.arrays()
        act = a.action.astype(np.int64)
        wins = int((a.cost < 0).sum())
        print(f"\ndata seed {s}: {len(ds)} rows, {wins} winning transitions, "
              f"{int((a.cost > 0).sum())} losing", flush=True)
        pols = {}
        for name, kw in (("default", {}), ("per_action", {"mode": "frozen", "action_encoding": "per_action"})):
            f = FittedQIteration(gamma=GAMMA, random_state=args.learner_seed,
                                 regressor_params={"n_estimators": 50, "n_jobs": 1}, **kw).fit(ds)
            pols[name] = f.policy_
        if use_mr:
            arrays = {"obs": a.obs, "action": act, "cost": a.cost, "next_obs": a.next_obs,
                      "terminated": a.terminated.astype(bool), "n_actions": ds.info.n_actions}
            res = run_mushroom(args.mushroom_python, arrays, GAMMA, 50, 50, args.learner_seed)
            if res is not None:
                pols["mushroom-rl"] = GreedyPolicy(res["q"])
        ret_d, _, _ = follow(pols["default"], pols["default"], grid)
        for other in [k for k in pols if k != "default"]:
            ret_o, part_o, _ = follow(pols[other], pols["default"], grid)
            _, part_d, _ = follow(pols["default"], pols[other], grid)
            # both paths part at the same state (the same start, the same actions up to there)
            parted = ~np.isnan(part_d[:, 0])
            diff = (ret_d - ret_o) / len(grid)
            print(f"  default {ret_d.mean():.4f} vs {other} {ret_o.mean():.4f}: difference {diff.sum():+.4f}; "
                  f"{parted.sum()} of 289 paths part", flush=True)
            for radius in args.radius:
                sup = support(a.obs, act, part_d, radius)
                on = parted & (sup.min(axis=1) > 0)
                off = parted & ~on
                rec = {"data_seed": s, "other": other, "radius": radius, "score_default": float(ret_d.mean()),
                       "score_other": float(ret_o.mean()), "difference": float(diff.sum()),
                       "parted": int(parted.sum()), "parted_on_data": int(on.sum()),
                       "parted_off_data": int(off.sum()), "difference_on_data": float(diff[on].sum()),
                       "difference_off_data": float(diff[off].sum()), "winning_transitions": wins,
                       "same_path_check": bool(np.allclose(part_o[parted], part_d[parted]))}
                records.append(rec)
                print(f"    radius {radius} (position +-{radius * 2:.2f}, speed +-{radius * 6:.2f}): "
                      f"{rec['difference_on_data']:+.4f} decided on the data ({on.sum()} start states), "
                      f"{rec['difference_off_data']:+.4f} off it ({off.sum()})", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(records, indent=1))


if __name__ == "__main__":
    main()
