"""The one checkpoint codec of fitted-Q runs (local and Dask fits alike).

A checkpoint directory holds the last completed iteration of a resumable fit::

    CHECKPOINT/q.json, q.npz    Q_k (finite horizon: Q_{T-1}, ..., Q_{T-k} as a TimeIndexedQ)
                                and ``"iteration": k`` (:func:`offline_adp.artifacts.save_q`)
    CHECKPOINT/history.csv      the k history rows (one per iteration, in order)

:func:`write_checkpoint` replaces the directory as a whole (a temporary directory renamed
over it, a planted symbolic link replaced, never followed), so a crash leaves the
previous checkpoint. Once the run's ``model/`` is written, :func:`share_with_model`
makes the checkpoint's ``q.npz`` (stored uncompressed) a hard link to the model's
(compressed) when the two hold the same arrays (an infinite-horizon fit saves one Q in
both): a finished run keeps one copy on disk, and the checkpoint still reads on its own
(resume; ``model/`` removed or replaced).
:func:`read_checkpoint` reads an untrusted directory: the Q-function
through the checked artifact reader, the history through the checked table reader, then
its size, columns, types and agreement with the Q-function; anything else is an
:class:`~offline_adp.errors.ArtifactError` naming the file. The run writer
(:mod:`offline_adp.runs`) and the Dask engine (:mod:`offline_adp.engines.dask`) both use
these two functions.
"""

from __future__ import annotations

import os
import zipfile
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from offline_adp.errors import ArtifactError

HISTORY = "history.csv"
#: The largest history file read back (a row is ~200 bytes: millions of iterations).
MAX_HISTORY_BYTES = 256 << 20
#: Columns every fitted-Q history row has, all numbers (``step``: empty for infinite horizons).
NUMERIC_COLUMNS = ("iteration", "step", "sup_dq", "mean_dq", "max_abs_q", "bellman_residual", "greedy_changed",
                   "start_value")
#: number columns a resume reads when present (the frozen mode's structure record); empty allowed
OPTIONAL_NUMERIC_COLUMNS = ("structure", "structure_trees", "structure_screen")
#: columns the convergence verdict and the divergence monitor read: finite numbers on every row
FINITE_COLUMNS = ("sup_dq", "max_abs_q")


def write_checkpoint(directory: str | PathLike[str], est: Any, rows: list[dict[str, Any]]) -> int:
    """Write the fitted-Q estimator ``est``'s current Q and the history ``rows`` as the
    checkpoint ``directory``, replacing it atomically; returns the iterations written
    (0: nothing to write, the checkpoint left as it was).

    Parameters
    ----------
    directory : path-like
        The checkpoint directory (e.g. ``RUN/checkpoint``).
    est : FittedQIteration or FittedQEvaluation
        Mid-fit. Its :meth:`~offline_adp.algorithms.fqi_loop.FittedQEstimator.checkpoint_q`
        says which Q and how many of ``rows`` go together (a fit stopped inside an
        iteration: the rows of the iterations before); an estimator without it has
        ``q_function_`` (infinite horizon) or ``q_functions_`` (finite) of all ``rows``.
    rows : list of dict
        The history rows of the completed iterations.

    The arrays are stored uncompressed (written at every paced checkpoint, read only to
    resume); :func:`share_with_model` links the last one to the model's compressed copy.
    """
    from offline_adp.artifacts import save_q
    from offline_adp.data.rundir import RunDirectory
    from offline_adp.qfunctions import TimeIndexedQ

    d = Path(directory)
    hook = getattr(est, "checkpoint_q", None)
    if hook is not None:
        state = hook()
        if state is None or state[1] == 0:
            return 0
        q, n = state
    else:
        q, n = (est.q_function_ if est.horizon_ is None else TimeIndexedQ(list(reversed(est.q_functions_)))), len(rows)
    with RunDirectory(d.parent).subdirectory(d.name) as tmp:
        save_q(q, tmp, extra={"iteration": n}, compress=False)
        pd.DataFrame(rows[:n]).to_csv(tmp / HISTORY, index=False)
    return n


def share_with_model(directory: str | PathLike[str], model: str | PathLike[str]) -> bool:
    """Replace the checkpoint's ``q.npz`` (in ``directory``) by a hard link to
    ``model/q.npz`` when both hold the same members (names, sizes and CRC-32 of every
    array, from the zip directories): one copy on disk instead of two. Atomic (a link made
    aside, renamed over); where links are not possible, or the arrays differ (a finite
    horizon stores its steps in the other order), the copy stays. Returns whether linked."""
    c, m = Path(directory) / "q.npz", Path(model) / "q.npz"
    try:
        if c.is_symlink() or not c.is_file() or not m.is_file() or _members(c) != _members(m):
            return False
        tmp = c.with_name("q.npz.link")
        tmp.unlink(missing_ok=True)
        os.link(m, tmp)
        os.replace(tmp, c)
        return True
    except (OSError, zipfile.BadZipFile):
        return False


def _members(path: Path) -> list[tuple[str, int, int]]:
    with zipfile.ZipFile(path) as zf:
        return sorted((i.filename, i.file_size, i.CRC) for i in zf.infolist())


def read_checkpoint(directory: str | PathLike[str]) -> dict[str, Any] | None:
    """The checkpoint in ``directory`` as ``{"q", "history"}`` for
    :meth:`~offline_adp.algorithms.fqi_loop.FittedQEstimator.run_fitted_q`'s ``resume`` (finite horizons: ``q``
    is the list Q_{T-1}, Q_{T-2}, ... in the order they were fitted), or None when there
    is none (no ``q.json``).

    Raises
    ------
    ArtifactError
        A member is missing, unreadable, too large, lacks a column, holds text in a number
        column, or disagrees with the Q-function (iterations not 1..k, k Q-functions for a
        finite horizon); the message names the file.
    """
    from offline_adp.artifacts import load_q
    from offline_adp.qfunctions import TimeIndexedQ

    d = Path(directory)
    if not (d / "q.json").exists():
        return None
    q, meta = load_q(d)
    hist = _read_history(d / HISTORY)
    n = len(hist)
    where = d / HISTORY
    saved = meta.get("iteration")
    if saved is not None and saved != n:
        raise ArtifactError(f"{where}: {n} history rows, but {d / 'q.json'} was written after iteration {saved}; "
                            f"the checkpoint is inconsistent: remove {d} to start the fit again")
    if isinstance(q, TimeIndexedQ) and len(q.qs) != n:
        raise ArtifactError(f"{where}: {n} history rows for {len(q.qs)} per-step Q-functions in {d / 'q.json'}; "
                            f"remove {d} to start the fit again")
    rows = [{k: (None if pd.isna(v) else v) for k, v in r.items()} for r in hist.to_dict("records")]
    return {"q": list(q.qs) if isinstance(q, TimeIndexedQ) else q, "history": rows}


def _read_history(path: Path) -> pd.DataFrame:
    """``history.csv`` read with checks: size, the number columns, iterations 1..k."""
    from offline_adp.data.files import read_table_file

    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise ArtifactError(f"{path}: missing (the checkpoint is incomplete: remove {path.parent} to start the fit "
                            "again)") from None
    except OSError as exc:
        raise ArtifactError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if not path.is_file() or path.is_symlink():
        raise ArtifactError(f"{path}: not a regular file this fit wrote; remove {path.parent} to start the fit again")
    if size > MAX_HISTORY_BYTES:
        raise ArtifactError(f"{path}: {size} bytes, more than a history can be ({MAX_HISTORY_BYTES}); "
                            f"remove {path.parent} to start the fit again")
    hist = read_table_file(path)  # unparsable: ArtifactError naming it
    missing = [c for c in NUMERIC_COLUMNS if c not in hist.columns]
    if missing:
        raise ArtifactError(f"{path}: no column {missing} (found {list(hist.columns)[:12]}); a checkpoint of another "
                            f"version or a damaged file: remove {path.parent} to start the fit again")
    for c in (*NUMERIC_COLUMNS, *(c for c in OPTIONAL_NUMERIC_COLUMNS if c in hist.columns)) if len(hist) else ():
        col = hist[c]
        if not (pd.api.types.is_numeric_dtype(col) and not pd.api.types.is_bool_dtype(col)):
            bad = col[pd.to_numeric(col, errors="coerce").isna() & col.notna()]
            shown = repr(bad.iloc[0]) if len(bad) else f"dtype {col.dtype}"
            raise ArtifactError(f"{path}: column {c!r} must hold numbers, found {shown}"
                                f"{f' (row {int(bad.index[0]) + 1})' if len(bad) else ''}; "
                                f"remove {path.parent} to start the fit again")
    for c in FINITE_COLUMNS if len(hist) else ():
        bad = ~np.isfinite(hist[c].to_numpy(dtype=np.float64))
        if bad.any():
            raise ArtifactError(f"{path}: column {c!r} must hold finite numbers, found "
                                f"{hist[c].iloc[int(bad.argmax())]!r} "
                                f"(row {int(bad.argmax()) + 1}); remove {path.parent} to start the fit again")
    if "structure" in hist.columns and len(hist):
        v = hist["structure"].dropna().to_numpy(dtype=np.float64)
        if len(v) and ((v != np.round(v)) | (v < 1) | (v > 10**9)).any():
            raise ArtifactError(f"{path}: column 'structure' must count builds 1, 2, ...; found {v[:8].tolist()}; "
                                f"remove {path.parent} to start the fit again")
    it = hist["iteration"].to_numpy()
    if not np.array_equal(it, np.arange(1, len(hist) + 1)):
        raise ArtifactError(f"{path}: column 'iteration' must count 1, 2, ..., {len(hist)}; found "
                            f"{it[:8].tolist()}{'...' if len(it) > 8 else ''}; remove {path.parent} to start "
                            "the fit again")
    return hist
