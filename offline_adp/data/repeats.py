"""Episodes logged twice: an episode that repeats an earlier one row for row (states, next
states, actions, exact commands, costs) under another id -- the same recording ingested
twice (a copied file, two exports that overlap). Each copy counts in a fit, and the
evaluation's bootstrap draws the copies as independent episodes, so its intervals are
narrower than the logs warrant. Found by each episode's column sums and length (one pass,
``np.add.reduceat``), each candidate then compared exactly with its group's first episode
(vectorised), the few groups whose members differ compared pairwise; reported with a
warning, nothing dropped (a deterministic system driven the same way from the same start
does log equal episodes).
"""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd

from offline_adp.data import schema as S
from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import LogWarning


def repeated_episodes(ds: TransitionDataset) -> list[tuple[str, str]]:
    """The episodes equal, row for row, to an earlier one.

    Parameters
    ----------
    ds : TransitionDataset

    Returns
    -------
    list of (str, str)
        ``(id, id of the earlier episode it repeats)``, in the dataset's episode order.
    """
    if ds.n_episodes < 2:
        return []
    t = ds.table
    names = [*ds.obs_columns, *ds.next_obs_columns, S.COST, S.ACTION,
             *(c for c in t.column_names if c.startswith("action_value."))]
    codes = np.asarray(ds.episode_codes)
    starts = np.flatnonzero(np.r_[True, codes[1:] != codes[:-1]])
    lengths = np.diff(np.r_[starts, len(codes)])
    cols = [t.column(c).to_numpy(zero_copy_only=False).astype(np.float64, copy=False) for c in names]
    with np.errstate(invalid="ignore", over="ignore"):  # NaN sums are one signature of their own
        sig = np.column_stack([np.add.reduceat(c, starts) for c in cols] + [lengths])
    # one 64-bit hash per signature (a collision is harmless: the candidates are compared exactly)
    key = pd.util.hash_pandas_object(pd.DataFrame(np.nan_to_num(sig, nan=np.pi)), index=False).to_numpy()
    _, group, size = np.unique(key, return_inverse=True, return_counts=True)
    cand = np.flatnonzero(size[group] > 1)  # episodes sharing a signature (so a length) with another
    if not len(cand):
        return []
    cand = cand[np.argsort(group[cand], kind="stable")]  # by group, each in episode order
    g = group[cand]
    head = np.r_[True, g[1:] != g[:-1]]
    first = cand[np.flatnonzero(head)[np.cumsum(head) - 1]]  # each candidate's group's first episode
    L = lengths[cand]
    offs = np.arange(L.sum()) - np.repeat(np.cumsum(L) - L, L)  # row within its episode
    mine, theirs = np.repeat(starts[cand], L) + offs, np.repeat(starts[first], L) + offs
    eq = np.ones(len(mine), bool)
    for c in cols:
        eq &= (c[mine] == c[theirs]) | (np.isnan(c[mine]) & np.isnan(c[theirs]))
    same = np.logical_and.reduceat(eq, np.cumsum(L) - L)  # candidate == its group's first, row for row
    found = [(int(e), int(f)) for e, f, s in zip(cand, first, same, strict=True) if e != f and s]
    for grp in np.unique(g[~same]):  # members unlike their group's first: compared among themselves (rare)
        kept: list[int] = []
        for e in cand[(g == grp) & ~same]:
            rows = slice(starts[e], starts[e] + lengths[e])
            f = next((k for k in kept if all(np.array_equal(c[rows], c[starts[k]:starts[k] + lengths[k]],
                                                            equal_nan=True) for c in cols)), None)
            if f is None:
                kept.append(int(e))
            else:
                found.append((int(e), f))
    ids = ds.episode_ids
    return [(str(ids[codes[starts[e]]]), str(ids[codes[starts[f]]])) for e, f in sorted(found)]


def warn_repeated(ds: TransitionDataset, where: str) -> list[tuple[str, str]]:
    """:func:`repeated_episodes`, with one :class:`~offline_adp.errors.LogWarning` naming the
    first few when there are any.

    Parameters
    ----------
    ds : TransitionDataset
    where : str
        What the warning names (the input files).

    Returns
    -------
    list of (str, str)
        As :func:`repeated_episodes`.
    """
    rep = repeated_episodes(ds)
    if rep:
        shown = ", ".join(f"{a!r} repeats {b!r}" for a, b in rep[:3]) + (f", ... ({len(rep) - 3} more)"
                                                                        if len(rep) > 3 else "")
        warnings.warn(f"{where}: {len(rep)} of {ds.n_episodes} episodes repeat an earlier episode row for row "
                      f"({shown}): the same recording ingested twice? Each copy counts in a fit, and the "
                      "evaluation's bootstrap draws the copies as independent episodes (its intervals come out "
                      "too narrow); if they are copies, ingest one of each", LogWarning, stacklevel=3)
    return rep
