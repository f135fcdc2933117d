"""Episodes logged twice: an episode that repeats an earlier one row for row (states, next
states, actions, costs) under another id -- the same recording ingested twice (a copied
file, two exports that overlap). Each copy counts in a fit, and the evaluation's bootstrap
draws the copies as independent episodes, so its intervals are narrower than the logs
warrant. Found by each episode's column sums and length (one pass, ``np.add.reduceat``),
the candidates then compared exactly; reported with a warning, nothing dropped (a
deterministic system driven the same way from the same start does log equal episodes).
"""

from __future__ import annotations

import warnings

import numpy as np

from offline_adp.data import schema as S
from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import LogWarning


def repeated_episodes(ds: TransitionDataset) -> list[tuple[str, str]]:
    """``(id, id of the earlier episode it repeats)`` for every episode equal, row for row,
    to an earlier one in the dataset's order."""
    if ds.n_episodes < 2:
        return []
    t = ds.table
    names = [*ds.obs_columns, *ds.next_obs_columns, S.COST, S.ACTION]
    codes = np.asarray(ds.episode_codes)
    starts = np.flatnonzero(np.r_[True, codes[1:] != codes[:-1]])
    lengths = np.diff(np.r_[starts, len(codes)])

    def column(c: str) -> np.ndarray:
        return t.column(c).to_numpy(zero_copy_only=False)

    with np.errstate(invalid="ignore", over="ignore"):  # NaN sums are one signature of their own
        sig = np.column_stack([np.add.reduceat(column(c).astype(np.float64, copy=False), starts) for c in names]
                              + [lengths])
    _, group, size = np.unique(np.nan_to_num(sig, nan=np.pi), axis=0, return_inverse=True, return_counts=True)
    group = group.ravel()
    out: list[tuple[str, str]] = []
    ids = ds.episode_ids
    cand = np.flatnonzero(size[group] > 1)  # episodes sharing a signature: compared exactly
    if not len(cand):
        return out
    rows = np.concatenate([np.arange(starts[e], starts[e] + lengths[e]) for e in cand])
    x = np.column_stack([column(c)[rows].astype(np.float64) for c in names])
    at = dict(zip(cand.tolist(), np.cumsum(np.r_[0, lengths[cand][:-1]]).tolist(), strict=True))
    for g in np.unique(group[cand]):
        firsts: list[int] = []
        for e in np.flatnonzero(group == g):
            mine = x[at[e]:at[e] + lengths[e]]
            same = next((f for f in firsts if np.array_equal(mine, x[at[f]:at[f] + lengths[f]], equal_nan=True)), None)
            if same is None:
                firsts.append(int(e))
            else:
                out.append((str(ids[codes[starts[e]]]), str(ids[codes[starts[same]]])))
    return out


def warn_repeated(ds: TransitionDataset, where: str) -> list[tuple[str, str]]:
    """:func:`repeated_episodes`, with one :class:`~offline_adp.errors.LogWarning` naming the
    first few when there are any."""
    rep = repeated_episodes(ds)
    if rep:
        shown = ", ".join(f"{a!r} repeats {b!r}" for a, b in rep[:3]) + (f", ... ({len(rep) - 3} more)"
                                                                        if len(rep) > 3 else "")
        warnings.warn(f"{where}: {len(rep)} of {ds.n_episodes} episodes repeat an earlier episode row for row "
                      f"({shown}): the same recording ingested twice? Each copy counts in a fit, and the "
                      "evaluation's bootstrap draws the copies as independent episodes (its intervals come out "
                      "too narrow); if they are copies, ingest one of each", LogWarning, stacklevel=3)
    return rep
