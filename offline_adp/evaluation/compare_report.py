"""The HTML report of ``offline-adp compare``: one self-contained page (figures embedded).

It shows what :func:`offline_adp.evaluation.compare.compare_runs` returns: the ranking with
every candidate's interval (a figure, the behaviour's logged cost as the reference line,
the simulator truth where one exists), the candidates' episode-cost distributions with
their CVaR, and per candidate its shift diagnostic, support, fit and verdict. The page's
style, tables and figure embedding are :mod:`offline_adp.evaluation.report`'s.
"""

from __future__ import annotations

import html
import os
import tempfile
import textwrap
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.evaluation.figures import DIST_COLOURS, Figures, behaviour_line, distribution_figure, pyplot
from offline_adp.evaluation.html_blocks import (
    details_html,
    figure_html,
    page,
    table_html,
    verdict_html,
)
from offline_adp.evaluation.ope import is_finite_number as _is_finite_number
from offline_adp.evaluation.summary import OUTCOME_COLOUR
from offline_adp.evaluation.verdict import behaviour_words

#: Column labels of the comparison's tables.
LABELS = {"name": "candidate", "algorithm": "algorithm", "estimator": "ranked by", "truth": "simulator truth",
          "truth_interval": "truth 95% interval", "reliability": "reliability", "support": "support",
          "shift": "shift diagnostic", "convergence": "fit", "verdict": "verdict", "mean": "mean",
          "cvar": "CVaR", "source": "distribution from", "note": "note", "interval_words": "interval (its level)",
          "outcome_html": "verdict", "fit": "fit converged?"}


def _label(c: dict[str, Any]) -> str:
    return f"{c['rank'] if c.get('rank') else '-'}. {c['name']}"


def _ranking_figure(figs: Figures, res: dict[str, Any]) -> None:
    """One row per candidate (best first): estimate and interval; the truth (with its
    interval) where a simulator ran; the behaviour's logged cost as a reference line."""
    plt = pyplot()
    cands = res["candidates"]
    beh = (res.get("behaviour") or {}).get("mean")
    pts = _ranking_points(res, beh)
    if not pts:
        return
    lo, hi = min(pts), max(pts)
    pad = 0.08 * (hi - lo) if hi > lo else 1.0
    fig, ax = plt.subplots(figsize=(9, 0.6 * len(cands) + 2.0))
    y = np.arange(len(cands))[::-1]
    drawn_demo = False
    levels, drawn_nolevel, drawn_truth = _draw_candidates(ax, y, cands)
    band = behaviour_line(ax, res.get("behaviour") or {})
    demo = (res.get("demonstrator") or {}).get("mean")
    if demo is not None and np.isfinite(demo):
        drawn_demo = True
        ax.axvline(demo, color="#17becf", ls=":", lw=1.5, label="demonstrator: simulator")
    ax.set_yticks(y, [_label(c) for c in cands], fontsize=9)
    ax.set_ylim(-0.7, len(cands) - 0.4)
    ax.set_xlim(min(lo, demo if drawn_demo else lo) - pad, max(hi, demo if drawn_demo else hi) + pad)
    label = f"{res.get('estimand') or 'expected discounted cost'} (lower is better)"
    ax.set_xlabel(textwrap.fill(label, 70), fontsize=9)  # one long line ran off the figure's left edge
    ax.set_title(f"Candidates ranked by {res['estimator'].upper()} (lowest estimate first)", fontsize=10)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.grid(axis="x", alpha=0.3)
    figs.save(fig, "ranking", _ranking_caption(levels, drawn_nolevel, drawn_truth, drawn_demo, beh is not None) + "."
              + band)


def _ranking_points(res: dict[str, Any], beh: float | None) -> list[float]:
    """Every finite value the ranking figure draws (estimates, intervals, truths, the behaviour's
    and the demonstrator's costs): its x range."""
    cands = res["candidates"]
    pts = [v for c in cands for v in ([c["estimate"]] + list(c["interval"] or []) + [c["truth"]]
                                      + list(c.get("truth_interval") or [])) if v is not None and np.isfinite(v)]
    if beh is not None:
        pts.append(beh)
    d_mean = (res.get("demonstrator") or {}).get("mean")
    if d_mean is not None and np.isfinite(d_mean):
        pts.append(d_mean)
    return pts


def _draw_candidates(ax: Any, y: np.ndarray, cands: list[dict[str, Any]]) -> tuple[set[str], bool, bool]:
    """Each candidate's estimate and interval in its verdict's colour, and its simulator truth;
    returns ``(interval levels drawn, an interval without a level drawn, a truth drawn)``."""
    seen: set[str] = set()

    def lab(s: str) -> str | None:
        if s in seen:
            return None
        seen.add(s)
        return s

    drawn_truth = drawn_nolevel = False
    levels: set[str] = set()
    for yi, c in zip(y, cands, strict=True):
        out = c.get("outcome") or "cannot tell"
        col = OUTCOME_COLOUR.get(out, "#888888")
        if c["interval"] and c.get("level") is not None:
            levels.add(f"{c['level']:.0%}")
            ax.plot(c["interval"], [yi, yi], color=col, lw=3, alpha=0.8, solid_capstyle="butt",
                    label=lab(f"{out}: estimate, {c['level']:.0%} interval"))
        elif c["interval"]:  # shown, without a level: thin and dashed
            drawn_nolevel = True
            ax.plot(c["interval"], [yi, yi], color=col, lw=1.5, ls="--",
                    label=lab(f"{out}: estimate, interval without a level (dashed)"))
        if c["estimate"] is not None and np.isfinite(c["estimate"]):
            ax.plot([c["estimate"]], [yi], "o", color=col, ms=7,
                    label=None if c["interval"] else lab(f"{out}: estimate, no interval"))
        if c["truth"] is not None:
            drawn_truth = True
            ti = c.get("truth_interval")
            if ti:
                ax.plot(ti, [yi - 0.25, yi - 0.25], color="k", lw=1.2)
            ax.plot([c["truth"]], [yi - 0.25], "kx", ms=7, label=lab("simulator truth (95% interval)"))
    return levels, drawn_nolevel, drawn_truth


def _ranking_caption(levels: set[str], drawn_nolevel: bool, drawn_truth: bool, drawn_demo: bool,
                     behaviour: bool) -> str:
    """The ranking figure's caption (without its full stop): what each mark drawn means."""
    caption = ("The candidates in the order of their off-policy estimate (top: lowest estimated cost), each in the "
               "colour of its verdict (green better, red worse, amber cannot tell, purple fit not converged)")
    if levels:
        caption += f", with its {'/'.join(sorted(levels))} interval"
    if drawn_nolevel:
        caption += "; dashed: an interval without a level (the policy left the data's support, or its coverage was "\
                   "not measured)"
    if drawn_truth:
        caption += "; black crosses: the simulator truth with its 95% interval"
    if drawn_demo:
        caption += "; dotted: the demonstrator in the simulator"
    if behaviour:
        caption += "; dash-dotted: the behaviour's logged cost"
    return caption


def _distributions(figs: Figures, res: dict[str, Any]) -> None:
    """The candidates' episode-cost distributions (simulator where measured, else the logs'
    importance-weighted one where usable) and the behaviour's logged one."""
    dists: dict[str, tuple[str, dict[str, Any], str]] = {}
    for i, c in enumerate(res["candidates"]):
        cd = c.get("cost_distribution") or {}
        for key, how in (("rollouts", "simulator"), ("logs", "logs, weighted")):
            d = cd.get(key)
            if isinstance(d, dict) and d.get("usable", True) and "quantiles" in d:
                dists[c["run"]] = (f"{c['name']} ({how})", d, f"C{i % 10}")
                break
    b = (res.get("behaviour") or {}).get("cost_distribution")
    if isinstance(b, dict) and "quantiles" in b:
        dists["behaviour"] = ("behaviour (logged)", b, DIST_COLOURS["behaviour_logged"])
    if len(dists) > (1 if "behaviour" in dists else 0):
        distribution_figure(figs, dists, "episode cost (the estimand per episode)", name="cost_distribution")


def _risk_rows(res: dict[str, Any]) -> list[dict[str, Any]]:
    rows = []
    for c in res["candidates"]:
        cd = c.get("cost_distribution") or {}
        row: dict[str, Any] = {"name": _label(c)}
        ro, lg = cd.get("rollouts"), cd.get("logs")
        if isinstance(ro, dict):
            row.update(sim_mean=ro["mean"], sim_cvar=ro["cvar"])
        if isinstance(lg, dict) and lg.get("usable"):
            row.update(logs_mean=lg["mean"], logs_cvar=lg["cvar"])
        elif isinstance(lg, dict):
            row["logs_note"] = "cannot tell from these logs: " + lg.get("reason", "")
        elif not cd:
            row["logs_note"] = "no distribution in this evaluation (re-run with --force)"
        rows.append(row)
    b = (res.get("behaviour") or {}).get("cost_distribution")
    if isinstance(b, dict):
        rows.append({"name": "behaviour (logged)", "logs_mean": b["mean"], "logs_cvar": b["cvar"],
                     "logs_note": f"the {b['n_episodes']} logged episodes themselves"})
    return rows


def _relative(path: str, base: Path | None) -> str:
    """``path`` relative to the report's folder ``base`` (as it is when the report moves with its runs)."""
    if base is None or not path:
        return path
    try:
        return os.path.relpath(Path(path).resolve(), base.resolve())
    except ValueError:  # another drive
        return path


def compare_html(res: dict[str, Any], figs: Figures, base: Path | None = None) -> str:
    """The comparison page for ``res`` (from :func:`~offline_adp.evaluation.compare.compare_runs`)
    with the figures already saved in ``figs``; paths relative to ``base`` (the report's folder)."""
    cands = res["candidates"]
    sel = res.get("selection")
    parts = ["<h1>Comparison of candidate policies</h1>",
             f"<p class='sub'>{len(cands)} candidates on "
             f"{html.escape(_relative(res['dataset']['path'], base))}, ranked by "
             f"{html.escape(res['estimator'].upper())}: {html.escape(res.get('method', ''))}. Estimand: "
             f"{html.escape(str(res.get('estimand')))}. Costs are minimised: lower is better.</p>"]
    parts += _compare_summary(res)
    parts += ["<h2>Figures</h2>", *figure_html(figs, folder=None)]
    rows = _candidate_rows(cands)
    parts += ["<h2>Ranking</h2>", _ranking_table(rows, cands)]
    if res.get("separation"):
        parts.append("<p><b>Can the logs tell them apart?</b> " + "; ".join(
            html.escape(p["text"][:1].upper() + p["text"][1:]) for p in res["separation"])
            + ". (Pairwise, from their intervals: separated only where both have a level and do not overlap.)</p>")
    parts.append("<h2>Verdict and fit per candidate</h2>")
    for r in rows:
        parts.append(f"<h3>{html.escape(_label(r))} <small>({html.escape(_relative(r['run'], base))})</small></h3>"
                     f"{r['verdict_html']}<p><small>{html.escape(r.get('convergence') or '')}</small></p>"
                     + (f"<p><b>Discount: {html.escape(r['discount_note'])}</b></p>" if r.get("discount_note") else ""))
    parts += _risk_section(res)
    if sel:
        parts.append(details_html("Selection scores (how they are computed)",
                                  f"<p>{html.escape(sel.get('method', ''))}. Spearman's rho and Kendall's tau between "
                                  "the estimated and the true costs (1: the same order); regret of the top pick "
                                  "(or, where the logs pick none, of the lowest estimate): its true cost minus the "
                                  "best candidate's.</p>"))
    return page("compare: " + ", ".join(c["name"] for c in cands), parts)


def _compare_summary(res: dict[str, Any]) -> list[str]:
    """The summary box: the top pick (or why there is none), the demonstrator, the behaviour,
    the ranking's scores against the simulator, notes and discount notes."""
    cands = res["candidates"]
    sel = res.get("selection")
    beh = res.get("behaviour") or {}
    box = ["<section class='summary'><h2>Summary</h2><table class='kv'>"]

    def kv(k: str, v: str) -> None:
        box.append(f"<tr><th>{html.escape(k)}</th><td>{v}</td></tr>")

    top = next((c for c in cands if c.get("rank") == 1), None)
    separable = res.get("top_pick") is not None if "top_pick" in res else top is not None  # older results: as before
    if top is not None and separable:
        iv = top["interval"]
        kv("Top pick", f"<b>{html.escape(top['name'])}</b>: {top['estimate']:.4g}"
           + (f" [{iv[0]:.4g}, {iv[1]:.4g}] ({html.escape(top.get('level_words') or 'no level')})" if iv
              else " (no interval)")
           + " &mdash; the logs separate it from every other candidate"
           + (" &mdash; <b>it left the data's support</b>: its estimate is an extrapolation" if top.get("support_left")
              else ""))
    elif top is not None:
        why = "; ".join(res.get("cannot_separate") or []) or "the logs cannot separate the candidates"
        kv("Top pick", "<span class='verdict meh' style='display:inline-block;font-size:13px'><b>no top pick</b>"
           "</span> " + html.escape(why[:1].upper() + why[1:])
           + f" (lowest estimate: {html.escape(top['name'])} {top['estimate']:.4g}, not a pick)")
    d = res.get("demonstrator")
    if d:
        di = d.get("interval")
        kv("Demonstrator (simulator)", f"{d['mean']:.4g}" + (f" [{di[0]:.4g}, {di[1]:.4g}]" if di else "")
           + (f", failures {d['failures']}" if d.get("failures") is not None else "")
           + (f" over {d['n_episodes']} episodes" if d.get("n_episodes") else "")
           + f" ({html.escape(str(d.get('simulator')))})")
    if _is_finite_number(beh.get("mean")):
        kv("Behaviour (logged)", html.escape(behaviour_words(beh)))
    if sel:
        who = "the top pick" if top is not None and separable else "the lowest estimate (not a pick)"
        kv("Against the simulator", f"Spearman {sel['spearman']:.2f}, Kendall {sel['kendall']:.2f}; regret of {who} "
           f"{sel['regret_top1']:.4g} ({sel['relative_regret_top1']:.0%} of the candidates' spread); "
           + (f"{who} is the best candidate" if sel["top_pick_is_best"] else f"<b>{who} is not the best "
              "candidate</b>"))
    else:
        kv("Against the simulator", "no simulator truth for every candidate: the ranking is not scored")
    if res.get("note"):
        kv("Note", html.escape(res["note"]))
    for c in cands:
        if c.get("discount_note"):
            kv(f"Discount ({c['name']})", html.escape(c["discount_note"]))
    box.append("</table></section>")
    return box


def _candidate_rows(cands: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The candidates as table rows: support in words, the verdict box, its outcome word and
    colour class, the interval with its level."""
    rows = []
    for c in cands:
        v = {"performance": c.get("performance"), "support_left": c.get("support_left"), "text": c.get("verdict"),
             "outcome": c.get("outcome"), "lines": c.get("verdict_lines")}
        box = verdict_html(v, {"verdict": c.get("fit_verdict")}, tag="div")
        cls = box.split("class='verdict ", 1)[1].split("'", 1)[0]
        word = box.split("<span class='outcome", 1)[1].split(">", 1)[1].split("<", 1)[0]
        iv = c.get("interval")
        rows.append({**c,
                     "support": "LEFT the data's support" if c.get("support_left") else "within the data's support",
                     "verdict_html": box, "outcome_html": word, "outcome_class": cls,
                     "interval_words": f"[{iv[0]:.4g}, {iv[1]:.4g}] ({c.get('level_words') or 'no level'})" if iv
                     else None,
                     "fit": c.get("fit") or c.get("fit_verdict")})
    return rows


def _ranking_table(rows: list[dict[str, Any]], cands: list[dict[str, Any]]) -> str:
    """The ranking table, each verdict cell in its outcome's colour."""
    cols = ["rank", "name", "algorithm", "estimator", "estimate", "interval_words", "reliability", "fit",
            "outcome_html"] + \
        (["truth", "truth_interval"] if any(c["truth"] is not None for c in cands) else []) + ["support", "shift"]
    table = table_html(rows, cols, "ope", labels=LABELS)
    for r in rows:  # the verdict cell in its outcome's colour
        table = table.replace(f"<td>{html.escape(r['outcome_html'])}</td>",
                              f"<td class='verdict {r['outcome_class']}'><b>{html.escape(r['outcome_html'])}</b></td>",
                              1)
    return table


def _risk_section(res: dict[str, Any]) -> list[str]:
    """The cost distribution and CVaR table (nothing when no candidate has a distribution)."""
    cands = res["candidates"]
    risk = _risk_rows(res)
    alpha = next((c["cost_distribution"]["alpha"] for c in cands if c.get("cost_distribution")), 0.1)
    if not any(len(r) > 1 for r in risk):
        return []
    labels = {"sim_mean": "mean (simulator)", "sim_cvar": f"CVaR_{alpha:g} (simulator)", "logs_mean": "mean (logs)",
              "logs_cvar": f"CVaR_{alpha:g} (logs)", "logs_note": "logs: how", "name": "candidate"}
    return ["<h2>Cost distribution and CVaR</h2>",
            f"<p>CVaR_{alpha:g}: the mean of the worst {alpha:.0%} of episode costs. Simulator: the rollouts' "
            "episodes. Logs: the logged episodes re-weighted by the candidate's importance weights, only where "
            "those weights are usable.</p>",
            table_html(risk, ["name", "sim_mean", "sim_cvar", "logs_mean", "logs_cvar", "logs_note"],
                       labels=labels)]


def write_compare_report(res: dict[str, Any], path: str | PathLike[str]) -> Path:
    """Write the comparison ``res`` as one self-contained HTML file at ``path`` (atomically)."""
    from offline_adp.data.files import atomic_write_text

    with tempfile.TemporaryDirectory(prefix="offline-adp-compare-") as tmp:
        figs = Figures(Path(tmp))
        _ranking_figure(figs, res)
        _distributions(figs, res)
        text = compare_html(res, figs, base=Path(path).parent)
    return atomic_write_text(path, text, what="comparison report")
