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

from offline_adp.data.io import read_info
from offline_adp.data.rundir import read_json_file, read_table_file
from offline_adp.envs import PROBLEM_NAMES, problem_class
from offline_adp.errors import ArtifactError, RunDirectoryError

UNITS = {"e": "m", "e_psi": "rad", "p": "", "v": "m/s", "s": "m", "delta": "rad", "kappa": "1/m"}


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _label(name: str, units: dict[str, str]) -> str:
    u = units.get(name, "")
    return f"{name} [{u}]" if u else name


class Figures:
    """Figures saved as PNG files in ``folder`` and embedded in an HTML page (:func:`figure_html`)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.items: list[tuple[str, str, Path]] = []

    def save(self, fig: Any, name: str, caption: str) -> None:
        path = self.folder / f"{name}.png"
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        pyplot().close(fig)
        self.items.append((name, caption, path))


def _convergence(figs: Figures, run: Path) -> None:
    h_path = run / "model" / "history.csv"
    if not h_path.exists():
        return
    h = read_table_file(h_path)
    cols = [c for c in ("sup_dq", "bellman_residual", "mean_dq") if c in h]
    if not cols or "iteration" not in h:
        return
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    for c, lab in (("sup_dq", "sup |Q_k - Q_{k-1}|"), ("mean_dq", "mean |Q_k - Q_{k-1}|"), ("bellman_residual", "Bellman residual (RMS)")):
        if c in h and h[c].notna().any():
            ax.plot(h["iteration"], h[c].abs(), marker=".", label=lab)
    rebuilt = []
    if "structure" in h and h["structure"].nunique() > 1:
        rebuilt = [int(k) for k in h.loc[h["structure"].diff() > 0, "iteration"]]
        for i, k in enumerate(rebuilt):  # one legend entry for all of them, no text on the plot
            ax.axvline(k, color="0.5", ls=":", lw=1, label="trees rebuilt" if i == 0 else None)
    ax.set_yscale("log")
    ax.set_xlabel("iteration k")
    ax.set_ylabel("cost units (log scale)")
    ax.set_title("Convergence of the fit")
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2, frameon=False)
    caption = "Convergence: change between successive Q-functions and the Bellman residual per iteration."
    if rebuilt:
        caption += (f" Dotted lines: the tree structures were rebuilt (iterations {', '.join(map(str, rebuilt))}); "
                    "the jumps after them are the new structures' first fits.")
    figs.save(fig, "convergence", caption)


def _grid(ratios: pd.DataFrame, features: list[str], axes: tuple[str, str], n: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xa, ya = axes
    lo = ratios[[xa, ya]].quantile(0.01).to_numpy()
    hi = ratios[[xa, ya]].quantile(0.99).to_numpy()
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n))
    obs = np.tile(ratios[features].median().to_numpy(), (gx.size, 1))
    obs[:, features.index(xa)] = gx.ravel()
    obs[:, features.index(ya)] = gy.ravel()
    return gx, gy, obs


def _support_mask(ratios: pd.DataFrame, axes: tuple[str, str], gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Grid cells with no logged state within one cell (True = outside the data's support)."""
    xa, ya = axes
    ex = np.linspace(gx[0, 0], gx[0, -1], gx.shape[1] + 1)
    ey = np.linspace(gy[0, 0], gy[-1, 0], gy.shape[0] + 1)
    h, _, _ = np.histogram2d(ratios[ya].to_numpy(), ratios[xa].to_numpy(), bins=[ey, ex])
    p = np.pad(h, 1)  # one-cell neighbourhood: a cell next to data counts as supported
    near = sum(p[1 + i: 1 + i + h.shape[0], 1 + j: 1 + j + h.shape[1]] for i in (-1, 0, 1) for j in (-1, 0, 1))
    return near < 1


def _shade_unsupported(ax: Any, gx: np.ndarray, gy: np.ndarray, mask: np.ndarray) -> None:
    if mask.any():
        ax.pcolormesh(gx, gy, np.ma.masked_where(~mask, np.ones_like(gx)), shading="auto", cmap="Greys", vmin=0,
                      vmax=1.4, alpha=0.75)
        ax.contourf(gx, gy, mask.astype(float), levels=[0.5, 1.5], colors="none", hatches=["///"])


def _maps(figs: Figures, run: Path, ratios: pd.DataFrame, features: list[str], axes: tuple[str, str],
          units: dict[str, str], action_values: np.ndarray, action_names: list[str] | None = None,
          action_label: str = "action") -> None:
    from matplotlib.colors import BoundaryNorm, ListedColormap

    from offline_adp.artifacts import load_index_policy, load_q

    plt = pyplot()
    gx, gy, obs = _grid(ratios, features, axes)
    mask = _support_mask(ratios, axes, gx, gy)
    sliced = len(features) > 2
    note = " (other features at their data medians)" if sliced else ""
    policy = load_index_policy(run / "model")
    acts = policy.act_index(obs, 0, np.random.default_rng(0))
    n_act = len(action_values)
    base = plt.get_cmap("RdBu_r" if n_act > 2 else "coolwarm")
    cmap = ListedColormap([base(x) for x in np.linspace(0.08, 0.92, n_act)])
    norm = BoundaryNorm(np.arange(n_act + 1) - 0.5, n_act)
    fig, ax = plt.subplots(figsize=(6.6, 4.8))
    im = ax.pcolormesh(gx, gy, acts.reshape(gx.shape), shading="auto", cmap=cmap, norm=norm)
    _shade_unsupported(ax, gx, gy, mask)
    cb = fig.colorbar(im, ax=ax, ticks=np.arange(n_act))
    cb.ax.set_yticklabels(action_names or [f"{v:g}" for v in action_values], fontsize=8)
    cb.set_label(f"chosen {action_label}")
    ax.set_xlabel(_label(axes[0], units))
    ax.set_ylabel(_label(axes[1], units))
    ax.set_title("Policy map at t = 0" + note, fontsize=10)
    figs.save(fig, "policy_map", "Policy map: the learned policy's action over two state features" + note +
              "; one colour per discrete action. Hatched grey: no logged state nearby (outside the data's support, "
              "where the policy is extrapolated).")
    if (run / "model" / "q.json").exists():
        q, _ = load_q(run / "model")
        v = q.values(obs, 0).min(axis=1)
        fig, ax = plt.subplots(figsize=(6.6, 4.8))
        im = ax.pcolormesh(gx, gy, v.reshape(gx.shape), shading="auto", cmap="viridis")
        _shade_unsupported(ax, gx, gy, mask)
        fig.colorbar(im, ax=ax, label="min_a Q(x, a): expected discounted cost to go")
        ax.set_xlabel(_label(axes[0], units))
        ax.set_ylabel(_label(axes[1], units))
        ax.set_title("Value map" + note, fontsize=10)
        figs.save(fig, "value_map", "Value map: min over actions of the fitted Q (cost to go)" + note +
                  "; hatched grey: outside the data's support.")


TIER_COLOURS = {0: "#1f77b4", 1: "#8c8c8c", 2: "#d62728"}


def _ope(figs: Figures, m: dict[str, Any], ranking: list[dict[str, Any]]) -> None:
    """Usable estimators on one readable scale; the unusable ones listed, not plotted."""
    plt = pyplot()
    shown = [e for e in ranking if e["tier"] < 2 and e["estimate"] is not None]
    if not shown:
        return
    truth = m.get("rollout", {}).get("policy", {}).get("mean_discounted_cost")
    demo = m.get("rollout", {}).get("demonstrator", {}).get("mean_discounted_cost")
    beh = (m.get("behaviour_value") or {}).get("mean")
    pts = [e["estimate"] for e in shown] + [v for e in shown if e["interval"] for v in e["interval"]]
    pts += [v for v in (truth, demo, beh) if v is not None]
    lo, hi = min(pts), max(pts)
    pad = 0.08 * (hi - lo) if hi > lo else 1.0
    fig, ax = plt.subplots(figsize=(8.5, 0.55 * len(shown) + 2.0))
    y = np.arange(len(shown))[::-1]
    for yi, e in zip(y, shown, strict=True):
        c = TIER_COLOURS[e["tier"]]
        if e["interval"]:
            ax.plot(e["interval"], [yi, yi], color=c, lw=3, solid_capstyle="butt", alpha=0.8)
        ax.plot([e["estimate"]], [yi], "o", color=c, ms=7)
    if truth is not None:
        ax.axvline(truth, color="k", ls="--", lw=1.5, label="policy: simulator truth")
    if demo is not None:
        ax.axvline(demo, color="#2ca02c", ls=":", lw=1.5, label="demonstrator: simulator")
    if beh is not None:
        ax.axvline(beh, color="#9467bd", ls="-.", lw=1.2, label="behaviour: logged cost")
    ax.set_yticks(y, [e["label"] for e in shown], fontsize=9)
    ax.set_ylim(-0.6, len(shown) - 0.4)
    ax.set_xlim(lo - pad, hi + pad)
    est = m.get("estimand", {})
    ax.set_xlabel(f"expected discounted cost over {est.get('horizon', m.get('horizon'))} steps "
                  f"(gamma = {est.get('gamma', m.get('gamma')):g}; lower is better)")
    ax.set_title("Off-policy estimates (blue: with 95% interval; grey: interval withheld)", fontsize=10)
    if truth is not None or demo is not None or beh is not None:
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.grid(axis="x", alpha=0.3)
    bad = [e for e in ranking if e["tier"] == 2]
    against = [w for w, v in (("the simulator truth", truth), ("the demonstrator in the simulator", demo),
                              ("the behaviour's logged cost", beh)) if v is not None]
    caption = ("Off-policy estimates ranked by reliability (most reliable at the top) with their 95% bootstrap "
               "intervals" + (", against " + " and ".join(against) if against else "") + ".")
    if bad:
        caption += " Not plotted (not usable here): " + "; ".join(f"{e['name'].upper()} ({e['reason']})" for e in bad) + "."
    figs.save(fig, "ope", caption)


def _ratios(figs: Figures, m: dict[str, Any], headline_method: str) -> None:
    """ESS/n per step for every method (the headline's method, if it is one of them, drawn
    boldly and called so) and the per-step ratio quantiles of the most trustworthy per-step
    method, with the single-state max and the region max the PSDP bound's upper bound bounds."""
    plt = pyplot()
    names = {"classifier": "classifier (simulator)", "recursion": "recursion (logs only)"}
    pooled = m.get("pooled_shift") if headline_method == "pooled" else None
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.4))
    shown = "classifier" if "classifier" in m["shift"] else "recursion"
    for i, (name, block) in enumerate(m["shift"].items()):
        d = pd.DataFrame(block["per_step"])
        if d.empty:
            continue
        bold = name == headline_method
        thin = name == "recursion" and headline_method in ("pooled", "none")
        a1.plot(d["step"], d["ess_fraction"], color=f"C{i}", lw=2.2 if bold else 1.0, alpha=1 if bold else 0.6,
                label=names.get(name, name.replace("reference:", "reference: ")) + (" (headline)" if bold else "")
                + (" (few states per step: optimistic)" if thin else ""))
        if name == shown:
            a2.plot(d["step"], d["q90"], color="C0", lw=1, label="90% quantile (single states)")
            a2.plot(d["step"], d["q99"], color="C1", lw=1, label="99% quantile (single states)")
            if "max" in d:
                a2.plot(d["step"], d["max"], color="0.55", lw=0.8, label="max (single states)")
            if "supported_sup" in d and "sup_ucb" in d:
                a2.fill_between(d["step"], d["supported_sup"], d["sup_ucb"], color="C3", alpha=0.25, lw=0,
                                label="max of region means, to its 95% upper bound")
                a2.plot(d["step"], d["sup_ucb"], color="C3", ls=":", lw=1.2)
    if pooled is not None:
        a1.axhline(pooled["ess_fraction"], color="k", ls="--", lw=1.5,
                   label=f"pooled over time (headline): {pooled['ess_fraction']:.3f}")
    a1.set_ylim(0, 1.05)
    a1.set_xlabel("time step t")
    a1.set_ylabel("ESS / n = 1 / E[w_t^2]")
    a1.set_title("Effective sample size per step (1 = no shift)", fontsize=10)
    a1.legend(fontsize=8, loc="best")
    a2.set_yscale("log")
    a2.set_xlabel("time step t")
    a2.set_ylabel("density ratio w_t (log scale)")
    a2.set_title(f"Ratio quantiles: {names.get(shown, shown)}"
                 + (" (few states per step: optimistic)" if shown == "recursion" and headline_method != "recursion"
                    else ""), fontsize=10)
    a2.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.15), ncol=2, frameon=False)
    head = {"classifier": "the classifier's (simulator)", "recursion": "the logs-only recursion's",
            "pooled": "the ratios pooled over time (dashed line; the per-step recursion has too few states per step)",
            "none": "none (too few states per step, and the policy is not stationary, so nothing is pooled)"}
    figs.save(fig, "ratios", "Density ratios mu_pi^t / mu_data^t per step. Left: effective sample size by every method; "
              f"the headline quotes {head.get(headline_method, headline_method)}. The logs-only recursion shrinks "
              "towards 1 where a step has few states. Right: quantiles and max of the "
              f"{names.get(shown, shown)} ratios at single data states, and the max over regions of at least 20 "
              "states of the region's mean ratio up to its bootstrap 95% upper bound (the ratio PSDP's bound uses, "
              "for the recursion). A region mean can be below single-state quantiles: the upper bound bounds the "
              "region max, not single states.")


def _coverage(figs: Figures, run: Path, ratios: pd.DataFrame, features: list[str], axes: tuple[str, str],
              units: dict[str, str]) -> None:
    plt = pyplot()
    xa, ya = axes
    rng = np.random.default_rng(0)
    sub = ratios.iloc[rng.permutation(len(ratios))[:20000]]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.4))
    for i, (src, g) in enumerate(sub.groupby("source")):
        a1.scatter(g[xa], g[ya], s=2, alpha=0.3, color=f"C{i}", label=f"data: {src}")
    st = run / "evaluation" / "rollout_states.npz"
    simulated = st.exists()
    if simulated:
        with np.load(st) as z:
            xs = np.concatenate([z[k] for k in z.files])
        xs = xs[rng.permutation(len(xs))[:5000]]
        a1.scatter(xs[:, features.index(xa)], xs[:, features.index(ya)], s=2, alpha=0.4, color="k", label="policy (simulator)")
    a1.set_xlabel(_label(xa, units))
    a1.set_ylabel(_label(ya, units))
    a1.set_title("Where the data and the policy go" if simulated else "Where the data go (no simulator: the policy's "
                 "own states are unknown)", fontsize=10)
    a1.legend(fontsize=7, markerscale=4)
    wcol = next(c for c in ("w_classifier", "w_pooled", "w") if c in sub)
    sc = a2.scatter(sub[xa], sub[ya], s=2, c=np.log10(np.maximum(sub[wcol], 1e-3)), cmap="magma", vmin=-2, vmax=2)
    fig.colorbar(sc, ax=a2, label="log10 w_t(x) (policy density / data density)")
    a2.set_xlabel(_label(xa, units))
    a2.set_ylabel(_label(ya, units))
    a2.set_title("Coverage: density ratio at the data's states ("
                  + {"w_classifier": "classifier", "w_pooled": "pooled over time"}.get(wcol, "recursion") + ")", fontsize=10)
    method = {"w_classifier": "classifier ratios from the simulator's rollouts", "w_pooled": "ratios pooled over time, "
              "from the logs alone"}.get(wcol, "the ratio recursion, from the logs alone")
    left = ("data by source with the policy's simulated states (left)" if simulated else
            "the data by source (left; no simulator was used, so the policy's own states are not shown)")
    figs.save(fig, "coverage", f"Coverage map: {left}; the density ratio w_t at every data state (right; {method}; "
              "bright = the policy goes there more often than the data).")


def _sources(figs: Figures, m: dict[str, Any]) -> None:
    plt = pyplot()
    ps = m["per_source"]
    names = list(ps)
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(5.5, 3.4))
    ax.bar(x - 0.2, [ps[k]["data_mass"] for k in names], 0.4, label="share of the data")
    ax.bar(x + 0.2, [ps[k]["policy_mass"] for k in names], 0.4, label="share of the policy's (re-weighted) mass")
    ax.set_xticks(x, names)
    ax.set_ylabel("fraction of transitions")
    ax.set_title(f"Per-source breakdown (ratios: {m.get('per_source_ratio_method', 'recursion')})", fontsize=10)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2, frameon=False)
    figs.save(fig, "sources", "Per source: its share of the logged transitions and of the policy's state distribution "
              "(data re-weighted by the density ratios).")


def _traced(figs: Figures, run: Path, features: list[str], traced: dict[str, str], dt: float | None, sim: str) -> None:
    """Per feature the problem traces (``ReferenceProblem.traced_features``): its mean
    absolute value over rollout time, learned policy vs demonstrator."""
    plt = pyplot()
    for name, label in traced.items():
        if name not in features:
            continue
        j = features.index(name)
        z = {}
        for who, fname in (("policy", "rollout_states.npz"), ("demonstrator", "rollout_states_demonstrator.npz")):
            p = run / "evaluation" / fname
            if p.exists():
                with np.load(p) as f:
                    z[who] = [np.abs(f[f"t{t}"][:, j]).mean() for t in range(len(f.files))]
        if not z:
            continue
        fig, ax = plt.subplots(figsize=(6.5, 3.4))
        for who, v in z.items():
            ax.plot(np.arange(len(v)) * (dt or 1.0), v, label=who)
        ax.set_xlabel("time [s]" if dt else "step")
        ax.set_ylabel(label)
        ax.set_title(f"{label[:1].upper()}{label[1:]} in the simulator", fontsize=10)
        ax.legend()
        figs.save(fig, f"traced_{name}", f"{label[:1].upper()}{label[1:]} over time in the {sim} simulator: learned "
                  "policy vs demonstrator.")


#: Human column labels for the report's tables.
LABELS = {
    "estimator": "estimator", "estimate": "estimate", "interval": "95% interval", "interval_method": "interval method",
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
        raise RunDirectoryError(f"{run}: no evaluation/metrics.json; run `offline-adp evaluate {run}` first")
    m = read_json_file(ev / "metrics.json")
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
        units.update({f["name"]: f["unit"] for f in info.get("features", []) if f.get("unit")})  # never blank a fallback
        problem = problem or info.get("problem") or ""
        from offline_adp.data.info import DatasetInfo

        table = DatasetInfo.from_dict(info, where=str(info_path)).action_table
        dims = list(getattr(table, "dims", []) or [])
        aunits = list(getattr(table, "units", []) or [])
        names = table.names() if callable(table.names) else table.names
        actions = {"values": table.values[:, 0], "names": [str(n) for n in names] or None,
                   "label": (dims[0] if dims else "action") + (f" [{aunits[0]}]" if aunits and aunits[0] else "")}
        units.setdefault("cost", "")
    cls = problem_class(problem) if problem in PROBLEM_NAMES else None  # problem-specific: the ReferenceProblem's hooks
    axes = getattr(cls, "map_features", None) or (tuple(features[:2]) if len(features) >= 2 else None)
    from offline_adp.data.io import atomic_directory
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
    _ope(figs, m, h["ranking"])
    _ratios(figs, m, h["shift"]["method"])
    if axes is not None and all(a in features for a in axes):
        vals = actions.get("values")
        _maps(figs, run, ratios, features, axes, units, vals if vals is not None else np.arange(100.0),
              actions.get("names"), actions.get("label", "action"))
        _coverage(figs, run, ratios, features, axes, units)
    _convergence(figs, run)
    _cost_distribution(figs, m)
    _sources(figs, m)
    cls = problem_class(problem) if problem in PROBLEM_NAMES else None
    if cls is not None and cls.traced_features:
        _traced(figs, run, features, cls.traced_features, cls.dt, problem)
    csv = (run / "evaluation" / "per_step.csv").read_bytes() if (run / "evaluation" / "per_step.csv").exists() else b""
    (tmp / "report.html").write_text(_html(m, h, figs, _title(run, m), csv))


#: The stylesheet of every HTML report (run report, comparison).
STYLE = ("body{font-family:system-ui,sans-serif;max-width:1100px;margin:auto;padding:1em;color:#222}"
         "h1{font-size:1.6em;margin-bottom:.2em}.sub{color:#555;margin-top:0}"
         "table{border-collapse:collapse;font-size:12px;margin:.5em 0}td,th{border:1px solid #ccc;padding:3px 7px;"
         "vertical-align:top}th{background:#f3f3f3;text-align:left}img{max-width:100%}"
         "figure{margin:1em 0}figcaption{font-size:12px;color:#444}"
         ".summary{border:2px solid #444;border-radius:6px;padding:.2em 1em 1em;background:#fafafa}"
         ".summary h2{margin:.4em 0}.kv th{width:170px}.kv td,.kv th{font-size:13px}"
         ".verdict{font-size:15px;padding:.5em;border-radius:4px}.good{background:#e3f4e1}.bad{background:#fbe3e3}"
         ".meh{background:#f4f0dc}details{margin:.5em 0}summary{cursor:pointer;font-weight:600}"
         "table.ope td{max-width:360px}")


def page(title: str, parts: list[str]) -> str:
    """A self-contained HTML page: ``title`` and the HTML fragments ``parts`` with :data:`STYLE`."""
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title><style>{STYLE}</style>"
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


def psdp_rows(m: dict[str, Any]) -> list[dict[str, Any]]:
    """The PSDP bound per reference policy with the two factors it multiplies, as
    :func:`offline_adp.evaluation.offpolicy.psdp_bound` uses them: ``sum_t eps_t`` (the
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
               "pooled_ratio_ucb": "UCB(sup pooled ratio)", "per_step": "bound: sum_t eps_t UCB_t",
               "averaged": "bound: T mean(eps) UCB(pooled)", "method": "ratios from"}


def psdp_section(m: dict[str, Any], h: dict[str, Any]) -> list[str]:
    """The PSDP bound's table and what it rests on, said where a better diagnostic disagrees."""
    b = m["psdp_bound"]
    eps_how = b.get("eps_method") or "in sample"
    text = (f"<p>{html.escape(b['label'])}: J(pi) &minus; J(pi_ref) &le; &sum;<sub>t</sub> eps_t &middot; "
            "UCB_t(sup mu_ref^t / mu^t), with mu^t the data's distribution. An estimate, not a guarantee. "
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
    return ["<h2>PSDP performance bound</h2>", text, table_html(psdp_rows(m), cols, labels=PSDP_LABELS)]


#: The cost distributions of ``metrics.json`` ``cost_distribution``, in the order shown.
DISTRIBUTIONS = {"policy_rollouts": "policy (simulator rollouts)", "policy_logs": "policy (logs, importance-weighted)",
                 "demonstrator_rollouts": "demonstrator (simulator rollouts)", "behaviour_logged": "behaviour (logged)"}
DIST_COLOURS = {"policy_rollouts": "k", "policy_logs": "#1f77b4", "demonstrator_rollouts": "#2ca02c",
                "behaviour_logged": "#9467bd"}


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


def distribution_figure(figs: Figures, dists: dict[str, tuple[str, dict[str, Any], str]], xlabel: str,
                        name: str = "cost_distribution", caption: str = "") -> None:
    """Quantile functions (episode cost against the fraction of episodes at or below it) of
    ``dists`` (``key -> (label, summary, colour)``), each with its CVaR drawn over the tail."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8.5, 3.8))
    alpha = None
    for label, d, colour in dists.values():
        q = d["quantiles"]
        ax.step(q["values"], q["levels"], where="post", color=colour, lw=1.6, label=label)
        alpha = d["alpha"]
        ax.plot([d["cvar"]] * 2, [1 - alpha, 1.0], color=colour, lw=4, alpha=0.6, solid_capstyle="butt")
        ax.plot([d["mean"]], [0.5], "o", color=colour, ms=5)
    if alpha is not None:
        ax.axhline(1 - alpha, color="0.6", lw=0.8, ls=":")
    ax.set_ylim(0, 1.02)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("fraction of episodes with cost <= x")
    ax.set_title("Episode-cost distributions (lower is better)", fontsize=10)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.grid(alpha=0.3)
    figs.save(fig, name, caption or (f"Distribution of the episode cost. Dot: the mean; thick bar at the top: CVaR_{alpha:g}"
                                     f", the mean of the worst {alpha:.0%} of episodes (dotted line: where that tail "
                                     "starts)."))


def _cost_distribution(figs: Figures, m: dict[str, Any]) -> None:
    cd = m.get("cost_distribution") or {}
    dists = {k: (lab, cd[k], DIST_COLOURS[k]) for k, lab in DISTRIBUTIONS.items()
             if isinstance(cd.get(k), dict) and cd[k].get("usable", True) and "quantiles" in cd[k]}
    if not dists:
        return
    est = m.get("estimand", {})
    a = cd.get("alpha", 0.1)
    missing = "" if "policy_rollouts" in dists or "policy_logs" in dists else (
        " The policy's own distribution is not shown: no simulator was used and its importance weights on these logs "
        "are not usable (see the table below), so the logs cannot tell it.")
    distribution_figure(figs, dists, f"episode cost sum_t gamma^t c_t over {est.get('horizon', m.get('horizon'))} steps",
                        caption=f"Distribution of the episode cost (the estimand per episode). Dot: the mean; thick bar "
                                f"at the top: CVaR_{a:g}, the mean of the worst {a:.0%} of episodes (dotted line: where "
                                "that tail starts)." + missing)


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
            table_html(distribution_rows(cd), ["distribution", "episodes", "mean", "median", "q90", "cvar", "max", "note"],
                       labels=labels)]


def verdict_colour(v: dict[str, Any], conv: dict[str, Any]) -> str:
    """The verdict box's colour follows the weakest of its clauses: green ("good") only for
    a policy better than the behaviour that stayed within the data's support and whose fit
    converged; red ("bad") for worse; amber ("meh") for everything in between, so a doubt
    in the same sentence is never painted green."""
    if v.get("performance") == "worse":
        return "bad"
    from offline_adp.evaluation.summary import FIT_SETTLED

    ok = conv.get("verdict") in FIT_SETTLED
    if v.get("performance") == "better" and not v.get("support_left") and ok:
        return "good"
    return "meh"


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
    v, b, sh, cv = h["verdict"], h["best"], h["shift"], h["convergence"]
    cls = verdict_colour(v, cv)
    text = v["text"][:1].upper() + v["text"][1:]
    rows = [f"<p class='verdict {cls}'>{html.escape(text)}</p>", "<table class='kv'>"]

    def kv(k: str, val: str) -> None:
        rows.append(f"<tr><th>{html.escape(k)}</th><td>{val}</td></tr>")

    est = m.get("estimand", {})
    kv("Estimand", html.escape(est.get("quantity", f"expected discounted cost over {m.get('horizon')} steps")) +
       " (lower is better)")
    if b is not None:
        lo, hi = b["interval"]
        caveat = "" if lo <= b["estimate"] <= hi else (" &mdash; <b>the interval excludes the estimate</b>: its bootstrap "
                                                      "replicates are shifted, treat the interval as unreliable")
        corrected = (f"; bias-corrected by the bootstrap (plug-in estimate {b['plugin_estimate']:.4g}, its replicates "
                     "shifted away from it)" if b.get("plugin_estimate") is not None else "")
        kv("Best estimate", f"<b>{b['estimate']:.4g}</b> [{lo:.4g}, {hi:.4g}] (95%), "
           f"{html.escape(b['label'])}, the most reliable estimator here{corrected}{caveat}")
    else:
        top = next((e for e in h["ranking"] if e["tier"] == 1), None)
        kv("Best estimate", f"{top['estimate']:.4g} ({html.escape(top['label'])}) without an interval: "
           f"{html.escape(top['reason'])}" if top else "none: no estimator is usable on these logs (see below)")
    if "rollout" in m:
        p, d = m["rollout"]["policy"], m["rollout"].get("demonstrator")
        vs = f" vs demonstrator {d['mean_discounted_cost']:.4g}" if d is not None else " (no demonstrator to compare with)"
        kv("Simulator truth", f"policy {p['mean_discounted_cost']:.4g} [{p['interval'][0]:.4g}, {p['interval'][1]:.4g}]{vs} "
           f"({html.escape(str(m.get('simulator')))}, {p['n_episodes']} episodes)")
    else:
        kv("Simulator", html.escape(m.get("simulator_note") or "none used"))
    bv = m.get("behaviour_value")
    if bv:
        kv("Behaviour (logged)", f"{bv['mean']:.4g} [{bv['interval'][0]:.4g}, {bv['interval'][1]:.4g}] over "
           f"{bv['episodes']} episodes")
    cd = m.get("cost_distribution")
    if cd:
        kv("Cost distribution", html.escape(risk_text(cd)))
    kv("Distribution shift", html.escape(sh["text"]))
    kv("Fit", html.escape(cv["text"]))
    kv("Warnings", f"{h['n_warnings']} (listed with each estimator and diagnostic below)")
    rows.append("</table>")
    return "<section class='summary'><h2>Summary</h2>" + "".join(rows) + "</section>"


def details_html(summary: str, body: str, open_: bool = False) -> str:
    """A collapsible block (``<details>``) with ``summary`` as its title."""
    return f"<details{' open' if open_ else ''}><summary>{summary}</summary>{body}</details>"


def _html(m: dict[str, Any], h: dict[str, Any], figs: Figures, title: str, csv: bytes) -> str:
    ds = m["dataset"]
    src = ", ".join(f"{k}: {v}" for k, v in (ds.get("sources") or {}).items())
    parts = [f"<h1>{html.escape(title)}</h1>",
             f"<p class='sub'>Policy fitted by {html.escape(str(m.get('algorithm') or 'unknown').upper())} on "
             f"{ds['transitions']:,} transitions in {ds['episodes']} episodes ({html.escape(src)}). "
             "Costs are minimised: lower is better.</p>",
             _summary_box(m, h), "<h2>Figures</h2>"]
    parts += figure_html(figs)
    # estimators ranked by reliability; the unusable ones collapsed with the reason
    rk = h["ranking"]
    ope = m["ope"]

    def row(e: dict[str, Any]) -> dict[str, Any]:
        r = ope[e["name"]]
        return {"rank": e["rank"], "estimator": e["label"], "estimate": e["estimate"], "interval": e["interval"],
                "interval_method": r.get("interval_method"), "ess": r.get("ess"), "rollout_error": r.get("rollout_error"),
                "reason": e["reason"] or "", "warnings": r.get("warnings") or []}

    cols = ["rank", "estimator", "estimate", "interval", "interval_method", "ess"] + \
        (["rollout_error"] if "rollout" in m else []) + ["warnings"]
    good = [row(e) for e in rk if e["tier"] < 2]
    bad = [row(e) for e in rk if e["tier"] == 2]
    parts += ["<h2>Off-policy estimates, most reliable first</h2>",
              "<p>Every estimator targets the estimand above. Reliable: a finite estimate inside the possible range "
              "with a 95% interval; grey rows have no interval (it was withheld because it would not cover as "
              "labelled).</p>", table_html(good, cols, "ope")]
    if bad:
        parts.append(details_html(f"{len(bad)} estimators not usable on these logs: "
                              + html.escape(", ".join(b["estimator"].split(" ")[0] for b in bad)) + " (why)",
                              "<p>Their weights are degenerate, or their estimate is impossible for this cost, or they "
                              "target another quantity. They are never quoted as support.</p>"
                              + table_html(bad, ["estimator", "estimate", "reason", "warnings"])))
    beh = m["behaviour"]
    sv = beh["support_violations"]
    parts += ["<h2>Distribution shift</h2>", f"<p><b>{html.escape(h['shift']['text'])}</b>.</p>",
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
    parts += psdp_section(m, h)
    parts += cost_distribution_section(m)
    parts += ["<h2>Per source</h2>", table_html([{"source": k, **v} for k, v in m["per_source"].items()],
                                          ["source", "episodes", "transitions", "logged_mean_discounted_cost", "data_mass",
                                           "policy_mass", "mean_ratio"])]
    if m.get("warnings"):
        parts += ["<h2>Evaluation warnings</h2>", "<ul>" + "".join(f"<li>{html.escape(w)}</li>" for w in m["warnings"])
                  + "</ul>"]

    return page(title, parts)
