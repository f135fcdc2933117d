"""``n_iterations="auto"`` through the CLI against a fixed 50-iteration CLI fit (issue #44).

Our own collector (:func:`offline_adp.envs.gym.record_random_log`: uniformly random actions,
each held 1-8 steps) writes 50,000 transitions per task as a dataset directory (gamma 0.99;
MountainCar episodes of up to 2,000 steps, else its log holds no goal; Pendulum's torque in
11 equal-width bins, each the mean logged torque in it, as a discrete action table, so that
the CLI's defaults fit over the bins). Every arm is an ``offline-adp fit`` of the same
dataset in its own process, with a config file holding only the arm's parameters (``{}``:
the CLI defaults); its CPU is the whole process's (user + sys, ``os.wait4``: imports,
reading the data, the fit, writing the model; what a user pays) and the fit's own
(``fit_cpu_seconds`` in run.json). Score: mean undiscounted return of the saved greedy
policy over episodes seeded 10_000 + i at gymnasium's time limit (20 episodes; Pendulum
100, as ``benchmarks/continuous_commands.py``), with its standard error.

The arms of one task run one after the other in the same session, ``--rounds`` times in
turn (A B C, A B C, ...), so that load drifts reach every arm alike (``--once``: arms run in
the first round only). At the end: a Markdown table of the means and the CPU ratios to
``--reference`` (default ``fixed50``).

    nice -n 10 python benchmarks/fqi_auto_iterations.py [--tasks CartPole-v1 ...] \
        [--arm fixed50='{"n_iterations": 50}' --arm default='{}' ...] [--rounds 1] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from gym_returns import returns  # noqa: E402

TASKS = {"CartPole-v1": {}, "Acrobot-v1": {}, "MountainCar-v0": {"max_episode_steps": 2000}, "Pendulum-v1": {}}
EPISODES = {"Pendulum-v1": 100}  # others: 20
ARMS = {"fixed50": {"n_iterations": 50}, "default": {}}
PENDULUM_BINS = 11
#: a tiny frozen fit: every compiled kernel a fit uses, compiled or loaded from numba's disk cache
WARM_UP = ("from offline_adp.algorithms.fqi import FittedQIteration; from offline_adp.simulate import simulate; "
           "FittedQIteration(gamma=0.9, n_iterations=3, regressor_params={'n_estimators': 3}).fit("
           "simulate('car_on_hill', 5, 0, seed=0))")


def collect(env_id: str, n: int, seed: int, path: Path) -> Path:
    """Write the task's random-play log as a dataset directory at ``path`` (once)."""
    if (path / "meta" / "info.json").exists():
        return path
    from offline_adp.data.dataset import TransitionDataset
    from offline_adp.data.info import ActionTable, DatasetInfo, Feature
    from offline_adp.envs.gym import record_random_log

    log = record_random_log(env_id, n, seed=seed, **TASKS[env_id])
    a = np.asarray(log["action"])
    if np.issubdtype(a.dtype, np.integer):
        action, values = a.astype(int), np.arange(int(a.max()) + 1, dtype=float)
    else:  # one torque component: equal-width bins over the action box
        import gymnasium

        space = gymnasium.make(env_id).action_space
        edges = np.linspace(float(space.low[0]), float(space.high[0]), PENDULUM_BINS + 1)
        u = a.reshape(len(a), -1)[:, 0].astype(np.float64)
        action = np.clip(np.searchsorted(edges, u, side="right") - 1, 0, PENDULUM_BINS - 1)
        values = np.array([u[action == b].mean() if (action == b).any() else (edges[b] + edges[b + 1]) / 2
                           for b in range(PENDULUM_BINS)])
    d = log["obs"].shape[1]
    info = DatasetInfo(features=tuple(Feature(f"o{j}") for j in range(d)), action_table=ActionTable.from_values(values),
                       gamma=0.99, name=env_id)
    term = log["terminated"].astype(bool)
    ds = TransitionDataset.from_arrays(
        info, episode_id=np.char.zfill(log["episode"].astype(int).astype(str), 6), step=log["step"], obs=log["obs"],
        action=action, cost=-log["reward"], next_obs=log["next_obs"], terminated=term,
        truncated=log["truncated"].astype(bool) & ~term)
    ds.save(path, overwrite=True)
    return path


def cli_fit(dataset: Path, run: Path, params: dict, source: str | None = None) -> dict:
    """``offline-adp fit`` in a child process (``source``: the source tree it imports
    ``offline_adp`` from, default this one); its CPU (user + sys) and run.json."""
    import shutil

    if run.exists():
        shutil.rmtree(run)
    run.parent.mkdir(parents=True, exist_ok=True)
    cfg = run.parent / (run.name + ".toml")
    lines = ["[fqi]"] + [f"{k} = {json.dumps(v)}" for k, v in params.items() if not isinstance(v, dict)]
    for k, v in params.items():  # sub-tables ([fqi.regressor_params])
        if isinstance(v, dict):
            lines += [f"[fqi.{k}]"] + [f"{kk} = {json.dumps(vv)}" for kk, vv in v.items()]
    cfg.write_text("\n".join(lines) + "\n")
    cmd = [sys.executable, "-m", "offline_adp", "-q", "fit", str(dataset), "--algorithm", "fqi", "--config", str(cfg),
           "--out", str(run)]
    # not -m's cwd: the source
    proc = subprocess.Popen(cmd, env=_env(source), cwd=run.parent, stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(cmd)} failed")
    meta = json.loads((run / "run.json").read_text())
    return {"process_cpu_s": usage.ru_utime + usage.ru_stime, **meta}


def _env(source: str | None) -> dict[str, str]:
    """The environment of a child importing ``offline_adp`` from ``source`` (default: this checkout)."""
    env = os.environ.copy()
    env["PYTHONPATH"] = os.pathsep.join([str(Path(source or Path(__file__).resolve().parent.parent).resolve()),
                                         env.get("PYTHONPATH", "")])
    return env


def score(env_id: str, run: Path, dataset: Path) -> tuple[float, float]:
    from offline_adp.deploy import load_run_policy

    pol = load_run_policy(run, dataset)
    values = np.asarray(pol.signature.action_table.values, np.float64)

    def command(x: np.ndarray, t: int) -> np.ndarray:
        return values[pol.act_index(x, t)]

    r, _ = returns(env_id, command, EPISODES.get(env_id, 20))
    return float(r.mean()), float(r.std(ddof=1) / np.sqrt(len(r)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", nargs="+", default=list(TASKS))
    ap.add_argument("--arm", action="append", default=[],
                    help="NAME[@SOURCE_TREE]=JSON parameters of [fqi] (repeatable; SOURCE_TREE: another checkout's "
                    "directory holding offline_adp, e.g. the code before a change)")
    ap.add_argument("--seed", type=int, default=0, help="data seed (the learner's random_state stays the default)")
    ap.add_argument("--transitions", type=int, default=50_000)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--once", nargs="*", default=[], help="arms run in the first round only (e.g. a slow old default)")
    ap.add_argument("--reference", default="fixed50", help="the arm the CPU ratios divide by")
    ap.add_argument("--out", default=None, help="where datasets and runs go (default: a temporary directory)")
    ap.add_argument("--json", default=None, help="append every fit's record here (JSON lines)")
    args = ap.parse_args()
    arms = {k: (None, v) for k, v in ARMS.items()}
    if args.arm:
        arms = {}
        for a in args.arm:
            name, params = a.split("=", 1)
            name, _, source = name.partition("@")
            parsed = json.loads(params)
            nulls = [k for k, v in parsed.items() if v is None or (isinstance(v, dict) and None in v.values())]
            if nulls:  # TOML has no null: say so before any fit runs
                ap.error(f"--arm {name}: {', '.join(nulls)} holds null, which a TOML config cannot express")
            arms[name] = (source or None, parsed)
    root = (Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="fqi_auto_"))).resolve()
    root.mkdir(parents=True, exist_ok=True)
    for source in {s for s, _ in arms.values()}:  # each tree's compiled kernels (cached on disk) are nobody's fit
        subprocess.run([sys.executable, "-c", WARM_UP], env=_env(source), cwd=root, check=True)
    records = []
    for env in args.tasks:
        ds = collect(env, args.transitions, args.seed, root / "data" / f"{env}-s{args.seed}")
        for rnd in range(args.rounds):
            for arm, (source, params) in arms.items():
                if rnd and arm in args.once:
                    continue
                run = root / "runs" / f"{env}-s{args.seed}-{arm}-r{rnd}"
                fit = cli_fit(ds, run, params, source)
                m, se = score(env, run, ds)
                rec = {"task": env, "arm": arm, "round": rnd, "params": params, "source": source, "score": round(m, 2),
                       "se": round(se, 2),
                       "process_cpu_s": round(fit["process_cpu_s"], 2), "fit_cpu_s": round(fit["fit_cpu_seconds"], 2),
                       "iterations": fit.get("iterations"), "builds": len(fit.get("structure_builds") or []),
                       "inner_backups": _inner_backups(run),
                       "verdict": fit.get("verdict")}
                print(json.dumps(rec), flush=True)
                records.append(rec)
                if args.json:
                    with open(args.json, "a") as fh:
                        fh.write(json.dumps(rec) + "\n")
    print(table(records, args.reference))


def _inner_backups(run: Path) -> int:
    """The settling solver's backups of a run (its history's ``inner_backups``; 0 before it existed)."""
    import pandas as pd

    h = pd.read_csv(run / "model" / "history.csv")
    return int(h["inner_backups"].fillna(0).sum()) if "inner_backups" in h else 0


def table(records: list[dict], reference: str) -> str:
    """Per task and arm: the score (mean over rounds), the CPU seconds (process, fit: means)
    and their ratios to the reference arm's means, as a Markdown table."""
    lines = ["| task | arm | score | process CPU-s | fit CPU-s | ratio to " + reference
             + " (process / fit) | iterations |",
             "|---|---|---|---|---|---|---|"]
    for env in dict.fromkeys(r["task"] for r in records):
        ref = [r for r in records if r["task"] == env and r["arm"] == reference]
        for arm in dict.fromkeys(r["arm"] for r in records if r["task"] == env):
            rs = [r for r in records if r["task"] == env and r["arm"] == arm]
            p, f = float(np.mean([r["process_cpu_s"] for r in rs])), float(np.mean([r["fit_cpu_s"] for r in rs]))
            ratio = (f"{p / np.mean([r['process_cpu_s'] for r in ref]):.2f} / "
                     f"{f / np.mean([r['fit_cpu_s'] for r in ref]):.2f}"
                     if ref else "-")
            scores = " / ".join(f"{r['score']:g}" for r in rs)
            lines.append(f"| {env} | {arm} | {np.mean([r['score'] for r in rs]):.1f} ({scores}) | {p:.1f} | {f:.1f} | "
                         f"{ratio} | {'/'.join(str(r['iterations']) for r in rs)} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
