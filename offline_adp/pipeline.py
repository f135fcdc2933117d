"""``offline-adp run PIPELINE.toml``: the stages of a pipeline file into one run directory.

A pipeline file names its stages and their settings::

    name = "driving"
    seed = 0

    [data]                      # exactly one source: ingest files, or simulate
    format = "mcap"             # "mcap" | "parquet"
    inputs = ["../data/driving/*.mcap"]
    spec = "../data/specs/path_tracking_mcap.toml"   # or an inline [data.spec] table
    on_error = "quarantine"

    [fit]
    algorithm = "fqi"
    [fit.params]
    gamma = 0.95

    [evaluate]
    simulator = "path_tracking" # or "none"
    episodes = 300

    [report]

``[data]`` may instead hold ``simulate = "car_on_hill"`` with ``demonstrations``,
``exploration``, ``horizon`` and ``problem_options``, or ``builtin = "gridworld_lattice"``
(every lattice state and move once: the Boyan & Moore setting). Paths are relative to the pipeline
file. Unknown keys fail with the valid ones listed.

The run directory (``runs/<name>__<seed>__<timestamp>/`` or ``--out``) holds::

    config.json      the resolved pipeline
    manifest.json    input fingerprints, config hash, seed, versions, per-stage status,
                     key, timings and whether the stage was reused
    dataset/         the data stage's dataset directory
    validation.json  the doctor's report on it
    fit/             the fit run directory (model/, checkpoints, run.json)
    fit/evaluation/  metrics and arrays; fit/report/ the report
    metrics.json, report.html, figures/   copies at the top for convenience

Each stage has a *key*: a hash of its settings and of its inputs' keys (input files by
sha256). A stage whose key matches the manifest's completed entry is reused. Without
``--out``, the latest run directory of the same name and seed is continued, so running
a pipeline twice reuses every stage, and a run killed mid-stage resumes from the last
completed stage (an interrupted FQI fit resumes from its last checkpointed iteration).
``--force`` starts a fresh directory; ``--from STAGE`` recomputes that stage and the
ones after it.
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import json
import os
import shutil
import time
import tomllib
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from os import PathLike
from pathlib import Path
from typing import Any

import pandas as pd

from offline_adp.data.io import sha256_file
from offline_adp.errors import SpecError

STAGES = ("data", "validate", "fit", "evaluate", "report")
TOP_KEYS = {"name", "seed", "description", "data", "validate", "fit", "evaluate", "report", "engine"}
ENGINE_KEYS = {"kind", "address", "n_workers", "threads_per_worker", "memory_limit"}
DATA_KEYS = {"format", "inputs", "spec", "on_error", "simulate", "demonstrations", "exploration", "horizon",
             "problem_options", "builtin"}
#: Datasets built by a documented example rather than logged or simulated.
BUILTIN = {"gridworld_lattice": "offline_adp.examples.gridworld_divergence:dataset"}
FIT_KEYS = {"algorithm", "params", "config"}
EVAL_KEYS = {"simulator", "episodes", "bootstrap", "fqe_bootstrap", "fqe_params", "horizon"}


def _check(table: dict[str, Any], valid: set[str], where: str, path: Path) -> None:
    bad = sorted(set(table) - valid)
    if bad:
        raise SpecError(f"{path}: unknown key(s) {bad} in {where}; valid keys are {sorted(valid)}")


def load_pipeline(path: str | PathLike[str]) -> dict[str, Any]:
    """Read and check a pipeline file; paths become absolute (relative to the file)."""
    p = Path(path).resolve()
    try:
        raw = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise SpecError(f"{path}: no such pipeline file") from None
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{path}: not valid TOML ({exc})") from exc
    _check(raw, TOP_KEYS, "the top level", p)
    for key in ("data", "fit"):
        if key not in raw:
            raise SpecError(f"{p}: a pipeline needs a [{key}] table")
    data = dict(raw["data"])
    _check(data, DATA_KEYS, "[data]", p)
    if sum(k in data for k in ("simulate", "inputs", "builtin")) != 1:
        raise SpecError(f"{p}: [data] needs exactly one of inputs = [...] (files to ingest), simulate = \"PROBLEM\" "
                        f"or builtin = one of {sorted(BUILTIN)}")
    if "builtin" in data and data["builtin"] not in BUILTIN:
        raise SpecError(f"{p}: [data] builtin = {data['builtin']!r}; known: {sorted(BUILTIN)}")
    if "inputs" in data:
        if data.get("format") not in ("mcap", "parquet"):
            raise SpecError(f"{p}: [data] format must be \"mcap\" or \"parquet\", got {data.get('format')!r}")
        files: list[str] = []
        for pattern in data["inputs"]:
            hits = sorted(glob.glob(str(p.parent / pattern)))
            if not hits:
                raise SpecError(f"{p}: [data] inputs pattern {pattern!r} matches no file (relative to {p.parent})")
            files += hits
        data["inputs"] = files
        if isinstance(data.get("spec"), str):
            data["spec"] = str((p.parent / data["spec"]).resolve())
        elif "spec" not in data:
            raise SpecError(f"{p}: [data] needs spec = \"FILE.toml\" or an inline [data.spec] table")
    fit = dict(raw["fit"])
    _check(fit, FIT_KEYS, "[fit]", p)
    fit.setdefault("algorithm", "fqi")
    if "config" in fit:
        from offline_adp.runs import load_config

        fit["params"] = {**load_config(p.parent / fit.pop("config"), fit["algorithm"]), **fit.get("params", {})}
    ev = dict(raw.get("evaluate", {}))
    _check(ev, EVAL_KEYS, "[evaluate]", p)
    engine = dict(raw.get("engine", {}))
    _check(engine, ENGINE_KEYS, "[engine]", p)
    if engine.get("kind", "local") not in ("local", "dask"):
        raise SpecError(f"{p}: [engine] kind must be \"local\" or \"dask\", got {engine.get('kind')!r}")
    _check(dict(raw.get("validate", {})), set(), "[validate]", p)
    _check(dict(raw.get("report", {})), set(), "[report]", p)
    return {"name": str(raw.get("name", p.stem)), "seed": int(raw.get("seed", 0)), "file": str(p), "data": data,
            "fit": fit, "evaluate": ev if "evaluate" in raw else None, "report": "report" in raw,
            "engine": {"kind": "local", **engine}}


def _hash(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


class Manifest:
    """``manifest.json``: written after every stage (atomically: temp file + rename)."""

    def __init__(self, run: Path, cfg: dict[str, Any]) -> None:
        self.path = run / "manifest.json"
        old = json.loads(self.path.read_text()) if self.path.exists() else {}
        from offline_adp.artifacts import versions

        self.data: dict[str, Any] = {"name": cfg["name"], "seed": cfg["seed"], "pipeline": cfg["file"],
                                     "config_hash": _hash(cfg), "versions": versions(), "created": old.get("created"),
                                     "inputs": old.get("inputs", {}), "stages": old.get("stages", {}), "runs": old.get("runs", 0) + 1}
        self.data["created"] = self.data["created"] or datetime.now(UTC).isoformat(timespec="seconds")

    def done(self, stage: str, key: str) -> bool:
        s = self.data["stages"].get(stage)
        return bool(s and s.get("status") == "completed" and s.get("key") == key)

    def set(self, stage: str, **fields: Any) -> None:
        self.data["stages"][stage] = {**self.data["stages"].get(stage, {}), **fields}
        self.write()

    def write(self) -> None:
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.data, indent=1, default=str))
        os.replace(tmp, self.path)


def default_run_dir(cfg: dict[str, Any], root: Path, force: bool) -> Path:
    """The latest ``<root>/<name>__<seed>__*`` directory, or a new timestamped one."""
    prefix = f"{cfg['name']}__{cfg['seed']}__"
    existing = sorted(d for d in root.glob(prefix + "*") if d.is_dir()) if root.exists() else []
    if existing and not force:
        return existing[-1]
    return root / (prefix + datetime.now(UTC).strftime("%Y%m%dT%H%M%S"))


def run_pipeline(
    path: str | PathLike[str],
    *,
    out: str | PathLike[str] | None = None,
    runs_root: str | PathLike[str] = "runs",
    from_stage: str | None = None,
    force: bool = False,
    say: Callable[[str], None] = print,
    overrides: dict[str, Any] | None = None,
    engine: dict[str, Any] | None = None,
) -> Path:
    """Run (or continue) a pipeline; returns the run directory.

    ``engine`` overrides the file's ``[engine]`` (``{"kind": "dask", "address": ...}``).
    The engine is not part of any stage key: it changes where work runs, not results.
    """
    cfg = load_pipeline(path)
    for dotted, value in (overrides or {}).items():  # e.g. {"data.exploration": 10} for reduced test sizes
        *parents, leaf = dotted.split(".")
        valid = {"data": DATA_KEYS, "fit": FIT_KEYS, "evaluate": EVAL_KEYS, "engine": ENGINE_KEYS}
        if not parents or parents[0] not in valid or (len(parents) == 1 and leaf not in valid[parents[0]]) \
                or (len(parents) > 1 and parents[:2] != ["fit", "params"]):
            raise SpecError(f"--set {dotted}: not a pipeline setting; settings are "
                            + ", ".join(f"{t}.{k}" for t in valid for k in sorted(valid[t])) + ", fit.params.NAME")
        node = cfg
        for k in parents:
            if node.get(k) is None:
                node[k] = {}
            node = node[k]
        node[leaf] = value
    if engine is not None:
        cfg["engine"] = {**cfg["engine"], **engine}
    if from_stage is not None and from_stage not in STAGES:
        raise SpecError(f"--from {from_stage!r}: stages are {list(STAGES)}")
    run = Path(out) if out is not None else default_run_dir(cfg, Path(runs_root), force)
    if force and run.exists():
        shutil.rmtree(run)
    run.mkdir(parents=True, exist_ok=True)
    (run / "config.json").write_text(json.dumps(cfg, indent=1, default=str))
    man = Manifest(run, cfg)
    redo = set(STAGES[STAGES.index(from_stage):]) if from_stage else set()
    say(f"run directory: {run}")

    def stage(name: str, key: str, fn: Callable[[], dict[str, Any] | None]) -> None:
        if name not in redo and man.done(name, key):
            man.set(name, reused=True)
            say(f"[{name}] reused (inputs and settings unchanged)")
            return
        say(f"[{name}] running")
        man.set(name, status="running", key=key, reused=False)
        t0 = time.perf_counter()
        try:
            extra = fn() or {}
        except BaseException as exc:
            man.set(name, status="interrupted" if isinstance(exc, KeyboardInterrupt) else "failed",
                    error=f"{type(exc).__name__}: {exc}")
            raise
        man.set(name, status="completed", seconds=round(time.perf_counter() - t0, 3), **extra)
        redo.update(STAGES[STAGES.index(name) + 1:])  # everything downstream depends on this output

    with _engine(cfg, say) as client:
        _run_stages(cfg, run, man, stage, client, say)
    man.write()
    return run


@contextlib.contextmanager
def _engine(cfg: dict[str, Any], say: Callable[[str], None]) -> Iterator[Any]:
    eng = cfg["engine"]
    if eng.get("kind", "local") == "local":
        yield None
        return
    from offline_adp.engines.dask import EngineConfig, dask_client

    ec = EngineConfig(**{k: v for k, v in eng.items() if k in ENGINE_KEYS})
    with dask_client(ec) as client:
        say(f"[engine] dask: {len(client.scheduler_info()['workers'])} workers at {client.scheduler.address}")
        yield client


def _run_stages(cfg: dict[str, Any], run: Path, man: Manifest, stage: Callable[..., None], client: Any,
                say: Callable[[str], None]) -> None:
    data = cfg["data"]
    if "inputs" in data:
        man.data["inputs"] = {f: sha256_file(f) for f in data["inputs"]}
        if isinstance(data["spec"], str):
            man.data["inputs"][data["spec"]] = sha256_file(data["spec"])
    data_key = _hash({"data": data, "inputs": man.data["inputs"], "seed": cfg["seed"]})
    stage("data", data_key, lambda: _data_stage(cfg, run, client))
    stage("validate", _hash(["validate", data_key]), lambda: _validate_stage(run))
    fit_key = _hash({"fit": cfg["fit"], "data": data_key, "seed": cfg["seed"]})
    stage("fit", fit_key, lambda: _fit_stage(cfg, run, say, client))
    if cfg["evaluate"] is not None:
        eval_key = _hash({"evaluate": cfg["evaluate"], "fit": fit_key, "seed": cfg["seed"]})
        stage("evaluate", eval_key, lambda: _evaluate_stage(cfg, run, say, client))
        if cfg["report"]:
            stage("report", _hash(["report", eval_key]), lambda: _report_stage(run))


def _data_stage(cfg: dict[str, Any], run: Path, client: Any = None) -> dict[str, Any]:
    data = cfg["data"]  # every writer below is atomic (temporary directory, then rename)
    shutil.rmtree(run / "dataset", ignore_errors=True)
    if "builtin" in data:
        import importlib

        module, fn = BUILTIN[data["builtin"]].split(":")
        ds = getattr(importlib.import_module(module), fn)()
        ds.save(run / "dataset")
        return {"transitions": len(ds), "episodes": len(ds.episode_ids)}
    if "simulate" in data:
        from offline_adp.simulate import simulate

        ds = simulate(data["simulate"], data.get("demonstrations", 100), data.get("exploration", 100), seed=cfg["seed"],
                      horizon=data.get("horizon"), problem_options=data.get("problem_options"))
        ds.save(run / "dataset")
        return {"transitions": len(ds), "episodes": len(ds.episode_ids)}
    if client is not None:  # one task per file on the workers, written here in file order
        from offline_adp.engines.dask import ingest_distributed

        spec = data["spec"]
        if not isinstance(spec, str):
            raise SpecError("the Dask engine needs [data] spec as a file path (inline specs: use the local engine)")
        ds, reports = ingest_distributed(client, data["inputs"], spec, run / "dataset", fmt=data["format"],
                                         on_error=data.get("on_error"))
        return {"transitions": len(ds), "episodes": len(ds.episode_ids), "engine": "dask", "files": len(data["inputs"])}
    if data["format"] == "parquet":
        from offline_adp.ingest.parquet import ingest_parquet

        res = ingest_parquet(data["inputs"], data["spec"], run / "dataset", on_error=data.get("on_error"))
        return res.summary()
    from offline_adp.ingest.mcap import ingest_mcap, load_mcap_spec, parse_mcap_spec

    spec = load_mcap_spec(data["spec"]) if isinstance(data["spec"], str) else \
        parse_mcap_spec(data["spec"], json.dumps(data["spec"], sort_keys=True), where=f"{cfg['file']} [data.spec]")
    ds, summary = ingest_mcap(data["inputs"], spec, out=run / "dataset", on_error=data.get("on_error"))
    return {"transitions": len(ds), "episodes": len(ds.episode_ids)}


def _validate_stage(run: Path) -> dict[str, Any]:
    from offline_adp.data.validate import validate_directory

    report = validate_directory(run / "dataset")
    (run / "validation.json").write_text(json.dumps(report.summary(), indent=1, default=str))
    return {"ok": bool(report.ok)}


def _fit_stage(cfg: dict[str, Any], run: Path, say: Callable[[str], None], client: Any = None) -> dict[str, Any]:
    from offline_adp.runs import fit_other, fit_run

    fit = cfg["fit"]
    if client is not None and fit["algorithm"] == "fqi" and fit.get("params", {}).get("regressor") == "lightgbm":
        return _fit_dask(cfg, run, say, client)
    params = {"random_state": cfg["seed"], **fit.get("params", {})} if fit["algorithm"] == "fqi" else dict(fit.get("params", {}))
    target = run / "fit"
    if fit["algorithm"] == "fqi":
        resume = (target / "config.json").exists() and json.loads((target / "config.json").read_text())["params"] == params \
            and (target / "checkpoint").exists()
        if target.exists() and not resume:
            shutil.rmtree(target)
        if resume:
            say("[fit] resuming from the last checkpointed iteration")

        def on_iteration(row: dict[str, Any]) -> None:
            if row["iteration"] % 10 == 0:
                say(f"[fit] iteration {row['iteration']}: sup|dQ| {row['sup_dq']:.4g}")

        est = fit_run(run / "dataset", target, params=params, resume=resume, on_iteration=on_iteration)
        return {"iterations": len(est.history_), "diverged": bool(est.diverged_)}
    shutil.rmtree(target, ignore_errors=True)
    fit_other(run / "dataset", target, fit["algorithm"], params)
    return {}


def _evaluate_stage(cfg: dict[str, Any], run: Path, say: Callable[[str], None], client: Any = None) -> dict[str, Any]:
    from offline_adp.evaluation.run import evaluate_run

    task_map = None
    if client is not None:  # rollout pieces and FQE bootstrap replicates on the workers (same results)
        from offline_adp.engines.dask import DaskTaskMap

        task_map = DaskTaskMap(client)
    ev = cfg["evaluate"]
    m = evaluate_run(run / "fit", dataset=run / "dataset", simulator=ev.get("simulator"), n_episodes=ev.get("episodes", 500),
                     n_boot=ev.get("bootstrap", 200), n_boot_fqe=ev.get("fqe_bootstrap", 10), fqe_params=ev.get("fqe_params"),
                     horizon=ev.get("horizon"), seed=cfg["seed"], progress=lambda s: say(f"[evaluate] {s}"),
                     task_map=task_map)
    shutil.copy(run / "fit" / "evaluation" / "metrics.json", run / "metrics.json")
    return {"fqe": m["ope"]["fqe"]["estimate"]}


def _report_stage(run: Path) -> dict[str, Any]:
    from offline_adp.evaluation.report import build_report

    html = build_report(run / "fit")
    shutil.copy(html, run / "report.html")
    shutil.rmtree(run / "figures", ignore_errors=True)
    shutil.copytree(html.parent / "figures", run / "figures")
    return {"report": str(run / "report.html")}


def _fit_dask(cfg: dict[str, Any], run: Path, say: Callable[[str], None], client: Any) -> dict[str, Any]:
    """FQI with LightGBM on the Dask cluster (``DistributedFQI``), into the same fit run
    directory layout as a local fit; resumes from ``fit/checkpoint`` after a lost cluster."""
    from offline_adp.artifacts import save_q, versions
    from offline_adp.data.io import atomic_directory, read_dataset
    from offline_adp.engines.dask import DistributedFQI

    params = dict(cfg["fit"].get("params", {}))
    allowed = {"regressor", "regressor_params", "gamma", "n_iterations", "random_state", "mode", "trees_per_iteration"}
    bad = sorted(set(params) - allowed)
    if bad:
        raise SpecError(f"[fit.params] {bad} are not supported by the Dask engine's FQI (supported: {sorted(allowed)}); "
                        "use the local engine")
    if params.get("mode", "refit") not in ("refit", "warm_start"):
        raise SpecError(f"[fit.params] mode = {params['mode']!r} is not available on the Dask engine (use 'refit' or "
                        "'warm_start', or the local engine)")
    target = run / "fit"
    target.mkdir(parents=True, exist_ok=True)
    ds = read_dataset(run / "dataset")
    gamma = params.get("gamma", ds.info.gamma if ds.info.gamma is not None else 0.95)
    est = DistributedFQI(gamma=gamma, n_iterations=params.get("n_iterations", 50), lgbm_params=params.get("regressor_params"),
                         random_state=params.get("random_state", cfg["seed"]), warm_start=params.get("mode") == "warm_start",
                         trees_per_iteration=params.get("trees_per_iteration", 10))
    if (target / "checkpoint" / "q.json").exists():
        say("[fit] resuming from the last checkpointed iteration (Dask)")
    est.fit(client, run / "dataset", checkpoint_dir=target / "checkpoint",
            on_iteration=lambda k: say(f"[fit] iteration {k} (Dask)") if k % 10 == 0 else None)
    with atomic_directory(target / "model", overwrite=True) as tmp:
        save_q(est.q_function_, tmp, extra={"algorithm": "fqi", "engine": "dask", "dataset_fingerprint": ds.fingerprint(),
                                            "policy": "greedy (argmin_a Q)"})
        pd.DataFrame(est.history_).to_csv(tmp / "history.csv", index=False)
    (target / "config.json").write_text(json.dumps({"algorithm": "fqi", "engine": "dask", "params": params}, indent=1))
    (target / "run.json").write_text(json.dumps({"dataset": str(run / "dataset"), "dataset_fingerprint": ds.fingerprint(),
                                                 "algorithm": "fqi", "engine": "dask", "versions": versions(),
                                                 "status": "completed", "iterations": len(est.history_)}, indent=1))
    return {"iterations": len(est.history_), "engine": "dask"}
