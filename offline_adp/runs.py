"""``offline-adp fit``: configuration, run directories, checkpoints and resume.

A run directory holds::

    RUN_DIR/config.json        the resolved algorithm parameters
    RUN_DIR/checkpoint/        the last completed iteration (Q-function, history), replaced atomically
    RUN_DIR/model/             the fitted Q-function(s), params.json, history.csv (written at the end)
    RUN_DIR/run.json           dataset path and fingerprint, status, timings, versions

Ctrl-C or a crash leaves ``checkpoint/`` at the last completed iteration;
``--resume`` continues from it.
"""

from __future__ import annotations

import json
import os
import shutil
import time
import tomllib
from collections.abc import Callable
from os import PathLike
from pathlib import Path
from typing import Any

import pandas as pd

from offline_adp.algorithms.fqi import FittedQIteration, save_fqi
from offline_adp.artifacts import load_q, save_q, versions
from offline_adp.data.io import read_dataset
from offline_adp.errors import OfflineADPError, SpecError
from offline_adp.qfunctions import TimeIndexedQ

ALGORITHMS = {"fqi": FittedQIteration}
#: Keys of each algorithm's TOML table besides its estimator's parameters, and the
#: access model it needs (trace data unless a simulator is named).
EXTRA_KEYS = {
    "fqi": set(),
    "fqe": {"policy"},
    "api": {"fqe"},
    "cpi": {"fqe", "simulator", "problem_options"},
    "psdp": {"simulator", "problem_options", "baseline_source", "drop_features"},
}


def _estimator_class(algorithm: str) -> type:
    from offline_adp.algorithms.api import ApproximatePolicyIteration
    from offline_adp.algorithms.cpi import ConservativePolicyIteration
    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.algorithms.psdp import PSDP

    return {"fqi": FittedQIteration, "fqe": FittedQEvaluation, "api": ApproximatePolicyIteration,
            "cpi": ConservativePolicyIteration, "psdp": PSDP}[algorithm]


def load_config(path: str | PathLike[str] | None, algorithm: str) -> dict[str, Any]:
    """Algorithm parameters from a TOML file's ``[<algorithm>]`` table (or its top level).

    Relative paths (``policy``) are resolved against the config file's folder.
    """
    if algorithm not in EXTRA_KEYS:
        raise SpecError(f"unknown algorithm {algorithm!r}; known: {sorted(EXTRA_KEYS)}")
    if path is None:
        return {}
    try:
        raw = tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise SpecError(f"{path}: no such config file") from None
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{path}: not valid TOML ({exc})") from exc
    params = dict(raw.get(algorithm, raw))
    valid = set(_estimator_class(algorithm)().get_params()) - {"fqe", "policy", "model", "initial_policy", "initial_q", "psdp"}
    valid |= EXTRA_KEYS[algorithm]
    unknown = sorted(set(params) - valid)
    if unknown:
        raise SpecError(f"{path}: unknown key(s) {unknown} for {algorithm}; valid keys are {sorted(valid)}")
    if "fqe" in params:
        fqe_valid = set(_estimator_class("fqe")().get_params()) - {"policy", "initial_q"}
        bad = sorted(set(params["fqe"]) - fqe_valid)
        if bad:
            raise SpecError(f"{path}: unknown key(s) {bad} in [{algorithm}.fqe]; valid keys are {sorted(fqe_valid)}")
    if "policy" in params:
        params["policy"] = str((Path(path).parent / params["policy"]).resolve())
    return params


def fit_other(dataset: str | PathLike[str], out: str | PathLike[str], algorithm: str, params: dict[str, Any]) -> Any:
    """FQE, API, CPI or PSDP into a run directory (``model/`` holds policy, params, history)."""
    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.artifacts import load_policy, save_policy
    from offline_adp.envs import make_problem

    run = Path(out)
    if run.exists():
        raise OfflineADPError(f"{run} already exists; choose another --out (only fqi runs can be resumed)")
    ds = read_dataset(dataset)
    p = dict(params)
    fqe = FittedQEvaluation(**p.pop("fqe")) if "fqe" in p else None
    sim = make_problem(p.pop("simulator"), **p.pop("problem_options", {})) if "simulator" in p else None
    t0, c0 = time.perf_counter(), time.process_time()
    if algorithm == "fqe":
        if "policy" not in p:
            raise SpecError("fqe needs the policy to evaluate: policy = \"RUN_DIR/model\" in [fqe]")
        est = FittedQEvaluation(policy=load_policy(p.pop("policy")), **p).fit(ds)
        summary = {"value": est.value_}
    elif algorithm == "api":
        est = _estimator_class("api")(fqe=fqe, **p).fit(ds)
        summary = {"value": float(est.history_["value"].iloc[-1])}
    elif algorithm == "cpi":
        est = _estimator_class("cpi")(fqe=fqe, model=sim, **p).fit(ds)
        summary = {"value": float(est.history_["value"].iloc[-1])}
    else:
        if sim is None:
            raise SpecError("psdp needs a simulator (a reference problem): simulator = \"path_tracking\" in [psdp]")
        source, drop = p.pop("baseline_source", None), p.pop("drop_features", None)
        from offline_adp.features import drop_features

        baseline = ds.filter_source(source) if source else ds
        fmap = drop_features(ds.feature_names, drop) if drop else None
        est = _estimator_class("psdp")(feature_map=fmap, **p).fit(sim, baseline)
        summary = {"simulator_steps": est.simulator_steps_}
    tmp = run.parent / f".{run.name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    save_policy(est.policy_, tmp / "model", extra={"algorithm": algorithm, "dataset_fingerprint": ds.fingerprint()})
    if getattr(est, "q_function_", None) is not None:
        save_q(est.q_function_, tmp / "model")
    est.history_.to_csv(tmp / "model" / "history.csv", index=False)
    (tmp / "config.json").write_text(json.dumps({"algorithm": algorithm, "params": params}, indent=1, default=str))
    status = {"dataset": str(dataset), "dataset_fingerprint": ds.fingerprint(), "algorithm": algorithm, "versions": versions(),
              "status": "completed", "fit_seconds": time.perf_counter() - t0, "fit_cpu_seconds": time.process_time() - c0,
              **summary}
    (tmp / "run.json").write_text(json.dumps(status, indent=1, default=float))
    os.replace(tmp, run)
    return est


def _write_checkpoint(run: Path, est: FittedQIteration, rows: list[dict[str, Any]]) -> None:
    from offline_adp.data.io import atomic_directory

    q: Any = est.q_function_ if est.horizon is None else TimeIndexedQ(list(reversed(est.q_functions_)))
    with atomic_directory(run / "checkpoint", overwrite=True) as tmp:
        save_q(q, tmp, extra={"iteration": len(rows)})
        pd.DataFrame(rows).to_csv(tmp / "history.csv", index=False)


def _read_checkpoint(run: Path, finite: bool) -> dict[str, Any] | None:
    ck = run / "checkpoint"
    if not (ck / "q.json").exists():
        return None
    q, _ = load_q(ck)
    hist = pd.read_csv(ck / "history.csv")
    rows = [{k: (None if pd.isna(v) else v) for k, v in r.items()} for r in hist.to_dict("records")]
    # finite horizons are stored as Q_{T-1}, Q_{T-2}, ... (the order they were fitted)
    return {"q": list(q.qs) if finite else q, "history": rows}


def fit_run(
    dataset: str | PathLike[str],
    out: str | PathLike[str],
    *,
    algorithm: str = "fqi",
    params: dict[str, Any] | None = None,
    resume: bool = False,
    on_iteration: Callable[[dict[str, Any]], None] | None = None,
    checkpoint_every: int = 1,
) -> FittedQIteration:
    """Fit ``algorithm`` on a dataset directory into a run directory (see module docstring)."""
    run = Path(out)
    params = dict(params or {})
    if run.exists() and not resume:
        raise OfflineADPError(f"{run} already exists; use --resume to continue it or choose another --out")
    if resume and not run.exists():
        raise OfflineADPError(f"{run} does not exist: nothing to resume")
    ds = read_dataset(dataset)
    run.mkdir(parents=True, exist_ok=True)
    if resume:
        saved = json.loads((run / "config.json").read_text())
        if params and params != saved["params"]:
            raise OfflineADPError(f"{run}: --resume with different parameters than the run was started with ({saved['params']})")
        params = saved["params"]
        info = json.loads((run / "run.json").read_text())
        if info["dataset_fingerprint"] != ds.fingerprint():
            raise OfflineADPError(f"{run}: the dataset changed since the run started (fingerprint differs); start a new run")
    else:
        (run / "config.json").write_text(json.dumps({"algorithm": algorithm, "params": params}, indent=1))
    est = ALGORITHMS[algorithm](**params)
    status = {"dataset": str(dataset), "dataset_fingerprint": ds.fingerprint(), "algorithm": algorithm, "versions": versions(), "status": "running"}
    (run / "run.json").write_text(json.dumps(status, indent=1))
    state = _read_checkpoint(run, est.horizon is not None) if resume else None
    t0, c0 = time.perf_counter(), time.process_time()
    rows: list[dict[str, Any]] = list(state["history"]) if state else []
    written, last_write, write_cost = len(rows), time.perf_counter(), 0.0
    try:
        for row in est.fit_iter(ds, resume=state):
            rows.append(row)
            # every mode checkpoints; when writing costs more than a tenth of the iterations since
            # the last write (a frozen structure is large, its iterations cheap), less often
            if len(rows) % checkpoint_every == 0 and time.perf_counter() - last_write >= 10 * write_cost:
                w0 = time.perf_counter()
                _write_checkpoint(run, est, rows)
                written, last_write, write_cost = len(rows), time.perf_counter(), time.perf_counter() - w0
            if on_iteration:
                on_iteration(row)
        if written != len(rows):  # the last iteration is always checkpointed before model/ is written
            _write_checkpoint(run, est, rows)
    except KeyboardInterrupt:
        status.update(status="interrupted", completed_iterations=len(rows))
        (run / "run.json").write_text(json.dumps(status, indent=1))
        raise
    model_tmp = run / "model.tmp"
    shutil.rmtree(model_tmp, ignore_errors=True)
    save_fqi(est, model_tmp, dataset_fingerprint=ds.fingerprint())
    shutil.rmtree(run / "model", ignore_errors=True)
    os.replace(model_tmp, run / "model")
    status.update(status="completed", iterations=len(rows), fit_seconds=time.perf_counter() - t0,
                  fit_cpu_seconds=time.process_time() - c0, diverged=bool(est.diverged_), verdict=est.verdict_,
                  verdict_message=est.verdict_message_)
    (run / "run.json").write_text(json.dumps(status, indent=1))
    return est
