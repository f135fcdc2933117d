"""``offline-adp fit``: configuration, the fit run directory, checkpoints and resume.

A fit run directory (:class:`~offline_adp.data.rundir.RunDirectory`) holds::

    RUN_DIR/config.json        the algorithm and its checked parameters
    RUN_DIR/checkpoint/        the last checkpointed iteration (Q-function, history), replaced atomically
    RUN_DIR/model/             the fitted artifacts, params.json, history.csv (written last, as a whole)
    RUN_DIR/run.json           dataset path and fingerprint, status, wall and CPU seconds, versions

Every algorithm of the registry (:mod:`offline_adp.algorithms.registry`) is fitted by
:func:`fit_run` into this one layout. The directory is locked while it is written, so a
second ``fit`` into the same ``--out`` fails at once; ``config.json`` is written before
the work starts and ``model/`` only at the end, so the two can never disagree.
Resumable algorithms (FQI) checkpoint as they iterate (the first and last iteration, and
between them as often as costs at most :data:`CHECKPOINT_CPU_SHARE` of the fit's CPU
time); after Ctrl-C or a crash, ``--resume`` continues from the last checkpoint.
``holdout`` (``--holdout FRACTION``) keeps a seeded share of whole episodes out of the fit
and records which in ``run.json``'s ``holdout`` (:mod:`offline_adp.data.holdout`), so
``offline-adp evaluate`` reads the policy on episodes the fit did not see.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from offline_adp.algorithms.checkpoint import read_checkpoint, share_with_model, write_checkpoint
from offline_adp.algorithms.registry import AlgorithmEntry, get_algorithm, resumable_algorithms
from offline_adp.artifacts import save_policy, save_q, versions
from offline_adp.config import load_toml
from offline_adp.data.dataset import read_dataset
from offline_adp.data.holdout import check_holdout, holdout_split, recorded_fraction
from offline_adp.data.rundir import RunDirectory
from offline_adp.data.validate import require_usable
from offline_adp.errors import InvalidArgumentError, RunDirectoryError


def load_config(path: str | PathLike[str] | None, algorithm: str) -> dict[str, Any]:
    """Algorithm parameters from a TOML file's ``[<algorithm>]`` table (or its top level),
    checked against the algorithm's configuration model before anything runs.

    Relative paths (``policy``) are resolved against the config file's folder.
    """
    entry = get_algorithm(algorithm)
    if path is None:
        return {}
    raw = load_toml(path, "fit configuration")
    params = entry.check_params(dict(raw.get(algorithm, raw)), str(path), algorithm)
    if params.get("policy") is not None:
        params["policy"] = str((Path(path).parent / params["policy"]).resolve())
    return params


#: A fit's checkpoints may cost at most this share of its CPU time: after a write that took
#: ``c`` CPU seconds, the next one waits until the iterations since took ``c / share``.
CHECKPOINT_CPU_SHARE = 0.05


def _check_run_output(out: Path, dataset: str | PathLike[str]) -> None:
    """A run directory is never the dataset it reads, a dataset directory or inside one
    (``fit DS --out DS`` put run files beside ``data/`` and ``meta/``). A run directory
    holding its dataset (``fit RUN/dataset --out RUN``) is fine: the fit adds files, it
    does not replace the directory."""
    from offline_adp.data.io import enclosing_dataset
    from offline_adp.errors import OutputExistsError

    target = out.resolve()
    if target == Path(dataset).resolve():
        raise OutputExistsError(f"--out {out} is the input dataset {dataset}; write the run elsewhere")
    d = enclosing_dataset(target)
    if d is not None:
        where = "is a dataset directory" if d == target else f"lies inside the dataset directory {d}"
        raise OutputExistsError(f"--out {out} {where}; write the run elsewhere")


def _write_checkpoint(run: Path, est: Any, rows: list[dict[str, Any]]) -> int:
    """Checkpoint ``est`` (the Q it has at hand, with its history rows); returns the
    iterations written (0: none)."""
    return write_checkpoint(run / RunDirectory.CHECKPOINT, est, rows)


def _read_checkpoint(run: Path) -> dict[str, Any] | None:
    return read_checkpoint(run / RunDirectory.CHECKPOINT)  # damaged: ArtifactError naming the file


def _iterate(rd: RunDirectory, est: Any, ds: Any, resume: bool, checkpoint_every: int,
             on_iteration: Callable[[dict[str, Any]], None] | None, engine: Any = None,
             dataset_dir: str | PathLike[str] | None = None) -> None:
    """Run a resumable algorithm's ``fit_iter`` (in process, or ``engine.fit_iter`` on the
    engine's workers from ``dataset_dir``), checkpointing every ``checkpoint_every``
    iterations at most, paced by their cost (:data:`CHECKPOINT_CPU_SHARE`); the first
    and the last iteration always. In process the fit is deferred (its Q is taken from
    the learner only when a checkpoint is written,
    :meth:`~offline_adp.algorithms.fqi_loop.FittedQEstimator.checkpoint_q`)."""
    state = _read_checkpoint(rd.path) if resume else None
    rows: list[dict[str, Any]] = list(state["history"]) if state else []
    written, last_write, write_cost = len(rows), time.process_time(), 0.0
    if engine is not None:
        iterations = engine.fit_iter(est, dataset_dir, state, checkpoint_dir=rd.file(rd.CHECKPOINT))
    else:
        iterations = est.fit_iter(ds, resume=state, deferred=True) if hasattr(est, "checkpoint_q") else \
            est.fit_iter(ds, resume=state)
    try:
        for row in iterations:
            rows.append(row)
            # every mode checkpoints; when writing costs more than CHECKPOINT_CPU_SHARE of the
            # iterations since the last write (a frozen structure is large, its iterations cheap), less often
            if len(rows) % checkpoint_every == 0 and \
                    time.process_time() - last_write >= write_cost / CHECKPOINT_CPU_SHARE:
                w0 = time.process_time()
                written = _write_checkpoint(rd.path, est, rows) or written
                last_write = time.process_time()
                write_cost = last_write - w0
            if on_iteration:
                on_iteration(row)
    except KeyboardInterrupt:  # Ctrl-C: keep the finished iterations the fit has a Q of (between two
        # iterations: all of them; inside one, a deferred fit's last result: maybe fewer than checkpointed)
        at_hand = est.checkpoint_iterations() if hasattr(est, "checkpoint_iterations") else len(rows)
        if at_hand > written:  # (never an older Q over a newer checkpoint)
            _write_checkpoint(rd.path, est, rows)
        raise
    finally:  # an engine releases its workers' data now, not when the generator is collected
        close = getattr(iterations, "close", None)
        if close is not None:
            close()
    if written != len(rows):  # the last iteration is always checkpointed before model/ is written
        _write_checkpoint(rd.path, est, rows)


def _save_model(entry: AlgorithmEntry, est: Any, rd: RunDirectory, fingerprint: str) -> None:
    with rd.subdirectory(RunDirectory.MODEL) as tmp:
        if entry.artifact == "q":
            from offline_adp.algorithms.fqi import save_fqi

            save_fqi(est, tmp, dataset_fingerprint=fingerprint)
            return
        save_policy(est.policy_, tmp, extra={"algorithm": entry.name, "dataset_fingerprint": fingerprint})
        if getattr(est, "q_function_", None) is not None:
            save_q(est.q_function_, tmp)
        pd.DataFrame(est.history_).to_csv(tmp / "history.csv", index=False)


def _summary(est: Any, engine: Any = None) -> dict[str, Any]:
    """Numbers for run.json: the value estimate, iterations, the fit's convergence verdict
    (and the engine's own, e.g. the Dask iterations trained with rows away from their workers)."""
    out: dict[str, Any] = {} if engine is None else dict(engine.summary())
    hist = getattr(est, "history_", None)
    if hist is not None:
        out["iterations"] = len(hist)
    if getattr(est, "value_", None) is not None:
        out["value"] = float(est.value_)
    elif isinstance(hist, pd.DataFrame) and "value" in hist and not hasattr(est, "value_"):  # (None: not known)
        out["value"] = float(hist["value"].iloc[-1])
    if isinstance(hist, pd.DataFrame) and "structure_trees" in hist:
        from offline_adp.algorithms.fqi import structure_builds

        out["structure_builds"] = structure_builds(hist)
    for attr in ("mode_", "simulator_steps_", "diverged_", "verdict_", "verdict_message_"):
        v = getattr(est, attr, None)
        if v is not None:
            out[attr.rstrip("_")] = v if not hasattr(v, "item") else v.item()
    return out


def _fit_seed(entry: AlgorithmEntry, params: dict[str, Any]) -> int:
    """The fit's seed, which also chooses the held-out episodes: ``random_state`` as given,
    else the estimator's default (0 where it has none)."""
    if params.get("random_state") is not None:
        return int(params["random_state"])
    import inspect

    p = inspect.signature(entry.estimator_class()).parameters.get("random_state")
    return int(p.default) if p is not None and isinstance(p.default, int) else 0


def _resumed_holdout(rd: RunDirectory, ds: Any, fraction: float | None,
                     seed: int) -> tuple[Any, dict[str, Any] | None]:
    """A resumed run's episodes to fit on and its ``holdout`` record: the run's own (a
    ``fraction`` given must be it), recomputed and checked against ``run.json``."""
    from offline_adp.data.holdout import held_out_episodes

    record = rd.read_json(rd.STATUS).get("holdout")
    own = recorded_fraction(record, str(rd.file(rd.STATUS)))
    if fraction is not None and fraction != own:
        raise RunDirectoryError(f"{rd.path}: the run was started with --holdout {own:g}, not {fraction:g}; resume "
                                "it with its own (or omit --holdout)")
    if not own:
        return ds, None
    held_out_episodes(ds, record, str(rd.file(rd.STATUS)))  # the record holds on this dataset
    if int(record["seed"]) != seed:
        raise RunDirectoryError(f"{rd.path}: its held-out episodes were chosen with seed {record['seed']}, its saved "
                                f"parameters say {seed}; start a new run")
    return holdout_split(ds, own, seed)[0], record


def fit_run(
    dataset: str | PathLike[str],
    out: str | PathLike[str],
    *,
    algorithm: str = "fqi",
    params: dict[str, Any] | None = None,
    resume: bool = False,
    on_iteration: Callable[[dict[str, Any]], None] | None = None,
    checkpoint_every: int = 1,
    engine: Any = None,
    holdout: float | None = None,
) -> Any:
    """Fit ``algorithm`` on a dataset directory into a run directory (see module docstring).

    Parameters
    ----------
    dataset : path-like
        A dataset directory.
    out : path-like
        The run directory: must not hold a run yet, unless ``resume``.
    algorithm : str
        A name of :data:`offline_adp.algorithms.registry.ALGORITHMS`.
    params : dict, optional
        The algorithm's parameters (checked before anything runs).
    resume : bool
        Continue an interrupted run of a resumable algorithm from its last checkpoint.
    on_iteration : callable, optional
        Called with each iteration's history row (resumable algorithms; in process the
        fit is deferred: the estimator's ``q_function_`` is set when the fit ends).
    checkpoint_every : int
        Checkpoint at most every this many iterations (paced by cost:
        :data:`CHECKPOINT_CPU_SHARE`).
    engine : optional
        Where a resumable algorithm's iterations run: None, in this process; an engine
        such as :class:`offline_adp.engines.dask.DaskFit` (FQI/FQE with LightGBM on a Dask
        cluster). The run directory is the same either way (``run.json`` names the engine).
    holdout : float, optional
        The fraction of whole episodes kept out of the fit, in [0, 1), chosen by the
        algorithm's ``random_state`` (:func:`offline_adp.data.holdout.holdout_split`) and
        recorded in ``run.json``'s ``holdout``; each side must keep 2 episodes. None: 0, or
        on ``resume`` the run's own; a resumed run must keep its fraction. Runs in process
        only (an engine reads the whole dataset directory).

    Returns
    -------
    The fitted estimator.
    """
    entry = get_algorithm(algorithm)
    params = entry.check_params(dict(params or {}), "parameters")  # before anything is written
    fraction = None if holdout is None else check_holdout(holdout)
    if fraction and engine is not None:
        raise InvalidArgumentError(f"--holdout {fraction:g}: the {engine.name} engine reads the whole dataset "
                                   "directory; hold episodes out with the local engine")
    if not resume:
        entry.check_complete(params)
    rd = RunDirectory(out)
    _check_run_output(rd.path, dataset)
    if resume and not entry.resumable:
        raise InvalidArgumentError(f"--resume is for {resumable_algorithms()} runs; "
                                   f"{algorithm} runs as a whole")
    if resume and not rd.path.exists():
        raise RunDirectoryError(f"{rd.path} does not exist: nothing to resume")
    ds = read_dataset(dataset)
    require_usable(ds, dataset)  # empty or failing the doctor: one error, not a crash mid-fit
    fit_ds, held = ds, None
    if not resume:  # too few episodes either side: refused before anything is written
        fit_ds, _, held = holdout_split(ds, fraction or 0.0, _fit_seed(entry, params))
    why = engine.unsupported(entry.estimator_class()(**params), dataset) \
        if engine is not None and entry.resumable and hasattr(engine, "unsupported") else None
    if why is not None:  # before anything is written
        raise InvalidArgumentError(f"the {engine.name} engine cannot run this fit ({why}); use the local engine")
    with rd.lock():
        if resume:
            if not rd.exists(rd.CONFIG):
                raise RunDirectoryError(f"{rd.path} has no {rd.CONFIG}: it is not a fit run directory that can be "
                                        "resumed (start it without --resume, or choose another --out)")
            saved = rd.read_json(rd.CONFIG)
            if saved.get("algorithm") != algorithm:
                raise RunDirectoryError(f"{rd.path}: the run was started with algorithm {saved.get('algorithm')!r}, "
                                        f"not {algorithm!r}")
            if params and params != saved["params"]:
                raise RunDirectoryError(f"{rd.path}: --resume with different parameters than the run was started "
                                        f"with ({saved['params']})")
            params = saved["params"]
            if not ds.matches_fingerprint(rd.read_json(rd.STATUS).get("dataset_fingerprint")):
                raise RunDirectoryError(f"{rd.path}: the dataset changed since the run started (fingerprint "
                                        "differs); start a new run")
            fit_ds, held = _resumed_holdout(rd, ds, fraction, _fit_seed(entry, params))
        elif any(rd.exists(n) for n in (rd.CONFIG, rd.STATUS, rd.MODEL)):
            raise RunDirectoryError(f"{rd.path} already holds a run; use --resume to continue it or choose "
                                    "another --out")
        else:
            rd.write_json(rd.CONFIG, {"algorithm": algorithm, "params": params})
        status: dict[str, Any] = {"dataset": str(dataset), "dataset_fingerprint": ds.fingerprint(),
                                  # the path as typed may be relative to this process's directory: the
                                  # absolute one finds the data from any directory (rundir.recorded_dataset)
                                  "dataset_resolved": str(Path(dataset).resolve()),
                                  # what the policy reads, in order: evaluate refuses data whose features differ
                                  # even where the fitted dataset itself was edited since (run_checks.py)
                                  "features": list(ds.feature_names),
                                  "action_values": np.asarray(ds.info.action_table.values).tolist(),
                                  "algorithm": algorithm,
                                  "access": entry.access, "versions": versions(), "status": "running"}
        if engine is not None:
            status["engine"] = engine.name
        if held is not None:  # which episodes the fit did not see (evaluate reads them)
            status["holdout"] = held
        rd.write_json(rd.STATUS, status)
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            if entry.resumable:
                est = entry.estimator_class()(**params)
                _iterate(rd, est, fit_ds, resume, checkpoint_every, on_iteration, engine, dataset)
            elif engine is not None:
                raise InvalidArgumentError(f"{algorithm} runs in process only (engines run {resumable_algorithms()})")
            else:
                est = entry.build_and_fit(params, fit_ds)
            _save_model(entry, est, rd, ds.fingerprint())  # a model that cannot be saved fails the run too
            if entry.resumable:  # the finished checkpoint shares the model's arrays (one copy on disk)
                share_with_model(rd.path / RunDirectory.CHECKPOINT, rd.path / RunDirectory.MODEL)
        except BaseException as exc:
            status.update(status="interrupted" if isinstance(exc, KeyboardInterrupt) else "failed",
                          error=f"{type(exc).__name__}: {exc}")
            rd.write_json(rd.STATUS, status)
            raise
        from offline_adp.artifacts import model_hashes

        status.update(status="completed", fit_seconds=time.perf_counter() - wall,
                      fit_cpu_seconds=time.process_time() - cpu,
                      model_sha256=model_hashes(rd.path / RunDirectory.MODEL), **_summary(est, engine))
        rd.write_json(rd.STATUS, status)
    return est
