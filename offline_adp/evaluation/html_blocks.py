"""The HTML building blocks of every report (the run report, :mod:`offline_adp.evaluation.report`,
and the comparison, :mod:`offline_adp.evaluation.compare_report`): the page and its stylesheet,
tables and their cells, embedded figures, collapsible blocks, the verdict box in its outcome's
colour and the list of warnings.
"""

from __future__ import annotations

import base64
import html
from typing import Any

import numpy as np

from offline_adp.evaluation.figures import Figures

#: Human column labels for the report's tables.
LABELS = {
    "estimator": "estimator", "estimate": "estimate", "interval": "interval (its level)",
    "interval_method": "interval method",
    "ess": "effective sample size (episodes)", "rollout_error": "error vs simulator truth", "warnings": "warnings",
    "step": "step t", "n": "data states", "ess_fraction": "ESS / n", "tv": "total variation", "q50": "median ratio",
    "q90": "90% quantile", "q99": "99% quantile", "max": "max ratio", "supported_sup": "supported max",
    "sup_ucb": "supported max (upper bound)", "poorly_covered_mass": "policy mass poorly covered",
    "auc": "classifier AUC", "uncovered": "policy states without data", "mean_discounted_cost": "mean discounted cost",
    "n_episodes": "episodes", "mean_length": "mean length (steps)", "terminated": "terminated episodes",
    "level": "level", "episodes": "episodes", "transitions": "transitions",
    "logged_mean_discounted_cost": "logged mean discounted cost", "data_mass": "share of the data",
    "policy_mass": "share of the policy's mass", "mean_ratio": "mean ratio", "reference": "reference policy",
    "per_step": "per-step bound", "averaged": "averaged bound", "method": "method", "rank": "rank",
    "reliability": "reliability", "reason": "why", "failures": "failures",
    "mean_abs_cross_track_error_m": "mean |cross-track error| [m]",
}


def fmt(v: Any) -> str:
    """One table cell: numbers to 4 significant digits, missing as a dash, lists and dicts spelled out."""
    if v is None:
        return "&ndash;"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return "&ndash;" if not np.isfinite(v) else f"{v:.4g}"
    if isinstance(v, list | tuple):
        if len(v) == 2 and all(isinstance(x, int | float) or x is None for x in v):
            return "&ndash;" if any(x is None for x in v) else f"[{fmt(v[0])}, {fmt(v[1])}]"
        return "<br>".join(fmt(x) for x in v) if v else "&ndash;"
    if isinstance(v, dict):
        return ", ".join(f"{html.escape(str(k))}: {fmt(x)}" for k, x in v.items())
    return html.escape(str(v).replace("_", " ") if isinstance(v, str) and v.isidentifier() else str(v))


def table_html(rows: list[dict[str, Any]], cols: list[str], cls: str = "", labels: dict[str, str] | None = None) -> str:
    """An HTML table of ``rows`` (dicts) with the columns ``cols``, headed by their labels
    (``labels``, then :data:`LABELS`), cells formatted by :func:`fmt`."""
    labels = {**LABELS, **(labels or {})}
    head = "".join(f"<th>{html.escape(labels.get(c, c.replace('_', ' ')))}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{fmt(r.get(c))}</td>" for c in cols) + "</tr>" for r in rows)
    return f"<table class='{cls}'><tr>{head}</tr>{body}</table>"


#: The stylesheet of every HTML report (run report, comparison).
STYLE = ("body{font-family:system-ui,sans-serif;max-width:1100px;margin:auto;padding:1em;color:#222}"
         "h1{font-size:1.6em;margin-bottom:.2em}.sub{color:#555;margin-top:0}"
         "table{border-collapse:collapse;font-size:12px;margin:.5em 0}td,th{border:1px solid #ccc;padding:3px 7px;"
         "vertical-align:top}th{background:#f3f3f3;text-align:left}img{max-width:100%}"
         "figure{margin:1em 0}figcaption{font-size:12px;color:#444}"
         ".summary{border:2px solid #444;border-radius:6px;padding:.2em 1em 1em;background:#fafafa}"
         ".summary h2{margin:.4em 0}.kv th{width:170px}.kv td,.kv th{font-size:13px}"
         ".verdict{font-size:15px;padding:.5em .7em;border-radius:4px;border-left:8px solid #888}"
         ".verdict .why{font-size:13px;color:#333}"
         ".good{background:#e3f4e1;border-color:#2e7d32}.bad{background:#fbe3e3;border-color:#c62828}"
         ".meh{background:#f7efd2;border-color:#b58900}.stale{background:#efe3f6;border-color:#7b1fa2}"
         ".outcome{display:inline-block;font-weight:700;text-transform:uppercase;letter-spacing:.04em;color:#fff;"
         "padding:.05em .5em;border-radius:3px;margin-right:.5em;font-size:13px}"
         ".outcome.good{background:#2e7d32}.outcome.bad{background:#c62828}.outcome.meh{background:#b58900}"
         ".outcome.stale{background:#7b1fa2}details{margin:.5em 0}summary{cursor:pointer;font-weight:600}"
         "table.ope td{max-width:360px}")


def page(title: str, parts: list[str]) -> str:
    """A self-contained HTML page: ``title`` and the HTML fragments ``parts`` with :data:`STYLE`."""
    return ("<!DOCTYPE html><html><head><meta "
            f"charset='utf-8'><title>{html.escape(title)}</title><style>{STYLE}</style>"
            f"</head><body>{''.join(parts)}</body></html>")


def figure_html(figs: Figures, folder: str | None = "figures") -> list[str]:
    """The figures of ``figs`` embedded as base64 PNGs with their captions (and, when ``folder``
    is given, the PNG file's name under it)."""
    out = []
    for name, caption, path in figs.items:
        data = base64.b64encode(path.read_bytes()).decode()
        where = f" (<code>{folder}/{name}.png</code>)" if folder else ""
        out.append(f'<figure id="{name}"><img alt="{html.escape(name)}" src="data:image/png;base64,{data}">'
                   f"<figcaption>{html.escape(caption)}{where}</figcaption></figure>")
    return out


def verdict_colour(v: dict[str, Any], conv: dict[str, Any]) -> str:
    """The CSS class of a verdict: one per outcome word
    (:data:`~offline_adp.evaluation.verdict.OUTCOME_CLASS`: better green, worse red, cannot
    tell amber, not converged purple), the word :func:`~offline_adp.evaluation.verdict.outcome_of`
    computed once for the CLI, the report and ``compare``. A verdict without its word (older
    metrics) gets it from its side and the fit's verdict. A doubt in the same sentence is never
    painted green: the logs claim a side only without doubts, and a fit that did not converge
    is its own colour."""
    from offline_adp.evaluation.summary import OUTCOME_CLASS, outcome_of

    out = v.get("outcome") or outcome_of(v.get("performance"), conv.get("verdict"), v.get("against_demonstrator"))
    return OUTCOME_CLASS.get(out, "meh")


def verdict_html(v: dict[str, Any], conv: dict[str, Any], tag: str = "p") -> str:
    """The verdict box: the outcome word as a badge in its colour, then the verdict's text."""
    from offline_adp.evaluation.summary import OUTCOME_CLASS, outcome_of

    out = v.get("outcome") or outcome_of(v.get("performance"), conv.get("verdict"), v.get("against_demonstrator"))
    cls = OUTCOME_CLASS.get(out, "meh")
    from offline_adp.evaluation.verdict import stored_lines

    three = stored_lines(v)
    if three:  # the verdict in bold, then the estimate and the why, one line each
        first = three[1][:1].upper() + three[1][1:]
        body = (f"<b>{html.escape(first)}</b><br><span class='why'>{html.escape(three[0])}</span>"
                f"<br><span class='why'>{html.escape(three[2])}</span>")
    else:
        body = html.escape((v.get("text") or "")[:1].upper() + (v.get("text") or "")[1:])
    return f"<{tag} class='verdict {cls}'><span class='outcome {cls}'>{html.escape(out)}</span>{body}</{tag}>"


def warning_items(ws: list[Any]) -> str:
    """The gathered warnings as list items, each with its source."""
    out = []
    for w in ws:
        if isinstance(w, dict):
            out.append(f"<li><b>{html.escape(str(w.get('source', '')))}</b>: "
                       f"{html.escape(str(w.get('message', '')))}</li>")
        else:
            out.append(f"<li>{html.escape(str(w))}</li>")
    return "".join(out)


def details_html(summary: str, body: str, open_: bool = False) -> str:
    """A collapsible block (``<details>``) with ``summary`` as its title."""
    return f"<details{' open' if open_ else ''}><summary>{summary}</summary>{body}</details>"
