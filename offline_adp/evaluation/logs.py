"""Which logs an evaluation reads, and whether the policy was fitted on them.

A run fitted with ``--holdout`` (``run.json``'s ``holdout``, :mod:`offline_adp.data.holdout`)
is evaluated on its held-out episodes only, when the dataset is the one it was fitted on
(``--dataset`` omitted, or naming data of the same fingerprint); other logs are read whole.
``metrics.json``'s ``logs`` says which (:func:`evaluated_logs`)::

    {"kind": "held_out" | "fit" | "other", "in_sample": bool, "episodes": N, "of": M,
     "description": "held-out episodes (N of M) the fit did not see"}

(held out: also ``ids_sha256`` and the whole dataset's ``dataset_fingerprint``; ``dataset``'s
``fingerprint`` is that of the episodes read).

``in_sample`` is true where the policy was chosen on these very episodes (``kind`` "fit",
any algorithm but ``fqe``, whose policy is given to it): there the greedy policy is optimal
for the logs' empirical model and FQE on the same logs read low (optimistic) in 9 of 10
tabular runs (docs/evaluation.md). :func:`in_sample_note` is the one clause the verdict
adds then, unless a simulator's rollouts measured the estimand (their truth is the
headline's). Other logs count as not the fit's by their fingerprint: logs that share
episodes with the fit's under another fingerprint are not detected.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from offline_adp.data.dataset import TransitionDataset
from offline_adp.evaluation.ope import is_finite_number
from offline_adp.evaluation.verdict import rollouts_of_another_value

#: The clause the verdict's why line (and its text) gains where the logs are the fit's own.
IN_SAMPLE_NOTE = ("the logs are the fit's own, so FQE-based readings may read optimistic "
                  "(`offline-adp fit --holdout` keeps episodes out)")


def evaluated_logs(run: Path, info: dict[str, Any], ds: TransitionDataset, ds_path: Path,
                   dataset_given: bool) -> tuple[TransitionDataset, dict[str, Any]]:
    """``(the episodes to evaluate on, metrics.json's logs block)``: the held-out episodes of
    a run fitted with ``--holdout`` on its own dataset (``dataset_given`` False, or data of the
    run's fingerprint), else ``ds`` whole."""
    from offline_adp.data.holdout import held_out_episodes, recorded_fraction

    stored, n = info.get("dataset_fingerprint"), ds.n_episodes
    same = not dataset_given or (ds.matches_fingerprint(stored) if stored is not None
                                 else _same_path(info.get("dataset_resolved"), ds_path))
    if not same:
        return ds, {"kind": "other", "in_sample": False, "episodes": n, "of": n,
                    "description": f"the logs given ({n} episodes), not the data the run was fitted on"}
    record = info.get("holdout")
    if recorded_fraction(record, str(run / "run.json")):
        held = held_out_episodes(ds, record, str(run / "run.json"))
        k = held.n_episodes
        return held, {"kind": "held_out", "in_sample": False, "episodes": k, "of": n,
                      "ids_sha256": record["ids_sha256"], "dataset_fingerprint": ds.fingerprint(),
                      "description": f"held-out episodes ({k} of {n}) the fit did not see"}
    given = info.get("algorithm") == "fqe"  # FQE evaluates a policy given to it: not chosen on these logs
    return ds, {"kind": "fit", "in_sample": not given, "episodes": n, "of": n,
                "description": f"the episodes the run was fitted on (all {n})"
                + (", its policy given to the fit, not chosen on them" if given else "")}


def _same_path(recorded: Any, ds_path: Path) -> bool:
    return isinstance(recorded, str) and bool(recorded) and Path(recorded).resolve() == ds_path.resolve()


def in_sample_note(m: dict[str, Any]) -> str | None:
    """:data:`IN_SAMPLE_NOTE` where ``metrics.json``'s ``logs`` says the policy was fitted on
    the logs evaluated, unless a simulator's rollouts measured the estimand; else None."""
    logs = m.get("logs")
    if not (isinstance(logs, dict) and logs.get("in_sample") is True):
        return None
    ro = (m.get("rollout") or {}).get("policy") or {}
    if is_finite_number(ro.get("mean_discounted_cost")) and ro.get("interval") and not rollouts_of_another_value(m):
        return None  # the rollouts are the truth the headline quotes first
    return IN_SAMPLE_NOTE


def with_note(v: dict[str, Any], note: str | None) -> dict[str, Any]:
    """The verdict ``v`` with ``note`` added to its why line and its text (``v`` itself when None)."""
    if note is None:
        return v
    lines = list(v.get("lines") or [])
    if len(lines) == 3:
        lines[2] = f"{lines[2]}; {note}"
    text = v.get("text") or ""
    return {**v, "lines": lines, "text": f"{text} The {note.removeprefix('the ')}." if text else text}
