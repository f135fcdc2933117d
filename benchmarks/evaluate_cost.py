"""CPU of ``evaluate`` against its fit's (issue #42: at most 3x), per stage.

Two cases, each in a fresh process, CPU seconds (user + sys of every thread,
``time.process_time``; never wall time, which other jobs on the machine move):

* ``demo``: ``pipelines/driving.toml`` (the MCAP driving logs, 9,432 transitions; fit,
  then evaluate with the path_tracking simulator, 300 episodes, 200 bootstrap replicates);
* ``50k``: ``simulate("path_tracking", 225, 225)`` (~50,000 transitions), fitted with the
  defaults, evaluated with the simulator and with ``simulator="none"``.

The evaluate stages are the progress lines ``evaluate`` prints (the CPU between a line
and the next). ``--base DIR`` runs the same cases against another checkout (e.g. a
worktree of the base commit, ``git worktree add /tmp/base <commit>``) and prints the two
side by side::

    python benchmarks/evaluate_cost.py [--case demo|50k|all] [--base DIR] [--repeat N] [--profile DIR]

With ``--repeat N`` each arm runs N times (alternating with the other arm) and every number
is the smallest of its N readings: other jobs on the machine only ever add CPU time (shared
caches, a busy sibling hyperthread), so the minimum is the least disturbed reading.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _stages(marks: list[tuple[str, float]], end: float) -> dict[str, float]:
    """CPU between each progress line and the next, summed by the line's stage name. A
    counter line (``"model rollouts: step 50/200, ETA 3 s"``) belongs to the stage it
    counts when their names share a start; else (``"FQE bootstrap 50/200"`` after ``"fitted
    Q evaluation"``) it starts a stage of its own name."""
    out: dict[str, float] = {}
    key = None
    for (name, t), (_, t_next) in zip(marks, [*marks[1:], ("end", end)], strict=True):
        counter = re.match(r"(.*?):? (step |fold )?\d+/\d+\b", name)
        desc = counter.group(1) if counter else name.split(" (")[0]
        if not (counter and key is not None and (key.startswith(desc) or desc.startswith(key))):
            key = desc
        out[key] = out.get(key, 0.0) + t_next - t
    return out


def _demo(tmp: Path) -> dict[str, object]:
    from offline_adp.pipeline import run_pipeline

    marks: list[tuple[str, float]] = []
    run = run_pipeline(ROOT / "pipelines" / "driving.toml", runs_root=tmp / "runs",
                       say=lambda s: marks.append((s, time.process_time())))
    end = time.process_time()
    top: dict[str, float] = {}
    ev: list[tuple[str, float]] = []
    stage, t_stage = None, 0.0
    for s, t in [*marks, ("[end] running", end)]:
        if s.endswith("] running"):
            if stage is not None:
                top[stage] = t - t_stage
            stage, t_stage = s[1:].split("]")[0], t
        elif s.startswith("[evaluate] "):
            ev.append((s[len("[evaluate] "):], t))
    ev_stages = _stages([("setup", _first(marks, "[evaluate] running")), *ev], _first(marks, "[report] running"))
    m = json.loads((run / "metrics.json").read_text())
    return {"fit": top.get("fit"), "evaluate": top.get("evaluate"), "stages": {"evaluate": ev_stages},
            "numbers": _numbers(m)}


def _first(marks: list[tuple[str, float]], line: str) -> float:
    return next(t for s, t in marks if s == line)


def _numbers(m: dict) -> dict[str, object]:
    """A few printed numbers, to see that before and after estimate the same."""
    ope = m.get("ope", {})
    out = {k: [r.get("estimate"), *(r.get("interval") or [None, None])] for k, r in ope.items()}
    if "rollout" in m:
        out["rollout"] = m["rollout"]["policy"]["mean_discounted_cost"]
    return out


def _case_50k(tmp: Path) -> dict[str, object]:
    from offline_adp.evaluation.run import evaluate_run
    from offline_adp.runs import fit_run
    from offline_adp.simulate import simulate

    ds = simulate("path_tracking", 225, 225, seed=0)
    ds.save(tmp / "ds")
    t0 = time.process_time()
    fit_run(tmp / "ds", tmp / "run")
    out: dict[str, object] = {"transitions": len(ds), "fit": time.process_time() - t0, "stages": {}, "numbers": {}}
    for sim in ("path_tracking", "none"):
        marks: list[tuple[str, float]] = []
        t0 = time.process_time()
        m = evaluate_run(tmp / "run", simulator=sim, progress=lambda s,
                         marks=marks: marks.append((s, time.process_time())))
        end = time.process_time()
        out[f"evaluate[{sim}]"] = end - t0
        out["stages"][sim] = _stages([("setup", t0), *marks], end)
        out["numbers"][sim] = _numbers(m)
    return out


def run_case(case: str, profile: str | None) -> dict[str, object]:
    fn = {"demo": _demo, "50k": _case_50k}[case]
    with tempfile.TemporaryDirectory() as tmp:
        if profile is not None:
            Path(profile).mkdir(parents=True, exist_ok=True)
        if profile is None:
            return fn(Path(tmp))
        import cProfile

        pr = cProfile.Profile(time.process_time)
        res = pr.runcall(fn, Path(tmp))
        pr.dump_stats(str(Path(profile) / f"{case}.prof"))
        return res


def _in_checkout(checkout: Path, case: str, profile: str | None) -> dict[str, object]:
    """The case run by this file's code in a fresh process importing ``checkout``'s package."""
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    cmd = [sys.executable, str(Path(__file__).resolve()), "--one", case, "--root", str(checkout)]
    if profile:
        cmd += ["--profile", profile]
    done = subprocess.run(cmd, env=env, cwd=checkout, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _print(case: str, arms: dict[str, dict]) -> None:
    names = list(arms)
    print(f"\n== {case}: CPU seconds (user + sys) " + " | ".join(names))
    evals = [k for k in arms[names[0]] if k.startswith("evaluate")]
    for key in ["fit", *evals]:
        cells = []
        for n in names:
            r = arms[n]
            ratio = f" ({r[key] / r['fit']:.1f}x fit)" if key != "fit" else ""
            cells.append(f"{r[key]:8.1f}{ratio:13s}")
        print(f"  {key:36s}" + " | ".join(cells))
    for which in arms[names[0]]["stages"]:
        print(f"  -- evaluate stages ({which})")
        keys = list(dict.fromkeys(k for n in names for k in arms[n]["stages"][which]))
        for k in keys:
            print(f"     {k[:33]:33s}"
                  + " | ".join(f"{arms[n]['stages'][which].get(k, 0.0):8.1f}{'':13s}" for n in names))
    for n in names[1:]:
        same = arms[n]["numbers"] == arms[names[0]]["numbers"]
        print(f"  estimates {names[0]} vs {n}: {'identical' if same else 'DIFFER'}")
        if not same:
            print(json.dumps({k: arms[k]["numbers"] for k in (names[0], n)}, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", choices=["demo", "50k", "all"], default="all")
    ap.add_argument("--base", type=Path, default=None, help="a checkout of the code to compare with (before)")
    ap.add_argument("--profile", default=None, help="write cProfile stats (CPU timer) into this directory")
    ap.add_argument("--repeat", type=int, default=1,
                    help="runs of each arm; the smallest reading of each number is kept")
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--root", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:  # a child: one case, its result as the last line of stdout
        global ROOT
        ROOT = Path(args.root)
        print(json.dumps(run_case(args.one, args.profile)))
        return
    for case in (["demo", "50k"] if args.case == "all" else [args.case]):
        runs: dict[str, list[dict]] = {}
        for _ in range(max(1, args.repeat)):
            if args.base is not None:
                prof = None if args.profile is None else str(Path(args.profile) / "before")
                runs.setdefault("before", []).append(_in_checkout(args.base.resolve(), case, prof))
            name = "after" if args.base is not None else "this"
            prof = None if args.profile is None else str(Path(args.profile) / name)
            runs.setdefault(name, []).append(_in_checkout(ROOT, case, prof))
        _print(case, {name: _smallest(rs) for name, rs in runs.items()})


def _smallest(readings: list[dict]) -> dict:
    """Every CPU reading at its smallest over the runs (the estimates are the same in each)."""
    out = dict(readings[0])
    for key, value in out.items():
        if isinstance(value, float):
            out[key] = min(r[key] for r in readings)
    out["stages"] = {which: {k: min(r["stages"][which].get(k, 0.0) for r in readings) for k in stages}
                     for which, stages in readings[0]["stages"].items()}
    return out

if __name__ == "__main__":
    main()
