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

Each stage has a *key*: a hash of its settings, of its inputs' keys (input files by
sha256), of the versions the manifest records (the library's and of the libraries whose
models it stores) and of the library's code (:func:`code_fingerprint`): a stage computed by
other code is recomputed, and an interrupted fit resumes only from checkpoints written under
the same key. A stage whose key matches the manifest's completed entry is reused. Without
``--out``, the latest run directory of the same name and seed is continued, so running
a pipeline twice reuses every stage, and a run killed mid-stage resumes from the last
completed stage (an interrupted FQI fit resumes from its last checkpointed iteration).
``--force`` starts a fresh directory; ``--from STAGE`` recomputes that stage and the
ones after it.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from os import PathLike
from pathlib import Path
from typing import Any

from offline_adp.algorithms.registry import get_algorithm
from offline_adp.config import validate_config
from offline_adp.data.files import sha256_file
from offline_adp.data.rundir import RunDirectory
from offline_adp.errors import SpecError
from offline_adp.evaluation.settings import (  # MAX_*: the evaluate settings' bounds, from their one model
    MAX_EPISODES,  # noqa: F401
    MAX_REPLICATES,  # noqa: F401
    EvaluationSettings,
)

# the pipeline file's model and loader (pipeline_file.py), importable from here too
from offline_adp.pipeline_file import (  # noqa: F401
    BUILTIN,
    DASK_SCHEMES,
    DATA_KEYS,
    DataSection,
    EmptySection,
    EngineSection,
    EvaluateSection,
    FitSection,
    PipelineFile,
    _load_spec,
    load_pipeline,
)
from offline_adp.progress import log_milestone

STAGES = ("data", "validate", "fit", "evaluate", "report")


def _hash(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


#: The files a completed stage leaves in the run directory (checked before it is reused;
#: ``a|b``: either).
STAGE_OUTPUTS: dict[str, tuple[str, ...]] = {
    "data": ("dataset/meta/info.json",), "validate": ("dataset/meta/info.json",),
    "fit": ("fit/run.json", "fit/model/q.json|fit/model/policy.json"),
    "evaluate": ("fit/evaluation/metrics.json", "metrics.json"), "report": ("report.html",)}


class Manifest:
    """``manifest.json``: written after every stage (atomically: temp file + rename)."""

    def __init__(self, rd: RunDirectory, cfg: dict[str, Any]) -> None:
        self.rd = rd
        old = rd.read_json("manifest.json") if rd.exists("manifest.json") else {}
        from offline_adp.artifacts import versions

        self.data: dict[str, Any] = {"name": cfg["name"], "seed": cfg["seed"], "pipeline": cfg["file"],
                                     "config_hash": _hash(cfg), "versions": versions(), "code": code_fingerprint(),
                                     "created": old.get("created"),
                                     "inputs": old.get("inputs", {}), "stages": old.get("stages", {}),
                                     "runs": old.get("runs", 0) + 1}
        self.data["created"] = self.data["created"] or datetime.now(UTC).isoformat(timespec="seconds")

    def done(self, stage: str, key: str) -> bool:
        """Completed with this key *and* its outputs still there (a run killed while
        ``--force`` cleared it, or a directory deleted by hand, is recomputed, not reused)."""
        s = self.data["stages"].get(stage)
        run = self.rd.path
        return bool(s and s.get("status") == "completed" and s.get("key") == key
                    and all(any((run / q).is_file() for q in p.split("|")) for p in STAGE_OUTPUTS.get(stage, ())))

    def set(self, stage: str, **fields: Any) -> None:
        self.data["stages"][stage] = {**self.data["stages"].get(stage, {}), **fields}
        self.write()

    def write(self) -> None:
        self.rd.write_json("manifest.json", self.data)


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
    cfg = load_pipeline(path, overrides)  # e.g. {"data.exploration": 10} for reduced test sizes
    if engine is not None:
        cfg["engine"] = validate_config(EngineSection, {**cfg["engine"], **engine}, "--engine/--scheduler").model_dump(
            exclude_none=True)
    if from_stage is not None and from_stage not in STAGES:
        raise SpecError(f"--from {from_stage!r}: stages are {list(STAGES)}")
    run = Path(out) if out is not None else default_run_dir(cfg, Path(runs_root), force)
    from offline_adp.data.io import check_dataset_output

    check_dataset_output(run / "dataset", cfg["data"].get("inputs", []))  # before config.json is written
    with RunDirectory(run).lock() as rd:
        if force:  # the manifest first: killed half-way, nothing is left that claims a stage done
            for child in sorted(rd.path.iterdir(), key=lambda c: c.name != "manifest.json"):
                rd.remove(child.name)
        _run_locked(cfg, rd, from_stage, say)
    return run


def _run_locked(cfg: dict[str, Any], rd: RunDirectory, from_stage: str | None, say: Callable[[str], None]) -> None:
    run = rd.path
    rd.write_json("config.json", cfg)
    man = Manifest(rd, cfg)
    redo = set(STAGES[STAGES.index(from_stage):]) if from_stage else set()
    say(f"run directory: {run}")

    def stage(name: str, key: str, fn: Callable[[], dict[str, Any] | None]) -> None:
        if name not in redo and man.done(name, key):
            man.set(name, reused=True)
            say(f"[{name}] reused (inputs, settings and code unchanged)")
            return
        if from_stage and name not in redo:  # asked to start later, but this earlier stage has nothing to reuse
            say(f"[{name}] running: no completed {name} stage with these inputs and settings in {run} to reuse "
                f"(--from {from_stage} reuses what a previous run in that directory completed; --runs DIR or --out "
                "DIR names where it is)")
        else:
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


@contextlib.contextmanager
def _engine(cfg: dict[str, Any], say: Callable[[str], None]) -> Iterator[Any]:
    eng = cfg["engine"]
    if eng.get("kind", "local") == "local":
        yield None
        return
    from offline_adp.engines.dask import EngineConfig, dask_client

    ec = EngineConfig(**{k: v for k, v in eng.items() if k in EngineSection.model_fields})
    with dask_client(ec) as client:
        say(f"[engine] dask: {len(client.scheduler_info()['workers'])} workers at {client.scheduler.address}")
        yield client


@functools.cache
def code_fingerprint() -> str:
    """sha256 of the library's source (every ``.py`` file of the package, by relative path):
    part of every stage's key, so that a stage computed by other code, an upgrade or a local
    edit, is recomputed rather than reused under the new code's name."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()


def _run_stages(cfg: dict[str, Any], run: Path, man: Manifest, stage: Callable[..., None], client: Any,
                say: Callable[[str], None]) -> None:
    data = cfg["data"]
    if "inputs" in data:
        man.data["inputs"] = {f: sha256_file(f) for f in data["inputs"]}
        if isinstance(data["spec"], str):
            man.data["inputs"][data["spec"]] = sha256_file(data["spec"])
    data_key = _hash({"data": data, "inputs": man.data["inputs"], "seed": cfg["seed"],
                      "versions": man.data["versions"], "code": man.data["code"]})
    stage("data", data_key, lambda: _data_stage(cfg, run, client))
    stage("validate", _hash(["validate", data_key]), lambda: _validate_stage(run))
    fit_key = _hash({"fit": cfg["fit"], "data": data_key, "seed": cfg["seed"],
                     "policy": _model_fingerprint(cfg["fit"]["params"].get("policy"))})
    # its checkpoints are resumed only when the fit they were written by had this key (same code and settings)
    same_fit = man.data["stages"].get("fit", {}).get("key") == fit_key
    stage("fit", fit_key, lambda: _fit_stage(cfg, run, say, client, resumable=same_fit))
    if cfg["evaluate"] is not None:
        eval_key = _hash({"evaluate": cfg["evaluate"], "fit": fit_key, "seed": cfg["seed"]})
        stage("evaluate", eval_key, lambda: _evaluate_stage(cfg, run, say, client))
        if cfg["report"]:
            stage("report", _hash(["report", eval_key]), lambda: _report_stage(run))


def _model_fingerprint(path: str | None) -> str | None:
    """sha256 of the saved model a fit reads (``fqe``'s ``policy``: a run or model
    directory), so that a policy replaced at the same path is evaluated again, not reused
    under the old one's numbers (only its path was in the key)."""
    if not path:
        return None
    root = Path(path)
    for d in (root, root / "model", root / "fit" / "model"):
        if (d / "policy.json").is_file() or (d / "q.json").is_file():
            return _hash({f.name: sha256_file(f) for f in sorted(d.iterdir()) if f.is_file()})
    return None  # the fit itself says what is wrong with the path


def _data_stage(cfg: dict[str, Any], run: Path, client: Any = None) -> dict[str, Any]:
    from offline_adp.data.validate import refuse_all_quarantined

    data = cfg["data"]  # every writer below is atomic (temporary directory, then rename)
    RunDirectory(run).remove("dataset")
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

        res = ingest_parquet(data["inputs"], _load_spec(data, cfg["file"]), run / "dataset",
                             on_error=data.get("on_error"))
        refuse_all_quarantined(run / "dataset", res.summary())
        return res.summary()
    from offline_adp.ingest.mcap import ingest_mcap

    spec = _load_spec(data, cfg["file"])
    ds, summary = ingest_mcap(data["inputs"], spec, out=run / "dataset", on_error=data.get("on_error"))
    refuse_all_quarantined(run / "dataset", summary)
    return {"transitions": len(ds), "episodes": len(ds.episode_ids)}


def _validate_stage(run: Path) -> dict[str, Any]:
    from offline_adp.data.validate import validate_directory

    report = validate_directory(run / "dataset")
    RunDirectory(run).write_json("validation.json", report.summary())
    return {"ok": bool(report.ok)}


def _fit_stage(cfg: dict[str, Any], run: Path, say: Callable[[str], None], client: Any = None,
               resumable: bool = True) -> dict[str, Any]:
    """The fit into ``fit/`` by the run writer (:func:`offline_adp.runs.fit_run`), on the
    Dask cluster for FQI with LightGBM or the default frozen extra-trees mode when there is
    a client (:func:`_fit_dask`): the same run directory, checkpoints and resume either way
    (``resumable``: the checkpoints there were written under this stage's key)."""
    from offline_adp.runs import fit_run

    fit = cfg["fit"]
    entry = get_algorithm(fit["algorithm"])
    params = dict(fit.get("params", {}))
    holdout = fit.get("holdout")
    if holdout and client is not None and entry.dask:  # the engine reads the whole dataset directory
        say("[fit] runs in the client process (holdout: the Dask engine reads every episode)")
    engine = _fit_dask(entry, params, run / "dataset", client, say) if client is not None and entry.dask \
        and not holdout else None
    if "random_state" in entry.params_model().model_fields:
        params.setdefault("random_state", cfg["seed"])
    target = RunDirectory(run / "fit")
    resume = resumable and entry.resumable and target.exists("checkpoint") and target.exists(target.CONFIG) \
        and target.read_json(target.CONFIG).get("params") == params
    on = " (Dask)" if engine is not None else ""
    if resume:
        say(f"[fit] resuming from the last checkpointed iteration{on}")
    elif target.path.exists():
        RunDirectory(run).remove("fit")

    total = params.get("horizon") or params.get("n_iterations")

    def on_iteration(row: dict[str, Any]) -> None:  # a few progress lines a log can hold
        k = row.get("iteration", 0)
        if log_milestone(k, total):
            of = f"/{total}" if isinstance(total, int) else ""
            say(f"[fit] iteration {k}{of}{on}: sup|dQ| {row.get('sup_dq', float('nan')):.4g}")

    est = fit_run(run / "dataset", target.path, algorithm=entry.name, params=params, resume=resume,
                  on_iteration=on_iteration, engine=engine, holdout=holdout)
    hist = getattr(est, "history_", None)
    out = {"iterations": 0 if hist is None else len(hist), "diverged": bool(getattr(est, "diverged_", False))}
    if engine is None:
        return out
    # iterations whose row blocks trained away from their workers (a lost worker): same Q rule, more traffic
    unplaced = engine.unplaced_iterations_
    if unplaced:
        say(f"[fit] iterations {unplaced} trained with rows away from their workers (a worker was lost)")
    say(f"[fit] {est.verdict_message_}")
    return {**out, "engine": "dask", "verdict": est.verdict_, "verdict_message": est.verdict_message_,
            "unplaced_iterations": unplaced}


def _evaluate_stage(cfg: dict[str, Any], run: Path, say: Callable[[str], None], client: Any = None) -> dict[str, Any]:
    from offline_adp.evaluation.run import evaluate_run

    task_map = None
    if client is not None:  # rollout pieces and FQE bootstrap replicates on the workers (same results)
        from offline_adp.engines.dask import DaskTaskMap

        task_map = DaskTaskMap(client)
    settings = EvaluationSettings.resolve(None, {**cfg["evaluate"], "seed": cfg["seed"]}, cfg["file"])
    m = evaluate_run(run / "fit", settings=settings, dataset=run / "dataset", progress=lambda s: say(f"[evaluate] {s}"),
                     task_map=task_map)
    RunDirectory(run).copy_in(run / "fit" / "evaluation" / "metrics.json", "metrics.json")
    return {"fqe": m["ope"]["fqe"]["estimate"]}


def _report_stage(run: Path) -> dict[str, Any]:
    from offline_adp.evaluation.report import build_report

    html = build_report(run / "fit")
    rd = RunDirectory(run)
    rd.copy_in(html, "report.html")
    rd.copy_in(html.parent / "figures", "figures")
    return {"report": str(run / "report.html")}


def _fit_dask(entry: Any, params: dict[str, Any], dataset: Path, client: Any, say: Callable[[str], None]) -> Any:
    """The Dask engine (``DaskFit``) for a fit it can run as the local fit would
    (:func:`offline_adp.engines.dask.fqi.unsupported`: LightGBM, or the default frozen
    extra-trees mode, with every parameter it does not read at its default); otherwise
    None, the local engine, and a line saying why."""
    from offline_adp.engines.dask import DaskFit
    from offline_adp.engines.dask.fqi import unsupported

    why = unsupported(entry.estimator_class()(**params), dataset)
    if why is None:
        return DaskFit(client)
    say(f"[fit] runs in the client process ({why})")
    return None
