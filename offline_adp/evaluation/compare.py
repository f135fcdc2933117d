"""``offline-adp compare RUN_DIR...``: rank candidate policies on the same logs.

Off-policy selection (as in SCOPE-RL, Kiyohara et al. 2023): every candidate is evaluated on
the same dataset with the same estimator, and ranked by its estimated cost (lower is
better), each with its interval, its shift verdict and its fit's convergence. When the
simulator truth is known for every candidate (a reference problem), the ranking is scored
against it:

- **Spearman's rank correlation** and **Kendall's tau** between the estimated and the true
  costs (1: the same order);
- **regret of the top pick**: ``J(top pick) - min_k J(k)`` by the simulator (0: the best
  candidate was chosen), also relative to the spread ``max_k J(k) - min_k J(k)``.

Candidates already evaluated on the same dataset (``RUN_DIR/evaluation/metrics.json`` with
the dataset's fingerprint and the same simulator) are not re-evaluated unless ``force``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.errors import (
    IncompatibleError,
    InvalidArgumentError,
    RunDirectoryError,
    WriteError,
)
from offline_adp.evaluation.settings import EvaluationSettings
from offline_adp.evaluation.summary import (
    ESTIMATOR_NAMES,
    _f,
    discount_note,
    estimator_order,
    headline,
    level_words,
    outcome_of,
    rank_estimators,
    read_metrics,
    withdraw_levels,
)


def _metrics(run: Path) -> dict[str, Any] | None:
    p = run / "evaluation" / "metrics.json"
    return read_metrics(p) if p.exists() else None


def _dataset_of(run: Path) -> str | None:
    from offline_adp.data.rundir import recorded_dataset

    p = run / "run.json"
    return recorded_dataset(p) if p.exists() else None


def _fingerprint(path: str) -> str:
    from offline_adp.data.dataset import read_dataset

    return read_dataset(path).fingerprint()


def _same_model_rollouts(m: dict[str, Any], particles: int) -> bool:
    """Was the stored evaluation made with ``particles`` model-rollout particles? (Their bounds
    widen FQE's interval and can show support: candidates evaluated with other counts are not
    comparable.) Rollouts skipped for the logs' sake (a lattice, no start states) match any
    count; an evaluation of the infinite-horizon estimand runs none; one made before the model
    rollouts existed matches none."""
    fqe = (m.get("ope") or {}).get("fqe") or {}
    mr = fqe.get("model_rollouts")
    if mr is None:
        return (m.get("estimand") or {}).get("form") == "infinite"
    if "skipped" in mr:
        turned_off = str(mr["skipped"]).startswith("model_particles=0")
        return turned_off == (particles == 0)
    # evaluations made before the bounds had their own (trust) radius, before the model's own
    # interval was widened by its reading past the data (past_data_cost), or before it was hulled
    # with FQE's bootstrap interval where the two disagree (fqe_bootstrap_interval), are redone
    return (mr.get("n_particles") == particles and "trust_radius" in mr and "past_data_cost" in mr
            and ("fqe_interval" not in mr or "fqe_bootstrap_interval" in mr))


def compare_runs(
    run_dirs: Sequence[str | PathLike[str]],
    *,
    dataset: str | PathLike[str] | None = None,
    simulator: str | None = None,
    estimator: str | None = None,
    force: bool = False,
    evaluate_params: dict[str, Any] | None = None,
    progress: Callable[[str], None] | None = None,
    settings: EvaluationSettings | None = None,
) -> dict[str, Any]:
    """Rank the policies of ``run_dirs`` on one dataset (see the module docstring).

    Parameters
    ----------
    run_dirs : run directories (from ``offline-adp fit`` or a pipeline's ``fit/``), at least 2.
    dataset : the logs to compare on (default: the one every run was fitted on; they must agree).
    simulator : as for ``evaluate`` (default: the dataset's reference problem).
    estimator : rank by this estimator (default: the most reliable one that is reliable for
        every candidate, else each candidate's most reliable one, said so).
    force : re-evaluate even when a matching evaluation exists.
    evaluate_params : settings of the evaluations by name, set over ``settings``
        (:class:`~offline_adp.evaluation.settings.EvaluationSettings`; ``simulator`` too).

    Returns
    -------
    dict with ``candidates`` (ranked), ``estimator``, ``dataset``, and ``selection`` (rank
    correlations and regret) when the simulator truth is known.
    """
    cfg = EvaluationSettings.resolve(settings, {**(evaluate_params or {}),
                                                **({"simulator": simulator} if simulator is not None else {})})
    say = progress or (lambda _m: None)
    runs = _checked_runs(run_dirs, estimator)
    if dataset is None:  # their own logs: each is read on the episodes its fit held out, if any
        dataset = _common_dataset(runs)
    ds_path = str(Path(dataset).resolve())
    fp = _fingerprint(ds_path)
    metrics = _candidate_metrics(runs, ds_path, fp, cfg, force, say)
    rankings = [rank_estimators(withdraw_levels(m)) for m in metrics]  # a level only where it holds
    if estimator is None:  # reliable for all (with an interval), else usable for all (no interval)
        estimator = _common_estimator(rankings)
    rows = [_candidate_row(r, m, rk, estimator) for r, m, rk in zip(runs, metrics, rankings, strict=True)]
    usable = [x for x in rows if x["estimate"] is not None and np.isfinite(x["estimate"])]
    rest = [x for x in rows if x not in usable]
    usable.sort(key=lambda x: x["estimate"])
    for i, x in enumerate(usable + rest):
        x["rank"] = i + 1 if x in usable else None
    bv = metrics[0].get("behaviour_value") or {}
    beh = {"mean": bv.get("mean"), "interval": bv.get("interval"), "episodes": bv.get("episodes"),
           **{k: bv[k] for k in ("comparable", "not_comparable") if k in bv},
           "cost_distribution": (metrics[0].get("cost_distribution") or {}).get("behaviour_logged")}
    out: dict[str, Any] = {"dataset": {"path": ds_path, "fingerprint": fp}, "behaviour": beh,
                           "estimator": estimator or "mixed",
                           "estimand": metrics[0].get("estimand", {}).get("quantity"), "candidates": usable + rest,
                           "method": "candidates ranked by their off-policy estimate of the declared estimand "
                                     "(lower cost first)"}
    if estimator is None:
        out["note"] = "no estimator is reliable for every candidate: each is ranked by its own most reliable one"
    _top_pick_and_truth(out, usable, metrics[0])
    return out


def _checked_runs(run_dirs: Sequence[str | PathLike[str]], estimator: str | None) -> list[Path]:
    """The run directories as paths, at least two, each with a model; ``estimator`` a known name (or None)."""
    runs = [Path(r) for r in run_dirs]
    if len(runs) < 2:
        raise InvalidArgumentError("compare needs at least two run directories")
    if estimator is not None and estimator not in ESTIMATOR_NAMES:
        raise InvalidArgumentError(f"unknown estimator {estimator!r}; known: {sorted(ESTIMATOR_NAMES)}")
    for r in runs:
        if not (r / "model").is_dir():
            from offline_adp.data.rundir import pipeline_hint

            raise RunDirectoryError(f"{r}: not a run directory (no model/)"
                                    + (pipeline_hint(r) or "; fit one with `offline-adp fit`"))
    return runs


def _check_same_held_out(runs: list[Path]) -> None:
    """Before any evaluation: on the runs' own dataset each is read on the episodes its fit
    held out (``fit --holdout``), or on all; candidates read on different episodes are not
    ranked together (an error naming each run's holdout)."""
    from offline_adp.data.files import read_json_file
    from offline_adp.data.holdout import recorded_fraction

    held: dict[Path, tuple[float, Any, Any]] = {}
    for r in runs:
        rec = read_json_file(r / "run.json").get("holdout")
        frac = recorded_fraction(rec, str(r / "run.json"))
        held[r] = (frac, rec.get("seed") if frac else None, rec.get("ids_sha256") if frac else None)
    if len({h[2] for h in held.values()}) > 1:
        each = "; ".join(f"{r.name}: " + (f"--holdout {f:g} with random_state {s}" if f else "no holdout")
                         for r, (f, s, _) in held.items())
        raise IncompatibleError(f"the candidates would be read on different episodes of their logs ({each}): each "
                                "is evaluated on the episodes its fit held out, or on all. Fit them with the same "
                                "--holdout and random_state (or none), or compare them on other logs with --dataset "
                                "DIR (read whole)")


def _common_dataset(runs: list[Path]) -> str:
    """The dataset every run was fitted on (an error when a run names none, or they name different logs,
    or each would be read on other episodes of it: :func:`_check_same_held_out`)."""
    paths = {str(Path(p).resolve()) if p else "" for p in (_dataset_of(r) for r in runs)}
    if "" in paths:
        raise RunDirectoryError("a run does not name its dataset; pass --dataset DIR")
    fps = {_fingerprint(p) for p in paths}
    if len(fps) > 1:
        raise IncompatibleError(f"the runs were fitted on different logs ({len(fps)} datasets); compare them on "
                              "one with --dataset DIR")
    _check_same_held_out(runs)
    return sorted(paths)[0]


def _logs_of(m: dict[str, Any]) -> Any:
    """The fingerprint of the dataset an evaluation read: of the whole one where it read the
    episodes a fit held out (evaluation/logs.py)."""
    logs = m.get("logs") or {}
    held = logs.get("kind") == "held_out"
    return logs.get("dataset_fingerprint") if held else m.get("dataset", {}).get("fingerprint")


def _why_again(m: dict[str, Any] | None, fp: str, simulator: str | None, particles: int) -> str:
    """Why a candidate is evaluated again, and that its stored evaluation is replaced."""
    if m is None:
        return ""
    if _logs_of(m) != fp:
        why = "it was evaluated on other logs"
    elif simulator is not None and (m.get("simulator") or "none") != simulator:
        why = f"it was evaluated with simulator {m.get('simulator') or 'none'!r}, not {simulator!r}"
    else:
        why = f"its evaluation's model rollouts are not this one's ({particles} particles with the current bounds)"
    return f" ({why}: its evaluation/ is replaced)"


def _candidate_metrics(runs: list[Path], ds_path: str, fp: str, cfg: EvaluationSettings, force: bool,
                       say: Callable[[str], None]) -> list[dict[str, Any]]:
    """Every candidate's evaluation on the dataset: the stored one when it matches (dataset,
    simulator, model rollouts) and ``force`` is off, else a new one; all of one estimand."""
    from offline_adp.evaluation.run import evaluate_run

    simulator = cfg.simulator
    metrics = []
    for r in runs:
        m = None if force else _metrics(r)  # --force: a corrupt old evaluation is simply replaced
        same = (m is not None and _logs_of(m) == fp
                and (simulator is None or (m.get("simulator") or "none") == simulator)
                and _same_model_rollouts(m, cfg.model_particles))
        if force or not same:
            stored = (r / "evaluation" / "metrics.json").is_file()
            say(f"evaluating {r}" + (" (--force: its evaluation/ is replaced)" if force and stored
                                     else _why_again(m, fp, simulator, cfg.model_particles)))
            m = json.loads(json.dumps(evaluate_run(r, cfg, dataset=ds_path, progress=say), default=float))
            m = _metrics(r) or m
        metrics.append(m)
    read = {(m.get("dataset") or {}).get("fingerprint") for m in metrics}
    if len(read) > 1:  # e.g. one fitted with --holdout (read on its held-out episodes), one without (on all)
        words = sorted({str((m.get("logs") or {}).get("description", "the logs whole")) for m in metrics})
        raise IncompatibleError(f"the candidates were evaluated on different episodes of {ds_path} "
                                f"({'; '.join(words)}): fit them with the same --holdout and random_state (or "
                                "none) to compare them")
    estimands = {json.dumps({k: m.get("estimand", {}).get(k) for k in ("form", "horizon", "gamma")}) for m in metrics}
    if len(estimands) > 1:
        raise IncompatibleError("the candidates' evaluations target different quantities (horizon or discount differ); "
                              "re-run with the same --horizon, or pass force")
    return metrics


def _common_estimator(rankings: list[list[dict[str, Any]]]) -> str | None:
    """The most reliable estimator reliable (with an interval) for every candidate, else usable
    for every candidate (no interval); None when there is none."""
    # an estimator promoted on one candidate's own weights (summary.rank_estimators: on_policy) leads the
    # choice only where every candidate promotes it; else the shared ones go by the plain order
    promoted = {x["name"] for rk in rankings for x in rk if x.get("on_policy")}
    everywhere = {n for n in promoted if all(any(x["name"] == n and x.get("on_policy") for x in rk) for rk in rankings)}
    first = [{**e, "on_policy": e["name"] in everywhere} for e in rankings[0]]
    order = estimator_order(first)
    for max_tier in (0, 1):
        common = [e for e in first if e["tier"] <= max_tier
                  and all(any(x["name"] == e["name"] and x["tier"] <= max_tier for x in rk) for rk in rankings)]
        if common:
            return min(common, key=lambda e: (e["tier"], order.get(e["name"], len(order)), e["name"]))["name"]
    return None


def _candidate_row(r: Path, m: dict[str, Any], rk: list[dict[str, Any]], estimator: str | None) -> dict[str, Any]:
    """One candidate's row of the comparison: its estimate by ``estimator`` (None: its own most
    reliable), interval, verdicts and the simulator's truth."""
    pick = next((e for e in rk if e["name"] == estimator), None) if estimator else next(
        (e for e in rk if e["tier"] <= 1), None)
    h = m.get("headline")
    if not h or "outcome" not in h:  # written before the outcome word
        h = headline(m, r)
    truth = m.get("rollout", {}).get("policy", {}).get("mean_discounted_cost")
    shown = (pick["interval"] or pick.get("shown_interval")) if pick else None
    fit = h["convergence"].get("verdict")
    return {"run": str(r), "name": r.name if r.name != "fit" else r.parent.name,
            "algorithm": m.get("algorithm"), "estimator": pick["name"] if pick else None,
            "estimate": pick["estimate"] if pick else None, "interval": shown,
            "level": pick["level"] if pick and pick["interval"] else None,
            "level_words": level_words(pick) if shown else None,
            "reliability": pick["tier_label"] if pick else "no reliable estimate",
            "outcome": h["verdict"].get("outcome") or outcome_of(h["verdict"].get("performance"), fit),
            "fit": _FIT_WORDS.get(fit, fit or "unknown"),
            "discount_note": h.get("discount_note") or discount_note(m),
            "shift": h["shift"]["text"], "support_left": h["verdict"].get("support_left"),
            "convergence": h["convergence"]["text"], "truth": truth,
            "truth_interval": m.get("rollout", {}).get("policy", {}).get("interval"),
            "verdict": h["verdict"].get("text"), "verdict_lines": h["verdict"].get("lines"),
            "performance": h["verdict"].get("performance"),
            "fit_verdict": h["convergence"].get("verdict"), "cost_distribution": _risk(m)}


def _top_pick_and_truth(out: dict[str, Any], usable: list[dict[str, Any]], first: dict[str, Any]) -> None:
    """Into ``out``: the separation of the candidates, the top pick (only when it is separated
    from every other), the demonstrator's rollouts and, with every truth known, the selection scores."""
    out["separation"] = separation(usable)
    top = usable[0] if usable else None
    if top is not None and all(p["separated"] for p in out["separation"] if top["name"] in (p["a"], p["b"])):
        out["top_pick"] = top["name"]
    else:
        out["top_pick"] = None
        out["cannot_separate"] = [p["text"] for p in out["separation"]
                                  if not p["separated"] and top is not None and top["name"] in (p["a"], p["b"])]
    demo = (first.get("rollout") or {}).get("demonstrator")
    if isinstance(demo, dict) and demo.get("mean_discounted_cost") is not None:
        out["demonstrator"] = {"mean": demo["mean_discounted_cost"], "interval": demo.get("interval"),
                               "failures": demo.get("failures"), "simulator": first.get("simulator"),
                               "n_episodes": demo.get("n_episodes")}
    if len(usable) >= 2 and all(x["truth"] is not None for x in usable):
        out["selection"] = selection_scores([x["estimate"] for x in usable], [x["truth"] for x in usable])


#: How the comparison words a fit's verdict in its convergence column.
_FIT_WORDS = {"converged": "converged", "still changing": "did NOT converge", "not converged": "did NOT converge",
              "diverging": "DIVERGED", "diverged": "DIVERGED", "finite horizon": "finite horizon (exact)",
              "completed": "completed"}


def separation(cands: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Can the logs tell the candidates apart? Pairwise, from their intervals: two candidates
    are separated only when both intervals have a level and do not overlap (for two
    independent 95% intervals a conservative test of the difference); an interval without a
    level, or none, separates nothing. One entry per pair, in rank order, with its words."""
    out = []
    for i, a in enumerate(cands):
        for b in cands[i + 1:]:
            ia, ib = a.get("interval"), b.get("interval")
            both = bool(ia and ib and a.get("level") is not None and b.get("level") is not None)
            sep = both and (ia[1] < ib[0] or ib[1] < ia[0])
            if sep:
                text = (f"the logs separate {a['name']} from {b['name']}: their {a['level']:.0%} intervals "
                        f"[{ia[0]:.4g}, {ia[1]:.4g}] and [{ib[0]:.4g}, {ib[1]:.4g}] do not overlap")
            elif both:
                text = (f"the logs cannot separate {a['name']} and {b['name']}: their intervals [{ia[0]:.4g}, "
                        f"{ia[1]:.4g}] and [{ib[0]:.4g}, {ib[1]:.4g}] overlap")
            else:
                missing = [c["name"] for c in (a, b) if not (c.get("interval") and c.get("level") is not None)]
                text = (f"the logs cannot separate {a['name']} and {b['name']}: {' and '.join(missing)} "
                        f"{'has' if len(missing) == 1 else 'have'} no interval with a level")
            out.append({"a": a["name"], "b": b["name"], "separated": bool(sep), "text": text,
                        "method": "overlap of the candidates' intervals (both with a level)"})
    return out


def _risk(m: dict[str, Any]) -> dict[str, Any] | None:
    """A candidate's episode-cost distributions from its metrics: the simulator's (measured)
    and the logs' (importance-weighted, or why it cannot tell)."""
    cd = m.get("cost_distribution")
    if not cd:
        return None
    return {"alpha": cd.get("alpha"), "rollouts": cd.get("policy_rollouts"), "logs": cd.get("policy_logs")}


def selection_scores(estimated: Sequence[float], truth: Sequence[float]) -> dict[str, Any]:
    """Spearman's rho and Kendall's tau between estimated and true costs, and the regret of
    the top pick (the candidate with the lowest estimated cost) by the truth."""
    from scipy.stats import kendalltau, spearmanr

    e, t = np.asarray(estimated, dtype=float), np.asarray(truth, dtype=float)
    top = int(np.argmin(e))
    spread = float(t.max() - t.min())
    regret = float(t[top] - t.min())
    return {"spearman": float(spearmanr(e, t).statistic), "kendall": float(kendalltau(e, t).statistic),
            "regret_top1": regret, "relative_regret_top1": regret / spread if spread > 0 else 0.0,
            "top_pick_is_best": bool(regret <= 0.0), "n_candidates": int(len(e)),
            "method": "simulator rollouts of every candidate (same start states and seeds) as the truth"}


def compare_lines(res: dict[str, Any]) -> list[str]:
    """A table of the ranking for the terminal."""
    lines = [f"candidates on {res['dataset']['path']} ranked by {res['estimator'].upper()} "
             f"({res['estimand']}; lower cost is better)"]
    if res.get("note"):
        lines.append(res["note"])
    if res.get("top_pick"):
        lines.append(f"top pick: {res['top_pick']} (the logs separate it from every other candidate)")
    elif "top_pick" in res:
        lines.append("no top pick: " + "; ".join(res.get("cannot_separate") or ["no candidate has an estimate"]))
    d = res.get("demonstrator")
    if d:
        lines.append(f"demonstrator ({d.get('simulator')} simulator): {_f(d['mean'])}"
                     + (f", failures {d['failures']}" if d.get("failures") is not None else ""))
    lines.append(f"{'rank':>4}  {'candidate':24s} {'estimate':>9s}  {'interval (level)':32s} {'truth':>8s}  "
                 f"{'verdict':13s} {'fit':16s} shift / support")
    for c in res["candidates"]:
        iv = c["interval"]
        ivs = f"[{_f(iv[0])}, {_f(iv[1])}] ({c.get('level_words') or 'no level'})" if iv else "none"
        est = _f(c["estimate"]) if c["estimate"] is not None else "n/a"
        tr = _f(c["truth"]) if c["truth"] is not None else "-"
        sup = "LEFT support" if c["support_left"] else "in support"
        lines.append(f"{c['rank'] if c['rank'] else '-':>4}  {c['name'][:24]:24s} {est:>9s}  {ivs:32s} {tr:>8s}  "
                     f"{c.get('outcome') or '?':13s} {c.get('fit') or '?':16s} {sup}; {c['shift']}")
    for c in res["candidates"]:
        if c.get("discount_note"):
            lines.append(f"{c['name']}: {c['discount_note']}")
    s = res.get("selection")
    if s:
        who = "the top pick" if res.get("top_pick") else "the lowest estimate (not a pick)"
        lines.append(f"against the simulator: Spearman {s['spearman']:.2f}, Kendall {s['kendall']:.2f}; "
                     f"regret of {who} {s['regret_top1']:.3f} ({s['relative_regret_top1']:.0%} of the candidates' "
                     "spread)")
    return lines


def cli(args: Any) -> int:
    """``offline-adp compare`` (arguments parsed in :mod:`offline_adp.cli`)."""
    import logging

    def say(msg: str) -> None:  # an INFO record of the CLI logger: -q hides it
        logging.getLogger("offline_adp.cli").info("  %s", msg)

    if args.json and Path(args.json).is_dir():  # before the work, not after it
        raise WriteError(f"--json {args.json} is a directory; name a file to write (e.g. "
                         f"{Path(args.json) / 'compare.json'})")
    report = report_path(args.runs, args.json, getattr(args, "report", None))
    if report.is_dir():
        raise WriteError(f"--report {report} is a directory; name a file to write (e.g. {report / 'compare.html'})")
    res = compare_runs(args.runs, dataset=args.dataset, estimator=args.estimator, force=args.force,
                       settings=EvaluationSettings.of_arguments(args), progress=say)
    for line in compare_lines(res):
        print(line)
    from offline_adp.evaluation.run import json_safe

    if args.json:
        from offline_adp.data.files import atomic_write_text

        atomic_write_text(args.json, json.dumps(json_safe(res), indent=1, default=float, allow_nan=False),
                          what="comparison")
        print(args.json)
    from offline_adp.evaluation.compare_report import write_compare_report

    print(write_compare_report(json_safe(res), report))
    return 0


def report_path(runs: Sequence[str | PathLike[str]], json_path: str | None, report: str | None) -> Path:
    """Where ``compare`` writes its HTML report: ``report`` when given; else next to the
    ``--json`` file (its name with ``.html``); else ``compare.html`` in the run directories'
    common parent (the current directory when they share none)."""
    if report:
        return Path(report)
    if json_path:
        p = Path(json_path)
        return p.with_suffix(".html") if p.suffix != ".html" else p.with_name(p.name + ".html")
    import os

    try:
        parent = Path(os.path.commonpath([str(Path(r).resolve().parent) for r in runs]))
    except ValueError:  # different drives
        parent = Path(".")
    return (parent if parent != Path(parent.anchor) else Path(".")) / "compare.html"
