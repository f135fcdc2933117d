"""``offline-adp report RUN_DIR``: one self-contained ``report.html`` (figures embedded) plus
the figures as PNG files in ``RUN_DIR/report/figures/``.

Reads ``RUN_DIR/evaluation/`` (run ``offline-adp evaluate`` first) and the fitted model.
"""

from __future__ import annotations

import base64
import html
import json
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from offline_adp.data.files import read_table_file
from offline_adp.data.io import read_info
from offline_adp.envs import PROBLEM_NAMES, problem_class
from offline_adp.errors import ArtifactError, RunDirectoryError
from offline_adp.evaluation.figures import (
    DISTRIBUTIONS,
    UNITS,
    Figures,
    command_figures,
    convergence_figure,
    cost_distribution_figure,
    coverage_figure,
    ope_figure,
    policy_maps,
    ratios_figure,
    sources_figure,
    traced_figure,
)

# the building blocks of every report (LABELS, fmt, STYLE, verdict_colour: importable from here too)
from offline_adp.evaluation.html_blocks import (  # noqa: F401
    LABELS,
    STYLE,
    details_html,
    figure_html,
    fmt,
    page,
    table_html,
    verdict_colour,
    verdict_html,
    warning_items,
)
from offline_adp.evaluation.verdict import behaviour_words


def _title(run: Path, m: dict[str, Any]) -> str:
    """The pipeline's name (run/../config.json or manifest.json), else the run directory's."""
    for folder in (run, run.parent):
        for name in ("manifest.json", "config.json"):
            try:
                cfg = json.loads((folder / name).read_text())
            except (OSError, ValueError):
                continue
            if isinstance(cfg, dict) and isinstance(cfg.get("name"), str):
                desc = cfg.get("description")
                return cfg["name"] + (f": {desc}" if isinstance(desc, str) and desc else "")
    return run.resolve().name if run.name != "fit" else run.resolve().parent.name


def build_report(run_dir: str | PathLike[str]) -> Path:
    """Write ``RUN_DIR/report/report.html`` and ``report/figures/*.png``; returns the HTML path."""
    run = Path(run_dir)
    ev = run / "evaluation"
    if not (ev / "metrics.json").exists():
        from offline_adp.data.rundir import pipeline_hint

        hint = pipeline_hint(run)
        raise RunDirectoryError(f"{run}: no evaluation/metrics.json" + (hint or f"; run `offline-adp evaluate {run}` "
                                                                                 "first"))
    from offline_adp.evaluation.metrics_file import ReportMetricsFile, read_metrics

    m = read_metrics(ev / "metrics.json", ReportMetricsFile)
    ratios = read_table_file(ev / "ratios.parquet")
    features = [c for c in ratios.columns if c not in ("step", "source", "w", "w_classifier", "w_pooled")]
    problem = m.get("simulator") or ""
    ds_path = (m.get("dataset") or {}).get("path") if isinstance(m.get("dataset"), dict) else None
    if not isinstance(ds_path, str):
        raise ArtifactError(f"{ev / 'metrics.json'}: no dataset.path; run `offline-adp evaluate {run}` again")
    info_path = Path(ds_path) / "meta" / "info.json"
    units = dict(UNITS)
    actions: dict[str, Any] = {}
    if info_path.exists():
        info = read_info(info_path.parent.parent)
        # never blank a fallback
        units.update({f["name"]: f["unit"] for f in info.get("features", []) if f.get("unit")})
        problem = problem or info.get("problem") or ""
        from offline_adp.data.info import DatasetInfo

        table = DatasetInfo.from_dict(info, where=str(info_path)).action_table
        dims = list(getattr(table, "dims", []) or [])
        aunits = list(getattr(table, "units", []) or [])
        names = table.names() if callable(table.names) else table.names
        actions = {"values": table.values[:, 0], "names": [str(n) for n in names] or None, "table": table,
                   "label": (dims[0] if dims else "action") + (f" [{aunits[0]}]" if aunits and aunits[0] else "")}
        units.setdefault("cost", "")
    cls = problem_class(problem) if problem in PROBLEM_NAMES else None  # problem-specific: the ReferenceProblem's hooks
    axes = getattr(cls, "map_features", None) or (tuple(features[:2]) if len(features) >= 2 else None)
    from offline_adp.data.files import atomic_directory
    from offline_adp.data.rundir import RunDirectory

    # a writer of the run directory: under its lock (a concurrent evaluate or report fails at once)
    with RunDirectory(run).lock(), atomic_directory(run / "report", overwrite=True) as tmp:
        _build(run, m, ratios, features, axes, units, actions, problem, tmp)
    return run / "report" / "report.html"


def _build(run: Path, m: dict[str, Any], ratios: pd.DataFrame, features: list[str], axes: Any, units: dict[str, str],
           actions: dict[str, Any], problem: str, tmp: Path) -> None:
    from offline_adp.evaluation.summary import headline

    h = headline(m, run)
    figs = Figures(tmp / "figures")
    ope_figure(figs, m, h["ranking"])
    if m.get("shift"):  # none for a continuous policy (evaluation/continuous.py)
        ratios_figure(figs, m, h["shift"]["method"])
    if "commands" in m and actions.get("table") is not None:  # a continuous policy: one map per command component
        _command_figures(figs, run, m, ratios, features, axes, units, actions["table"])
    elif axes is not None and all(a in features for a in axes):
        vals = actions.get("values")
        policy_maps(figs, run, ratios, features, axes, units, vals if vals is not None else np.arange(100.0),
              actions.get("names"), actions.get("label", "action"))
        coverage_figure(figs, run, ratios, features, axes, units)
    convergence_figure(figs, run)
    if "per_source" in m:  # both from the density ratios (not for a continuous policy)
        cost_distribution_figure(figs, m)
        sources_figure(figs, m)
    cls = problem_class(problem) if problem in PROBLEM_NAMES else None
    if cls is not None and cls.traced_features:
        traced_figure(figs, run, features, cls.traced_features, cls.dt, problem)
    csv = (run / "evaluation" / "per_step.csv").read_bytes() if (run / "evaluation" / "per_step.csv").exists() else b""
    (tmp / "report.html").write_text(_html(m, h, figs, _title(run, m), csv))


def _command_figures(figs: Figures, run: Path, m: dict[str, Any], ratios: pd.DataFrame, features: list[str], axes: Any,
                     units: dict[str, str], table: Any) -> None:
    """A continuous policy's maps and command distributions (:func:`command_figures`)."""
    from offline_adp.artifacts import load_index_policy
    from offline_adp.data.dataset import TransitionDataset
    from offline_adp.policies import PolicySignature

    policy = load_index_policy(run / "model")
    policy.signature = PolicySignature(tuple(features), tuple(units.get(f, "") for f in features), table)
    ds_path = (m.get("dataset") or {}).get("path")
    logged = None
    if isinstance(ds_path, str) and (Path(ds_path) / "meta" / "info.json").exists():
        ds = TransitionDataset.load(ds_path)
        logs = m.get("logs") or {}
        held = logs.get("kind") == "held_out"  # read on the episodes the fit held out
        fp = logs.get("dataset_fingerprint") if held else (m.get("dataset") or {}).get("fingerprint")
        if ds.matches_fingerprint(fp):
            if held:
                from offline_adp.data.files import read_json_file
                from offline_adp.data.holdout import held_out_episodes

                ds = held_out_episodes(ds, read_json_file(run / "run.json").get("holdout"), str(run / "run.json"))
            logged = ds.commands()  # the logs the evaluation read
    command_figures(figs, policy, ratios, features, axes, units, table, logged)


def psdp_rows(m: dict[str, Any]) -> list[dict[str, Any]]:
    """The PSDP bound per reference policy with the two factors it multiplies, as
    :func:`offline_adp.evaluation.psdp_eps.psdp_bound` uses them: ``sum_t eps_t`` (the
    cross-fitted eps) and the ratio recursion's per-step upper bounds ``UCB_t`` of the
    supported sup (their max and where), and the pooled one of the averaged form."""
    b = m["psdp_bound"]
    eps = np.asarray([np.nan if e is None else e for e in b.get("eps") or []], dtype=np.float64)
    rows = []
    for ref, v in b["references"].items():
        block = m.get("shift", {}).get("recursion" if ref == "self" else f"reference:{ref}", {})
        ucb = pd.DataFrame(block.get("per_step") or [])
        r_max, r_step = v.get("ratio_ucb_max"), v.get("ratio_ucb_step")
        if r_max is None and "sup_ucb" in ucb and len(ucb):  # metrics written before the bound stored its factors
            i = ucb["sup_ucb"].idxmax()
            r_max, r_step = float(ucb.loc[i, "sup_ucb"]), int(ucb.loc[i, "step"])
        eps_sum = v.get("eps_sum", float(eps.sum()) if len(eps) and np.isfinite(eps).all() else None)
        rows.append({"reference": "the policy itself" if ref == "self" else ref, "eps_sum": eps_sum,
                     "ratio_ucb_max": None if r_max is None else f"{r_max:.4g} (t = {r_step})",
                     "pooled_ratio_ucb": v.get("pooled_ratio_ucb"), "per_step": v.get("per_step"),
                     "averaged": v.get("averaged"),
                     "method": "ratio recursion (logs only)" if v.get("method", "recursion") == "recursion"
                     else v.get("method")})
    return rows


PSDP_LABELS = {"eps_sum": "sum_t eps_t", "ratio_ucb_max": "max_t UCB_t(sup ratio)",
               "pooled_ratio_ucb": "UCB(sup pooled ratio)", "per_step": "estimate: sum_t eps_t UCB_t",
               "averaged": "estimate: T mean(eps) UCB(pooled)", "method": "ratios from"}


def psdp_section(m: dict[str, Any], h: dict[str, Any]) -> list[str]:
    """The PSDP bound's table and what it rests on, said where a better diagnostic disagrees."""
    b = m["psdp_bound"]
    eps_how = b.get("eps_method") or "in sample"
    text = (f"<p>{html.escape(b['label'])} of the bound J(pi) &minus; J(pi_ref) &le; &sum;<sub>t</sub> eps_t "
            "&middot; UCB_t(sup mu_ref^t / mu^t), with mu^t the data's distribution. Both factors are estimated "
            "from the logs, so the number is an estimate of the bound, <b>not a bound</b>: it has fallen below the "
            "true gap (a linear-regression candidate on path_tracking: 18.7 against a true gap of 29.7). "
            f"eps_t: {html.escape(eps_how)}. The ratios are the logs-only recursion's (the same for every reference "
            "policy), per step the bootstrap 95% upper bound of the largest region mean; the averaged form uses "
            "the ratio of the time-summed distributions.</p>")
    sh = h.get("shift", {})
    if sh.get("method") == "classifier" and (sh.get("separable_steps") or h["verdict"].get("support_left")):
        text += ("<p><b>The ratios this bound multiplies are optimistic here</b>: the logs-only recursion shrinks them "
                 "towards 1 where a step has few states, while the classifier (simulator) finds the policy's states "
                 f"almost separable from the data's at {sh.get('separable_steps', 0)} of {sh.get('n_steps', '?')} "
                 "steps, so the true sup ratio, and the bound, are larger than shown.</p>")
    elif sh.get("method") in ("pooled", "none"):
        text += ("<p><b>The per-step ratios this bound multiplies are optimistic here</b>: too few states per step "
                 "for the recursion, which shrinks them towards 1.</p>")
    cols = ["reference", "eps_sum", "ratio_ucb_max", "per_step", "pooled_ratio_ucb", "averaged", "method"]
    return ["<h2>PSDP performance bound: an estimate, not a bound</h2>", text,
            table_html(psdp_rows(m), cols, labels=PSDP_LABELS)]


def distribution_rows(cd: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per distribution of ``cost_distribution`` (unusable ones with the reason)."""
    rows = []
    for key, label in DISTRIBUTIONS.items():
        d = cd.get(key)
        if d is None:
            continue
        if d.get("usable") is False:
            rows.append({"distribution": label, "note": "cannot tell from these logs: " + d.get("reason", "")})
            continue
        n = d.get("n_episodes")
        ess = d.get("ess")
        eps = f"{n}" if ess is None or abs(ess - n) < 0.5 else f"{n} (effective {ess:.1f})"
        rows.append({"distribution": label, "episodes": eps, "mean": d.get("mean"), "median": d.get("median"),
                     "q90": d.get("q90"), "cvar": d.get("cvar"), "max": d.get("max"), "note": d.get("method", "")})
    return rows


def cost_distribution_section(m: dict[str, Any]) -> list[str]:
    """The table of episode-cost distributions with mean and CVaR."""
    cd = m.get("cost_distribution")
    if not cd:
        return []
    a = cd.get("alpha", 0.1)
    labels = {"cvar": f"CVaR_{a:g} (worst {a:.0%})", "q90": "90% quantile", "median": "median", "max": "worst episode",
              "mean": "mean", "note": "how", "distribution": "distribution"}
    return ["<h2>Cost distribution and CVaR</h2>",
            f"<p>Episode costs (each episode's sum_t gamma^t c_t, the estimand per episode) beside their mean: "
            f"CVaR_{a:g} is the mean of the worst {a:.0%} of episodes (costs are minimised: the highest costs). "
            "From the logs alone, the policy's distribution is the logged episodes re-weighted by their importance "
            "weights, given only where those weights are usable.</p>",
            table_html(distribution_rows(cd), ["distribution", "episodes", "mean", "median", "q90", "cvar", "max",
                                               "note"],
                       labels=labels)]


def risk_text(cd: dict[str, Any]) -> str:
    """One line: mean and CVaR of each distribution, and the policy's from the logs or why not."""
    a = cd.get("alpha", 0.1)
    out = []
    for key, label in DISTRIBUTIONS.items():
        d = cd.get(key)
        if d is None:
            continue
        if d.get("usable") is False:
            if key == "policy_logs":
                out.append(f"{label}: cannot tell from these logs ({d.get('reason', '').split('; ')[0]}; see below)")
            continue
        out.append(f"{label} mean {d['mean']:.4g}, CVaR_{a:g} {d['cvar']:.4g}")
    return "; ".join(out)


def _summary_box(m: dict[str, Any], h: dict[str, Any]) -> str:
    from offline_adp.evaluation.summary import level_words, model_reading

    v, b, sh, cv = h["verdict"], h["best"], h["shift"], h["convergence"]
    rows = [verdict_html(v, cv), "<table class='kv'>"]

    def kv(k: str, val: str) -> None:
        rows.append(f"<tr><th>{html.escape(k)}</th><td>{val}</td></tr>")

    est = m.get("estimand", {})
    kv("Estimand", html.escape(est.get("quantity", f"expected discounted cost over {m.get('horizon')} steps")) +
       " (lower is better)")
    if b is not None:
        lo, hi = b["interval"]
        caveat = "" if lo <= b["estimate"] <= hi else (" &mdash; <b>the interval excludes the estimate</b>: its "
                                                       "bootstrap replicates are shifted, treat the interval as "
                                                       "unreliable")
        corrected = (f"; bias-corrected by the bootstrap (plug-in estimate {b['plugin_estimate']:.4g}, its replicates "
                     "shifted away from it)" if b.get("plugin_estimate") is not None else "")
        x = model_reading(m, b["name"])
        model = "" if x is None else f"; model rollouts of the logs read {x:.4g} (a second reading the interval holds)"
        kv("Best estimate", f"<b>{b['estimate']:.4g}</b> [{lo:.4g}, {hi:.4g}] ({level_words(b)}), "
           f"{html.escape(b['label'])}, the most reliable estimator here{corrected}{caveat}{model}")
    else:
        top = next((e for e in h["ranking"] if e["tier"] == 1), None)
        if top is not None and top.get("shown_interval"):
            lo, hi = top["shown_interval"]
            x = model_reading(m, top["name"])
            model = "" if x is None else f"; model rollouts of the logs read {x:.4g}"
            kv("Best estimate", f"<b>{top['estimate']:.4g}</b> [{lo:.4g}, {hi:.4g}] (no level), "
               f"{html.escape(top['label'])}: " + html.escape(top.get("level_note") or "its coverage was not measured")
               + model)
        else:
            kv("Best estimate", f"{top['estimate']:.4g} ({html.escape(top['label'])}) without an interval: "
               f"{html.escape(top['reason'])}" if top else "none: no estimator is usable on these logs (see below)")
    if "rollout" in m:
        p, d = m["rollout"]["policy"], m["rollout"].get("demonstrator")
        vs = " (no demonstrator to compare with)" if d is None else f" vs demonstrator {d['mean_discounted_cost']:.4g}"
        kv("Simulator truth",
           f"policy {p['mean_discounted_cost']:.4g} [{p['interval'][0]:.4g}, {p['interval'][1]:.4g}]{vs} "
           f"({html.escape(str(m.get('simulator')))}, {p['n_episodes']} episodes)")
    else:
        kv("Simulator", html.escape(m.get("simulator_note") or "none used"))
    bv = m.get("behaviour_value")
    if bv:
        kv("Behaviour (logged)", html.escape(behaviour_words(bv)))
    cd = m.get("cost_distribution")
    if cd:
        kv("Cost distribution", html.escape(risk_text(cd)))
    logs = m.get("logs") or {}
    if isinstance(logs.get("description"), str):  # which episodes were read (in sample: the verdict's note says so)
        kv("Logs", html.escape(logs["description"]))
    kv("Distribution shift", html.escape(sh["text"]))
    kv("Fit", html.escape(cv["text"]))
    if h.get("discount_note"):
        kv("Discount", "<b>" + html.escape(h["discount_note"][:1].upper() + h["discount_note"][1:]) + "</b>")
    kv("Warnings", f"{h['n_warnings']} (gathered with their sources under <a href='#warnings'>Evaluation warnings</a> "
       "and in metrics.json's <code>warnings</code>)")
    rows.append("</table>")
    return "<section class='summary'><h2>Summary</h2>" + "".join(rows) + "</section>"


def _vector(v: Any) -> str:
    """A command bound vector at the report's 4 significant digits (unbounded: a dash)."""
    return "[" + ", ".join(fmt(None if x is None else float(x)) for x in v) + "]"


def _continuous_sections(m: dict[str, Any]) -> list[str]:
    """The sections of a continuous policy's report after its estimates: the command
    support, what was not computed and why, the warnings."""
    sv = m["behaviour"]["support_violations"]
    cmd = m["commands"]
    comps = ", ".join(f"{d} [{u}]" if u else d for d, u in zip(cmd["dims"], [*cmd["units"], *[""] * len(cmd["dims"])],
                                                                strict=False))
    parts = ["<h2>Command support</h2>",
             f"<p>Commands: {html.escape(comps)}, bounds {_vector(cmd['low'])} to "
             f"{_vector(cmd['high'])}. The policy commands farther from the commands logged near the state "
             f"than the logged commands themselves are at {sv['fraction']:.1%} of the logged states "
             f"({html.escape(sv['method'])}).</p>",
             "<h2>Not computed for continuous commands</h2>",
             "<ul>" + "".join(f"<li><b>{html.escape(k)}</b>: {html.escape(v)}</li>" for k, v in m["not_usable"].items())
             + "</ul>"]
    if m.get("warnings"):
        parts += ["<h2 id='warnings'>Evaluation warnings</h2>", "<ul>" + warning_items(m["warnings"]) + "</ul>"]
    return parts


def _html(m: dict[str, Any], h: dict[str, Any], figs: Figures, title: str, csv: bytes) -> str:
    """The run report's page: title, summary box, figures, the estimates most reliable first,
    then (discrete actions) the shift diagnostics, the PSDP bound, the cost distributions, the
    sources and the warnings; a continuous policy's own sections instead (:func:`_continuous_sections`)."""
    ds = m["dataset"]
    src = ", ".join(f"{k}: {v:,} transitions" if isinstance(v, int) else f"{k}: {v}"
                    for k, v in (ds.get("sources") or {}).items())
    kind = (m.get("logs") or {}).get("kind")  # the logs read: the fit's own (or unknown), held out, or others
    read = {"held_out": f"the {ds['episodes']} episodes its fit held out", "other": f"{ds['episodes']} episodes of "
            "other logs than its fit's"}.get(kind, f"{ds['episodes']} episodes")
    parts = [f"<h1>{html.escape(title)}</h1>",
             f"<p class='sub'>Policy fitted by {html.escape(str(m.get('algorithm') or 'unknown').upper())}, "
             f"{'evaluated' if kind in ('held_out', 'other') else 'fitted and evaluated'} on {ds['transitions']:,} "
             f"transitions in {read} ({html.escape(src)}). Costs are minimised: lower is better.</p>",
             _summary_box(m, h), "<h2>Figures</h2>"]
    parts += figure_html(figs)
    good, bad, cols = _estimate_rows(m, h)
    parts += ["<h2>Off-policy estimates, most reliable first</h2>",
              "<p>Every estimator targets the estimand above. Reliable: a finite estimate inside the possible range "
              "with an interval that has a level (printed beside it). An interval marked <i>no level</i> is shown, "
              "never quoted: its coverage was not measured, or the policy left the data's support where the value "
              "model extrapolates; a withheld interval (a dash) would not cover as labelled.</p>",
              table_html(good, cols, "ope")]
    if "commands" in m:  # a continuous policy (evaluation/continuous.py): what ran and what could not
        return page(title, parts + _continuous_sections(m))
    if bad:
        parts.append(details_html(f"{len(bad)} estimators not usable on these logs: "
                              + html.escape(", ".join(b["estimator"].split(" ")[0] for b in bad)) + " (why)",
                              "<p>Their weights are degenerate, or their estimate is impossible for this cost, or they "
                              "target another quantity. They are never quoted as support.</p>"
                              + table_html(bad, ["estimator", "estimate", "reason", "warnings"])))
    parts += _shift_section(m, h, csv)
    parts += psdp_section(m, h)
    parts += cost_distribution_section(m)
    parts += ["<h2>Per source</h2>", table_html([{"source": k, **v} for k, v in m["per_source"].items()],
                                          ["source", "episodes", "transitions", "logged_mean_discounted_cost",
                                           "data_mass",
                                           "policy_mass", "mean_ratio"])]
    if m.get("warnings"):
        parts += ["<h2 id='warnings'>Evaluation warnings</h2>", "<ul>" + warning_items(m["warnings"]) + "</ul>"]

    return page(title, parts)


def _estimate_rows(m: dict[str, Any], h: dict[str, Any]
                   ) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[str]]:
    """``(usable rows, unusable rows, columns)`` of the estimates table: estimators ranked by
    reliability; the unusable ones (collapsed in the report) with the reason."""
    rk = h["ranking"]
    ope = m["ope"]

    from offline_adp.evaluation.summary import level_words

    def row(e: dict[str, Any]) -> dict[str, Any]:
        r = ope[e["name"]]
        iv = e["interval"] or e.get("shown_interval")
        shown = f"[{iv[0]:.4g}, {iv[1]:.4g}] ({level_words(e)})" if iv else None
        return {"rank": e["rank"], "estimator": e["label"], "estimate": e["estimate"], "interval": shown,
                "interval_method": r.get("interval_method"),
                "ess": r.get("ess") if e["name"] not in ("fqe", "model") else None,  # weights' ESS: IS-based only
                "rollout_error": r.get("rollout_error"),
                "reason": e["reason"] or "", "warnings": r.get("warnings") or []}

    cols = ["rank", "estimator", "estimate", "interval", "interval_method", "ess"] + \
        (["rollout_error"] if "rollout" in m else []) + ["warnings"]
    good = [row(e) for e in rk if e["tier"] < 2]
    bad = [row(e) for e in rk if e["tier"] == 2]
    return good, bad, cols


def _shift_section(m: dict[str, Any], h: dict[str, Any], csv: bytes) -> list[str]:
    """The distribution shift: the headline's shift, the behaviour probabilities and action
    support, and each ratio method's per-step table (collapsed; ``csv`` linked as per_step.csv)."""
    beh = m["behaviour"]
    sv = beh["support_violations"]
    parts = ["<h2>Distribution shift</h2>", f"<p><b>{html.escape(h['shift']['text'])}</b>.</p>",
             f"<p>Behaviour probabilities: {html.escape(str(beh['source']))} (clipped at {beh['clip']:g}, "
             f"{beh['n_clipped']} rows clipped). The policy puts most of its mass on actions the data took with "
             f"probability below {sv['threshold']:g} at {sv['fraction']:.1%} of the data's states.</p>"]
    names = {"classifier": "Classifier ratios (simulator)", "recursion": "Ratio recursion (logs only)"}
    scols = ["step", "n", "ess_fraction", "tv", "q50", "q90", "q99", "max", "supported_sup", "sup_ucb",
             "poorly_covered_mass", "auc", "uncovered"]
    link = (f"<a download='per_step.csv' href='data:text/csv;base64,{base64.b64encode(csv).decode()}'>per_step.csv</a>"
            if csv else "per_step.csv")
    for name, block in m["shift"].items():
        d = block["per_step"]
        cols_ = [c for c in scols if d and c in d[0]]
        warn = block.get("warnings") or []
        body = f"<p>{html.escape(block['method'])}. All steps: {link} (also <code>evaluation/per_step.csv</code>).</p>"
        if warn:
            body += "<ul>" + "".join(f"<li>{html.escape(w)}</li>" for w in warn[:5]) + "</ul>"
            if len(warn) > 5:
                body += f"<p>... and {len(warn) - 5} more of the same kind (metrics.json).</p>"
        body += table_html(d, cols_, "steps")
        parts.append(details_html(f"{names.get(name, html.escape(name.replace('reference:', 'Reference policy: ')))}: "
                              f"per-step table ({len(d)} steps, {len(warn)} warnings)", body))
    return parts
