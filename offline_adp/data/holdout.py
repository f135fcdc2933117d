"""Episodes held out of a fit (``offline-adp fit --holdout FRACTION``), so that ``evaluate``
can read the policy on logs the fit did not see.

The rule is :meth:`~offline_adp.data.dataset.TransitionDataset.split`: a permutation of the
dataset's sorted episode ids drawn from ``numpy.random.default_rng(seed)`` (the fit's
``random_state``), the first ``round(fraction * n)`` of it held out. ``run.json`` records it as
``holdout`` (:func:`holdout_split`)::

    {"fraction": 0.3, "seed": 0, "episodes": 18, "of": 60,
     "ids_sha256": "<sha256 of the held-out ids, sorted, one per line>",
     "ids": ["ep-003", ...]}          # listed when at most MAX_LISTED_IDS

so the held-out set can be recomputed from the dataset (its fingerprint is ``run.json``'s
``dataset_fingerprint``) and checked against the hash (:func:`held_out_episodes`).
"""

from __future__ import annotations

import hashlib
import math
from typing import Any

from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import ArtifactError, InvalidArgumentError

#: ``run.json`` lists the held-out ids up to this many (beyond, their hash and the rule say which).
MAX_LISTED_IDS = 2000
#: Episodes each side of the split must keep at least.
MIN_EPISODES = 2


def check_holdout(fraction: Any, flag: str = "--holdout") -> float:
    """``fraction`` as a float in [0, 1), else an :class:`~offline_adp.errors.InvalidArgumentError` naming ``flag``."""
    ok = isinstance(fraction, int | float) and not isinstance(fraction, bool) and math.isfinite(fraction)
    if not ok or not 0.0 <= float(fraction) < 1.0:
        raise InvalidArgumentError(f"{flag} {fraction!r}: expected the fraction of episodes to hold out of the fit, "
                                   "a number in [0, 1) (0: fit on every episode), e.g. 0.3")
    return float(fraction)


def ids_sha256(ids: Any) -> str:
    """The hash ``run.json`` records of a set of episode ids: sha256 of the ids as strings,
    sorted, one per line (UTF-8)."""
    return hashlib.sha256("\n".join(sorted(str(i) for i in ids)).encode("utf-8")).hexdigest()


def holdout_split(ds: TransitionDataset, fraction: float, seed: int, flag: str = "--holdout"
                  ) -> tuple[TransitionDataset, TransitionDataset | None, dict[str, Any] | None]:
    """``(episodes to fit on, held-out episodes, run.json's record)``; with ``fraction`` 0:
    ``(ds, None, None)``. Fewer than :data:`MIN_EPISODES` on either side is an
    :class:`~offline_adp.errors.InvalidArgumentError` naming ``flag``."""
    fraction = check_holdout(fraction, flag)
    if fraction == 0.0:
        return ds, None, None
    n = ds.n_episodes
    k = int(round(fraction * n))  # TransitionDataset.split's count
    if k < MIN_EPISODES or n - k < MIN_EPISODES:
        raise InvalidArgumentError(f"{flag} {fraction:g}: holds out {k} of the dataset's {n} episodes and fits on "
                                   f"{n - k}; each side needs at least {MIN_EPISODES} episodes (choose another "
                                   "fraction, or 0 to fit on every episode)")
    fit, held = ds.split(fraction, seed)
    ids = [str(i) for i in held.episode_ids]
    record: dict[str, Any] = {"fraction": fraction, "seed": int(seed), "episodes": len(ids), "of": n,
                              "rule": "TransitionDataset.split(fraction, seed): a seeded permutation of the sorted "
                                      "episode ids, the first round(fraction * n) held out",
                              "ids_sha256": ids_sha256(ids)}
    if len(ids) <= MAX_LISTED_IDS:
        record["ids"] = sorted(ids)
    return fit, held, record


def recorded_fraction(record: Any, where: str = "run.json") -> float:
    """The fraction a ``run.json``'s ``holdout`` record holds out (0 when there is none: the
    key absent or null); a record of another shape, or a fraction out of [0, 1), is an
    :class:`~offline_adp.errors.ArtifactError` naming ``where`` (never read as "none": the
    fit did not see those episodes)."""
    if record is None:
        return 0.0
    try:
        if not isinstance(record, dict):
            raise TypeError(f"a {type(record).__name__}, not a table")
        return check_holdout(record["fraction"], "holdout.fraction")
    except (KeyError, TypeError, ValueError) as exc:
        raise ArtifactError(f"{where}: its 'holdout' record is not one this version reads ({exc}); "
                            "fit the run again") from None


def held_out_episodes(ds: TransitionDataset, record: Any, where: str) -> TransitionDataset:
    """The episodes of ``ds`` (the dataset the run was fitted on) that ``record`` (``run.json``'s
    ``holdout``) held out of the fit, recomputed by the rule and checked against the record's
    hash and list; a record that does not hold is an :class:`~offline_adp.errors.ArtifactError`
    naming ``where``."""
    try:
        fraction, seed = check_holdout(record["fraction"], "holdout.fraction"), int(record["seed"])
        stored = str(record["ids_sha256"])
        _, held, mine = holdout_split(ds, fraction, seed, "holdout.fraction")
    except (KeyError, TypeError, ValueError, OverflowError) as exc:  # InvalidArgumentError is a ValueError
        raise ArtifactError(f"{where}: its 'holdout' record is not one this version reads ({exc}); "
                            "fit the run again") from None
    assert held is not None and mine is not None
    listed = record.get("ids")
    if mine["ids_sha256"] != stored or (isinstance(listed, list)
                                        and sorted(map(str, listed)) != sorted(map(str, held.episode_ids))):
        raise ArtifactError(f"{where}: the held-out episodes it records are not the ones its rule gives on this "
                            "dataset (the record was edited, or the rule changed); pass --dataset DIR to evaluate "
                            "on logs of your choice")
    return held
