"""Benchmark: CPU cost of the model rollouts' support check in many dimensions.

A synthetic log of a stable linear system in ``d`` dimensions (``x' = 0.9 x + 0.1 B a +
noise``, 3 actions, uniformly random; ``--rows`` transitions in 200-step episodes).
:class:`offline_adp.evaluation.model_rollouts.LoggedDynamics` is fitted once; then the
rollouts of two policies (the logging one, which stays, and one that pushes one way and
drifts out) are timed with

- ``exact``: an exact nearest-neighbour search (the check before 2026-11-26 was exact too,
  and searched for every particle at every step, dead or already out; here both arms
  search only the particles still in the data and alive, so the gain of that is not timed);
- ``fast``: :meth:`LoggedDynamics.in_data` (approximate search, exact only where it cannot
  tell) on the particles still in the data and alive.

Both must give the same exit mass and bounds (the check is exact either way). CPU seconds
of the process (``time.process_time``), side by side in one run.

    python benchmarks/model_rollouts_dims.py [--dims 4 17] [--rows 50000] [--particles 1000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def synthetic_log(d: int, rows: int, seed: int = 0):  # type: ignore[no-untyped-def]
    from offline_adp.data.dataset import TransitionDataset
    from offline_adp.data.info import ActionTable, DatasetInfo, Feature

    H = 200
    n_ep = max(1, rows // H)
    rng = np.random.default_rng(seed)
    B = rng.standard_normal(d)
    x = rng.standard_normal((n_ep, d))
    obs, nxt, act = [], [], []
    for _ in range(H):
        a = rng.integers(0, 3, n_ep)
        y = 0.9 * x + 0.1 * np.outer(a - 1.0, B) + 0.3 * rng.standard_normal((n_ep, d))
        obs.append(x)
        nxt.append(y)
        act.append(a)
        x = y
    obs_a, nxt_a = np.stack(obs, 1).reshape(-1, d), np.stack(nxt, 1).reshape(-1, d)
    step = np.tile(np.arange(H), n_ep)
    ep = np.repeat(np.arange(n_ep), H)
    info = DatasetInfo(features=tuple(Feature(f"x{j}") for j in range(d)), gamma=0.95, horizon=H,
                       action_table=ActionTable.from_values([-1.0, 0.0, 1.0]))
    return TransitionDataset.from_arrays(
        info, episode_id=np.char.zfill(ep.astype(str), 6), step=step, obs=obs_a, action=np.stack(act, 1).ravel(),
        cost=np.linalg.norm(nxt_a, axis=1), next_obs=nxt_a, terminated=np.zeros(len(step), bool),
        truncated=step == H - 1)


def main(argv: list[str] | None = None) -> int:
    from offline_adp.data.dataset import TransitionDataset  # noqa: F401  (import cost outside the timings)
    from offline_adp.evaluation.model_rollouts import (
        LoggedDynamics,
        model_rollout_value,
        remainder_ranges,
    )
    from offline_adp.policies import FunctionPolicy, UniformPolicy

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dims", type=int, nargs="+", default=[4, 17])
    ap.add_argument("--rows", type=int, default=50_000)
    ap.add_argument("--particles", type=int, default=1000)
    args = ap.parse_args(argv)
    print("| d | rows | policy | exit mass | exact CPU s | fast CPU s | same result |")
    print("|---|---|---|---|---|---|---|")
    for d in args.dims:
        ds = synthetic_log(d, args.rows)
        a = ds.arrays()
        model = LoggedDynamics(random_state=0).fit(ds, a)
        ranges = remainder_ranges(a.cost, a.terminated, 0.95, 200)
        fast_check = model.in_data

        def exact(states, radius=None, m=model):  # type: ignore[no-untyped-def]
            r = m.radius_ if radius is None else radius
            dist, _ = m.tree_.query(np.asarray(states) / m.sd_)
            return dist <= r

        push = FunctionPolicy(lambda x, t=0: np.full(len(x), 2, np.int64), 3, name="push")
        for name, pol in (("logging", UniformPolicy(3)), ("push", push)):
            out = {}
            for how, check in (("exact", exact), ("fast", fast_check)):
                model.in_data = check  # type: ignore[method-assign]
                c0 = time.process_time()
                out[how] = (model_rollout_value(model, pol, 200, 0.95, ranges, n=args.particles, seed=1),
                            time.process_time() - c0)
            (e, te), (f, tf) = out["exact"], out["fast"]
            same = all(e[k] == f[k] for k in ("exit_mass", "lower", "upper", "estimate"))
            print(f"| {d} | {len(ds)} | {name} | {f['exit_mass']:.3f} | {te:.1f} | {tf:.1f} | {same} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
