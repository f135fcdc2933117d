"""By hand: ``evaluate`` of a fitted policy on ~1M logged transitions on a Dask LocalCluster
(issue #44: no process above 4 GiB), with every process's peak RSS and wall / CPU per stage.

Data: random-action car-on-the-hill episodes of up to 100 steps (``benchmarks/dask_10m.py``'s
generator, whole episodes, about ``--rows`` transitions), saved once to ``--data``; a run
directory ``--run`` fitted once in this process with
``FittedQIteration(gamma=0.95, n_iterations=--fit-iterations, regressor_params={"n_jobs": 1})``
(the default frozen mode; the fit is not measured). Then
``evaluate_run(run, dataset=data, task_map=DaskTaskMap(client), **settings)`` on
``EngineConfig(kind="dask", n_workers=--workers, threads_per_worker=1, memory_limit=--memory-limit)``
(``--workers 0``: the local evaluation, no cluster). The car-on-the-hill simulator is used
(the dataset names its problem): rollouts of the policy and of the demonstrator.

Measured: wall and CPU (this process and all its descendants: scheduler, nannies, workers;
``dask_scale.tree_cpu``) between the evaluation's progress lines, summed by stage; the peak
RSS of every process, sampled every 0.2 s with psutil (so a worker restarted by its nanny
still shows its peak) and, at the end, each live process's own VmHWM. The metrics are copied
to ``--metrics-out`` (compare two runs' files: they are equal but for ``dataset.path``).

    python benchmarks/dask_evaluate.py [--rows 1000000] [--data /tmp/ds1m] [--run /tmp/run1m]
        [--workers 2] [--memory-limit 4GiB] [--fqe-bootstrap N] [--model-particles N] [--episodes N]
        [--fqe-trees N] [--fqe-structure-rows auto]
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import threading
import time
from pathlib import Path
from typing import Any

import psutil
from dask_10m import make  # this directory is on the path when the script runs
from dask_scale import tree_cpu


class RSSSampler:
    """Peak RSS (bytes) of this process and every descendant, by pid, sampled every ``period`` s."""

    def __init__(self, period: float = 0.2) -> None:
        self.period, self.peak, self.names = period, {}, {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        me = psutil.Process()
        while not self._stop.is_set():
            for p in [me, *me.children(recursive=True)]:
                try:
                    rss = p.memory_info().rss
                    if p.pid not in self.names:
                        self.names[p.pid] = " ".join(p.cmdline()[-2:])[-60:]
                except psutil.Error:
                    continue
                self.peak[p.pid] = max(self.peak.get(p.pid, 0), rss)
            self._stop.wait(self.period)

    def __enter__(self) -> RSSSampler:
        self._thread.start()
        return self

    def __exit__(self, *_: Any) -> None:
        self._stop.set()
        self._thread.join()


def vmhwm_gib() -> float:
    """This process's own peak RSS (VmHWM), GiB."""
    return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM:")) / 2**20


def stages(marks: list[tuple[str, float, float]], end: tuple[float, float]) -> dict[str, list[float]]:
    """``{stage: [wall s, CPU s]}`` between each progress line and the next, counter lines
    (``"FQE bootstrap 5/20, ETA 7 s"``) folded into the stage they count."""
    out: dict[str, list[float]] = {}
    for (name, w, c), (_, w2, c2) in zip(marks, [*marks[1:], ("end", *end)], strict=True):
        m = re.match(r"(.*?):? (step |fold )?\d+/\d+\b", name)
        key = (m.group(1) if m else name.split(" (")[0].split(":")[0]).strip()
        acc = out.setdefault(key, [0.0, 0.0])
        acc[0] += w2 - w
        acc[1] += c2 - c
    return out


def prepare(args: argparse.Namespace) -> None:
    from offline_adp.runs import fit_run

    if not args.data.exists():
        t = time.perf_counter()
        make(args.rows, args.data)
        print(f"data: {args.data} written in {time.perf_counter() - t:.0f} s", flush=True)
    if not args.run.exists():
        t = time.perf_counter()
        fit_run(args.data, args.run, params={"gamma": 0.95, "n_iterations": args.fit_iterations,
                                             "regressor_params": {"n_jobs": 1}})
        print(f"fit: {args.run} in {time.perf_counter() - t:.0f} s", flush=True)


def evaluate(args: argparse.Namespace, settings: dict[str, Any]) -> dict[str, Any]:
    from offline_adp.engines.dask import DaskTaskMap, EngineConfig, dask_client
    from offline_adp.evaluation.run import evaluate_run

    t0, c0 = time.perf_counter(), tree_cpu()
    marks: list[tuple[str, float, float]] = [("setup", 0.0, 0.0)]

    def say(s: str) -> None:
        marks.append((s, time.perf_counter() - t0, tree_cpu() - c0))
        print(f"{marks[-1][1]:8.1f} s {marks[-1][2]:8.1f} CPU-s  {s}", flush=True)

    workers: dict[str, float] = {}
    with RSSSampler() as rss:
        if args.workers == 0:
            evaluate_run(args.run, dataset=args.data, progress=say, **settings)
            end = (time.perf_counter() - t0, tree_cpu() - c0)
        else:
            cfg = EngineConfig(kind="dask", n_workers=args.workers, threads_per_worker=1,
                               memory_limit=args.memory_limit)
            with dask_client(cfg) as client:
                say("cluster up")
                evaluate_run(args.run, dataset=args.data, progress=say, task_map=DaskTaskMap(client), **settings)
                end = (time.perf_counter() - t0, tree_cpu() - c0)  # before the workers (and their CPU) are gone
                workers = {k: round(v, 3) for k, v in client.run(vmhwm_gib).items()}
    by_pid = {f"{pid} {rss.names.get(pid, '')}": round(v / 2**30, 3) for pid, v in sorted(rss.peak.items())}
    return {"workers": args.workers, "settings": settings, "wall_s": round(end[0], 1), "cpu_s": round(end[1], 1),
            "stages": {k: [round(v[0], 1), round(v[1], 1)] for k, v in stages(marks, end).items()},
            "client_vmhwm_gib": round(vmhwm_gib(), 3), "worker_vmhwm_gib": workers,
            "sampled_peak_rss_gib": by_pid}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--data", type=Path, default=Path("/tmp/ds1m"))
    ap.add_argument("--run", type=Path, default=Path("/tmp/run1m"))
    ap.add_argument("--fit-iterations", type=int, default=10)
    ap.add_argument("--workers", type=int, default=2, help="0: the local evaluation (no cluster)")
    ap.add_argument("--memory-limit", default="4GiB")
    ap.add_argument("--fqe-bootstrap", type=int, default=None)
    ap.add_argument("--model-particles", type=int, default=None)
    ap.add_argument("--episodes", type=int, default=None)
    ap.add_argument("--bootstrap", type=int, default=None)
    ap.add_argument("--fqe-trees", type=int, default=None,
                    help='fqe_params={"regressor_params": {"n_estimators": N}} (default: the evaluation\'s 20)')
    ap.add_argument("--fqe-structure-rows", choices=["auto"], default=None,
                    help='fqe_params={"structure_max_samples": "auto"}: FQE\'s tree structures grown on a '
                         'bootstrap of at most 131,072 rows, their leaves averaged over every row '
                         '(default: the evaluation\'s, every row)')
    ap.add_argument("--metrics-out", type=Path, default=None)
    args = ap.parse_args()
    prepare(args)
    fqe_params: dict[str, Any] = {}
    if args.fqe_trees:
        fqe_params["regressor_params"] = {"n_estimators": args.fqe_trees}
    if args.fqe_structure_rows:
        fqe_params["structure_max_samples"] = args.fqe_structure_rows
    settings = {k: v for k, v in (("fqe_bootstrap", args.fqe_bootstrap), ("model_particles", args.model_particles),
                                  ("episodes", args.episodes), ("bootstrap", args.bootstrap),
                                  ("fqe_params", fqe_params or None),
                                  ) if v is not None}
    out = evaluate(args, settings)
    if args.metrics_out is not None:
        shutil.copy(args.run / "evaluation" / "metrics.json", args.metrics_out)
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
