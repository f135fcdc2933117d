"""Our continuous-command FQI next to d3rlpy's IQL and TD3+BC on the same logs (issue #41).

The log is :mod:`benchmarks.continuous_commands`'s (random play, each torque held 1-8 steps,
``record_random_log``); both sides are scored by the same code (mean return over episodes
seeded 10_000 + i, command smoothness ``mean |u_t - u_{t-1}|``), and CPU seconds are the
fitting process's own (``time.process_time`` here; the d3rlpy worker's user + system time
for its fit alone, read in the worker).

d3rlpy runs in its own virtual environment (never the project's), as a subprocess of this
file (``--worker ALGO IN.npz OUT.json``): it builds an ``MDPDataset`` from the arrays (rewards
as logged, ``timeouts`` for time-limit ends), fits ``IQLConfig`` / ``TD3PlusBCConfig`` with
d3rlpy's defaults on the CPU (observations standardised, commands scaled to [-1, 1]) for a
fixed number of gradient steps, and rolls its policy out. Nothing of d3rlpy is copied into
this repository. Install it outside the repository:

    python3.11 -m venv /work/d3/venv
    /work/d3/venv/bin/pip install torch==2.13.0     # the CPU build on this machine's disk
    /work/d3/venv/bin/pip install d3rlpy gymnasium

    nice -n 10 python benchmarks/continuous_vs_d3rlpy.py [--problem Pendulum-v1] [--transitions 50000] \
        [--steps 100000] [--episodes 100] [--d3rlpy-python /work/d3/venv/bin/python] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

DEFAULT_D3 = "/work/d3/venv/bin/python"


# ----------------------------------------------------------------------------- the d3rlpy side (its venv)
def worker(algo: str, src: str, out: str, steps: int, episodes: int) -> None:
    """Runs under d3rlpy's interpreter: fit ``algo`` on the arrays in ``src`` and score it."""
    import d3rlpy
    import torch

    torch.set_num_threads(1)  # one core: CPU seconds comparable with ours, no spinning on a shared machine
    z = np.load(src)
    env_id = str(z["env_id"])
    low, high = z["low"].astype(np.float32), z["high"].astype(np.float32)
    ds = d3rlpy.dataset.MDPDataset(observations=z["obs"].astype(np.float32), actions=z["action"].astype(np.float32),
                                   rewards=z["reward"].astype(np.float32), terminals=z["terminated"].astype(np.float32),
                                   timeouts=z["timeout"].astype(np.float32))
    kw = {"observation_scaler": d3rlpy.preprocessing.StandardObservationScaler(),
          "action_scaler": d3rlpy.preprocessing.MinMaxActionScaler(minimum=low, maximum=high)}
    cfg = {"iql": d3rlpy.algos.IQLConfig, "td3bc": d3rlpy.algos.TD3PlusBCConfig}[algo](**kw)
    model = cfg.create(device="cpu:0")
    d3rlpy.seed(0)
    c0 = os.times()
    model.fit(ds, n_steps=steps, n_steps_per_epoch=min(steps, 10_000), show_progress=False,
              logger_adapter=d3rlpy.logging.NoopAdapterFactory(), save_interval=10**9)
    c1 = os.times()
    cpu = (c1.user - c0.user) + (c1.system - c0.system)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from gym_returns import returns

    ret, smooth = returns(env_id, lambda x, t: model.predict(np.asarray(x, np.float32)), episodes, low, high)
    with open(out, "w") as f:
        json.dump({"score": float(ret.mean()), "score_se": float(ret.std() / np.sqrt(episodes)), "cpu_s": cpu,
                   "smoothness": smooth,
                   "d3rlpy": d3rlpy.__version__, "gradient_steps": steps}, f)


# ----------------------------------------------------------------------------- our side and the driver
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", default="Pendulum-v1")
    ap.add_argument("--transitions", type=int, default=50_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=100_000, help="d3rlpy gradient steps")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--algos", nargs="+", default=["ours", "iql", "td3bc"])
    ap.add_argument("--d3rlpy-python", default=DEFAULT_D3)
    ap.add_argument("--json")
    ap.add_argument("--worker", nargs=3, metavar=("ALGO", "IN", "OUT"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        worker(a.worker[0], a.worker[1], a.worker[2], a.steps, a.episodes)
        return
    import gymnasium

    sys.path.insert(0, os.path.dirname(__file__))
    from continuous_commands import PROBLEMS, run

    from offline_adp.envs.gym import record_random_log

    rows = []
    if "ours" in a.algos:
        rows += run(a.problem, a.transitions, a.seed, a.episodes, {"ours_continuous": {"commands": "continuous"}})
    d3 = [x for x in a.algos if x != "ours"]
    if d3:
        space = gymnasium.make(a.problem).action_space
        log = record_random_log(a.problem, a.transitions, seed=a.seed, **PROBLEMS[a.problem])
        term = log["terminated"].astype(bool)
        with tempfile.TemporaryDirectory() as tmp:
            src = os.path.join(tmp, "log.npz")
            np.savez(src, env_id=np.array(a.problem), obs=log["obs"],
                     action=np.asarray(log["action"], np.float64).reshape(len(term), -1),
                     reward=log["reward"], terminated=term, timeout=log["truncated"].astype(bool) & ~term,
                     low=np.asarray(space.low, np.float64), high=np.asarray(space.high, np.float64))
            for algo in d3:
                out = os.path.join(tmp, f"{algo}.json")
                t0 = time.perf_counter()
                proc = subprocess.run([a.d3rlpy_python, __file__, "--worker", algo, src, out, "--steps", str(a.steps),
                                       "--episodes", str(a.episodes)], capture_output=True, text=True)
                if proc.returncode != 0:
                    print(f"d3rlpy {algo} failed:\n{proc.stderr[-3000:]}", file=sys.stderr)
                    continue
                with open(out) as f:
                    row = {"problem": a.problem, "seed": a.seed, "arm": f"d3rlpy_{algo}", **json.load(f),
                           "wall_s": time.perf_counter() - t0}
                print(json.dumps(row), flush=True)
                rows.append(row)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
