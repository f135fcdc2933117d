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


def load_config(path: str | PathLike[str] | None, algorithm: str) -> dict[str, Any]:
    """Algorithm parameters from a TOML file's ``[fqi]`` table (or its top level)."""
    if algorithm not in ALGORITHMS:
        raise SpecError(f"unknown algorithm {algorithm!r}; known: {sorted(ALGORITHMS)}")
    if path is None:
        return {}
    try:
        raw = tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise SpecError(f"{path}: no such config file") from None
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{path}: not valid TOML ({exc})") from exc
    params = raw.get(algorithm, raw)
    valid = set(ALGORITHMS[algorithm]().get_params())
    unknown = sorted(set(params) - valid)
    if unknown:
        raise SpecError(f"{path}: unknown key(s) {unknown} for {algorithm}; valid keys are {sorted(valid)}")
    return dict(params)


def _write_checkpoint(run: Path, est: FittedQIteration, rows: list[dict[str, Any]]) -> None:
    tmp = run / "checkpoint.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    q: Any = est.q_function_ if est.horizon is None else TimeIndexedQ(list(reversed(est.q_functions_)))
    save_q(q, tmp, extra={"iteration": len(rows)})
    pd.DataFrame(rows).to_csv(tmp / "history.csv", index=False)
    old = run / "checkpoint.old"
    shutil.rmtree(old, ignore_errors=True)
    if (run / "checkpoint").exists():
        os.replace(run / "checkpoint", old)
    os.replace(tmp, run / "checkpoint")
    shutil.rmtree(old, ignore_errors=True)


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
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = list(state["history"]) if state else []
    try:
        for row in est.fit_iter(ds, resume=state):
            rows.append(row)
            if len(rows) % checkpoint_every == 0 and est.mode != "frozen":
                _write_checkpoint(run, est, rows)
            if on_iteration:
                on_iteration(row)
    except KeyboardInterrupt:
        status.update(status="interrupted", completed_iterations=len(rows))
        (run / "run.json").write_text(json.dumps(status, indent=1))
        raise
    model_tmp = run / "model.tmp"
    shutil.rmtree(model_tmp, ignore_errors=True)
    save_fqi(est, model_tmp, dataset_fingerprint=ds.fingerprint())
    shutil.rmtree(run / "model", ignore_errors=True)
    os.replace(model_tmp, run / "model")
    status.update(status="completed", iterations=len(rows), fit_seconds=time.perf_counter() - t0, diverged=bool(est.diverged_))
    (run / "run.json").write_text(json.dumps(status, indent=1))
    return est
