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

from offline_adp.errors import OfflineADPError

#: Two features spanning the value/policy maps and coverage maps, per problem.
MAP_FEATURES = {"path_tracking": ("e", "e_psi"), "car_on_hill": ("p", "s")}
UNITS = {"e": "m", "e_psi": "rad", "p": "", "v": "m/s", "s": "m", "delta": "rad", "kappa": "1/m"}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _label(name: str, units: dict[str, str]) -> str:
    u = units.get(name, "")
    return f"{name} [{u}]" if u else name


class _Figures:
    def __init__(self, folder: Path) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.items: list[tuple[str, str, Path]] = []

    def save(self, fig: Any, name: str, caption: str) -> None:
        path = self.folder / f"{name}.png"
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        _plt().close(fig)
        self.items.append((name, caption, path))


def _convergence(figs: _Figures, run: Path) -> None:
    h_path = run / "model" / "history.csv"
    if not h_path.exists():
        return
    h = pd.read_csv(h_path)
    cols = [c for c in ("sup_dq", "bellman_residual", "mean_dq") if c in h]
    if not cols or "iteration" not in h:
        return
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    for c, lab in (("sup_dq", "sup |Q_k - Q_{k-1}|"), ("mean_dq", "mean |Q_k - Q_{k-1}|"), ("bellman_residual", "Bellman residual (RMS)")):
        if c in h and h[c].notna().any():
            ax.plot(h["iteration"], h[c].abs(), marker=".", label=lab)
    if "structure" in h and h["structure"].nunique() > 1:
        for k in h.loc[h["structure"].diff() > 0, "iteration"]:
            ax.axvline(k, color="0.5", ls=":", lw=1)
            ax.annotate("trees rebuilt", (k, ax.get_ylim()[1]), fontsize=7, color="0.4", ha="left", va="top")
    ax.set_yscale("log")
    ax.set_xlabel("iteration k")
    ax.set_ylabel("cost units (log scale)")
    ax.set_title("Convergence of the fit")
    ax.legend()
    figs.save(fig, "convergence", "Convergence: change between successive Q-functions and the Bellman residual per iteration.")


def _grid(ratios: pd.DataFrame, features: list[str], axes: tuple[str, str], n: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xa, ya = axes
    lo = ratios[[xa, ya]].quantile(0.01).to_numpy()
    hi = ratios[[xa, ya]].quantile(0.99).to_numpy()
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n))
    obs = np.tile(ratios[features].median().to_numpy(), (gx.size, 1))
    obs[:, features.index(xa)] = gx.ravel()
    obs[:, features.index(ya)] = gy.ravel()
    return gx, gy, obs


def _maps(figs: _Figures, run: Path, ratios: pd.DataFrame, features: list[str], axes: tuple[str, str],
          units: dict[str, str], action_values: np.ndarray) -> None:
    from offline_adp.artifacts import load_policy, load_q

    plt = _plt()
    gx, gy, obs = _grid(ratios, features, axes)
    sliced = len(features) > 2
    note = " (other features at their data medians)" if sliced else ""
    policy = load_policy(run / "model")
    acts = policy.act_index(obs, 0, np.random.default_rng(0))
    fig, ax = plt.subplots(figsize=(6.2, 4.6))
    im = ax.pcolormesh(gx, gy, action_values[acts].reshape(gx.shape), shading="auto", cmap="coolwarm")
    fig.colorbar(im, ax=ax, label="chosen action (command value)")
    ax.set_xlabel(_label(axes[0], units))
    ax.set_ylabel(_label(axes[1], units))
    ax.set_title("Policy map" + note, fontsize=10)
    figs.save(fig, "policy_map", "Policy map: the learned policy's action over two state features" + note + ".")
    if (run / "model" / "q.json").exists():
        q, _ = load_q(run / "model")
        v = q.values(obs, 0).min(axis=1)
        fig, ax = plt.subplots(figsize=(6.2, 4.6))
        im = ax.pcolormesh(gx, gy, v.reshape(gx.shape), shading="auto", cmap="viridis")
        fig.colorbar(im, ax=ax, label="min_a Q(x, a): expected discounted cost")
        ax.set_xlabel(_label(axes[0], units))
        ax.set_ylabel(_label(axes[1], units))
        ax.set_title("Value map" + note, fontsize=10)
        figs.save(fig, "value_map", "Value map: min over actions of the fitted Q (cost to go)" + note + ".")


def _ope(figs: _Figures, m: dict[str, Any]) -> None:
    plt = _plt()
    ope = m["ope"]
    names = list(ope)
    est = np.array([ope[k]["estimate"] for k in names], dtype=float)
    lo = np.array([ope[k]["interval"][0] for k in names], dtype=float)
    hi = np.array([ope[k]["interval"][1] for k in names], dtype=float)
    ref = [x for x in (ope["fqe"]["interval"] + [ope["fqe"]["estimate"]]) if x is not None and np.isfinite(x)]
    truth = m.get("rollout", {}).get("policy", {}).get("mean_discounted_cost")
    demo = m.get("rollout", {}).get("demonstrator", {}).get("mean_discounted_cost")
    ref += [x for x in (truth, demo) if x is not None]
    span = max(ref) - min(ref) if len(ref) > 1 else 1.0
    xmin, xmax = min(ref) - 1.5 * span - 1e-9, max(ref) + 1.5 * span + 1e-9
    fig, ax = plt.subplots(figsize=(7, 0.45 * len(names) + 1.6))
    y = np.arange(len(names))[::-1]
    for yi, e, lo_k, hi_k, k in zip(y, est, lo, hi, names, strict=True):
        off = not (np.isfinite(e) and xmin <= e <= xmax)
        if off:
            ax.annotate(f"{k}: off scale ({e:.3g})", (xmax if not np.isfinite(e) or e > xmax else xmin, yi),
                        ha="right" if (not np.isfinite(e) or e > xmax) else "left", va="center", fontsize=8, color="gray")
            continue
        l2, h2 = (np.clip(lo_k, xmin, xmax), np.clip(hi_k, xmin, xmax)) if np.isfinite(lo_k) and np.isfinite(hi_k) else (e, e)
        color = "C0" if not ope[k]["warnings"] else "C1"
        ax.plot([l2, h2], [yi, yi], color=color, lw=2, solid_capstyle="butt")  # a bias-corrected interval may exclude e
        ax.plot([e], [yi], "o", color=color)
    if truth is not None:
        ax.axvline(truth, color="k", ls="--", label="policy, rollout truth")
    if demo is not None:
        ax.axvline(demo, color="C2", ls=":", label="demonstrator, rollout")
    ax.set_yticks(y, [k.upper() for k in names])
    ax.set_xlim(xmin, xmax)
    ax.set_xlabel(f"expected discounted cost over {m['horizon']} steps (gamma = {m['gamma']:g})")
    ax.set_title("Off-policy estimates with 95% intervals (orange: flagged)", fontsize=10)
    if truth is not None or demo is not None:
        ax.legend(fontsize=8, loc="lower right")
    figs.save(fig, "ope", "Off-policy estimates (points, 95% bootstrap intervals) against the simulator's rollout truth when known; "
              "orange estimates carry a warning (see the table).")


def _ratios(figs: _Figures, m: dict[str, Any]) -> None:
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8))
    for i, (name, block) in enumerate(m["shift"].items()):
        d = pd.DataFrame(block["per_step"])
        if d.empty:
            continue
        c = f"C{i}"
        a1.plot(d["step"], d["q90"], color=c, ls="-", label=f"{name}: 90% quantile")
        a1.plot(d["step"], d["q99"], color=c, ls="--", label=f"{name}: 99% quantile")
        a1.plot(d["step"], d["sup_ucb"], color=c, ls=":", label=f"{name}: supported sup (UCB)")
        a2.plot(d["step"], d["ess_fraction"], color=c, marker=".", label=name)
    a1.set_yscale("log")
    a1.set_xlabel("time step t")
    a1.set_ylabel("density ratio w_t (log scale)")
    a1.set_title("Per-step ratio quantiles", fontsize=10)
    a1.legend(fontsize=6)
    a2.set_ylim(0, 1.05)
    a2.set_xlabel("time step t")
    a2.set_ylabel("ESS / n = 1 / E[w^2]")
    a2.set_title("Effective sample size per step", fontsize=10)
    a2.legend(fontsize=7)
    figs.save(fig, "ratios", "Density ratios mu_pi^t / mu_data^t per step: quantiles, supported sup with its bootstrap upper bound, and ESS.")


def _coverage(figs: _Figures, run: Path, ratios: pd.DataFrame, features: list[str], axes: tuple[str, str],
              units: dict[str, str]) -> None:
    plt = _plt()
    xa, ya = axes
    rng = np.random.default_rng(0)
    sub = ratios.iloc[rng.permutation(len(ratios))[:20000]]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.4))
    for i, (src, g) in enumerate(sub.groupby("source")):
        a1.scatter(g[xa], g[ya], s=2, alpha=0.3, color=f"C{i}", label=f"data: {src}")
    st = run / "evaluation" / "rollout_states.npz"
    if st.exists():
        with np.load(st) as z:
            xs = np.concatenate([z[k] for k in z.files])
        xs = xs[rng.permutation(len(xs))[:5000]]
        a1.scatter(xs[:, features.index(xa)], xs[:, features.index(ya)], s=2, alpha=0.4, color="k", label="policy (simulator)")
    a1.set_xlabel(_label(xa, units))
    a1.set_ylabel(_label(ya, units))
    a1.set_title("Where the data and the policy go", fontsize=10)
    a1.legend(fontsize=7, markerscale=4)
    wcol = "w_classifier" if "w_classifier" in sub else "w"
    sc = a2.scatter(sub[xa], sub[ya], s=2, c=np.log10(np.maximum(sub[wcol], 1e-3)), cmap="magma", vmin=-2, vmax=2)
    fig.colorbar(sc, ax=a2, label="log10 w_t(x) (policy density / data density)")
    a2.set_xlabel(_label(xa, units))
    a2.set_ylabel(_label(ya, units))
    a2.set_title(f"Coverage: density ratio at the data's states ({'classifier' if wcol != 'w' else 'recursion'})", fontsize=10)
    figs.save(fig, "coverage", "Coverage map: data by source with the policy's simulated states (left); the density ratio "
              "w_t at every data state (right; classifier ratios when a simulator was used, else the recursion; "
              "bright = the policy goes there more often than the data).")


def _sources(figs: _Figures, m: dict[str, Any]) -> None:
    plt = _plt()
    ps = m["per_source"]
    names = list(ps)
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(5.5, 3.4))
    ax.bar(x - 0.2, [ps[k]["data_mass"] for k in names], 0.4, label="share of the data")
    ax.bar(x + 0.2, [ps[k]["policy_mass"] for k in names], 0.4, label="share of the policy's (re-weighted) mass")
    ax.set_xticks(x, names)
    ax.set_ylabel("fraction of transitions")
    ax.set_title(f"Per-source breakdown (ratios: {m.get('per_source_ratio_method', 'recursion')})", fontsize=10)
    ax.legend(fontsize=8)
    figs.save(fig, "sources", "Per source: its share of the logged transitions and of the policy's state distribution "
              "(data re-weighted by the density ratios).")


def _cross_track(figs: _Figures, run: Path) -> None:
    plt = _plt()
    z = {}
    for who in ("policy", "demonstrator"):
        p = run / "evaluation" / ("rollout_states.npz" if who == "policy" else "rollout_states_demonstrator.npz")
        if not p.exists():
            return
        with np.load(p) as f:
            z[who] = [np.abs(f[f"t{t}"][:, 1]).mean() for t in range(len(f.files))]
    fig, ax = plt.subplots(figsize=(6.5, 3.4))
    for who, v in z.items():
        ax.plot(np.arange(len(v)) * 0.1, v, label=who)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("mean |cross-track error| [m]")
    ax.set_title("Cross-track error in the simulator", fontsize=10)
    ax.legend()
    figs.save(fig, "cross_track", "Mean absolute cross-track error over time in the path_tracking simulator: learned policy vs demonstrator.")


def _table(rows: list[dict[str, Any]], cols: list[str]) -> str:
    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        if isinstance(v, list):
            return "[" + ", ".join(fmt(x) for x in v) + "]"
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{fmt(r.get(c, ''))}</td>" for c in cols) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def build_report(run_dir: str | PathLike[str]) -> Path:
    """Write ``RUN_DIR/report/report.html`` and ``report/figures/*.png``; returns the HTML path."""
    run = Path(run_dir)
    ev = run / "evaluation"
    if not (ev / "metrics.json").exists():
        raise OfflineADPError(f"{run}: no evaluation/metrics.json; run `offline-adp evaluate {run}` first")
    m = json.loads((ev / "metrics.json").read_text())
    ratios = pd.read_parquet(ev / "ratios.parquet")
    features = [c for c in ratios.columns if c not in ("step", "source", "w", "w_classifier")]
    problem = m.get("simulator") or ""
    info_path = Path(m["dataset"]["path"]) / "meta" / "info.json"
    units = dict(UNITS)
    action_values = None
    if info_path.exists():
        info = json.loads(info_path.read_text())
        units.update({f["name"]: f.get("unit", "") for f in info.get("features", [])})
        problem = problem or info.get("problem") or ""
        from offline_adp.data.info import DatasetInfo

        action_values = DatasetInfo.from_dict(info).action_table.values[:, 0]
    axes = MAP_FEATURES.get(problem, tuple(features[:2]) if len(features) >= 2 else None)
    from offline_adp.data.io import atomic_directory

    with atomic_directory(run / "report", overwrite=True) as tmp:
        _build(run, m, ratios, features, axes, units, action_values, problem, tmp)
    return run / "report" / "report.html"


def _build(run: Path, m: dict[str, Any], ratios: pd.DataFrame, features: list[str], axes: Any, units: dict[str, str],
           action_values: Any, problem: str, tmp: Path) -> None:
    figs = _Figures(tmp / "figures")
    _convergence(figs, run)
    if axes is not None and all(a in features for a in axes):
        _maps(figs, run, ratios, features, axes, units, action_values if action_values is not None else np.arange(100.0))
        _coverage(figs, run, ratios, features, axes, units)
    _ope(figs, m)
    _ratios(figs, m)
    _sources(figs, m)
    if problem == "path_tracking":
        _cross_track(figs, run)
    (tmp / "report.html").write_text(_html({**m, "run": run.resolve().name}, figs))



def _html(m: dict[str, Any], figs: _Figures) -> str:
    parts = [f"<h1>offline_adp report: {html.escape(m.get('run', ''))}</h1>",
             f"<p>Dataset <code>{html.escape(m['dataset']['path'])}</code>: {m['dataset']['transitions']} transitions, "
             f"{m['dataset']['episodes']} episodes, sources {html.escape(str(m['dataset']['sources']))}. "
             f"Algorithm {html.escape(str(m.get('algorithm')))}; evaluation horizon {m['horizon']}, gamma {m['gamma']:g}. "
             "Costs are minimised: lower is better.</p>"]
    if "rollout" in m:
        r = m["rollout"]
        rows = [{"policy": k, **{c: v for c, v in r[k].items()}} for k in ("policy", "demonstrator") if k in r]
        cols = ["policy"] + [c for c in rows[0] if c != "policy"]
        parts += ["<h2>Performance in the simulator</h2>", f"<p>{html.escape(r['method'])}.</p>", _table(rows, cols)]
    if "named" in m:
        parts += ["<h2>Named evaluations</h2>", _table([{"name": k, **v} for k, v in m["named"].items()], ["name", "value", "method"])]
    ope_rows = [{"estimator": k.upper(), **v} for k, v in m["ope"].items()]
    parts += ["<h2>Off-policy estimates (logs only)</h2>",
              f"<p>Behaviour probabilities: {m['behaviour']['source']} (clip {m['behaviour']['clip']}, "
              f"{m['behaviour']['n_clipped']} clipped); support violations: "
              f"{m['behaviour']['support_violations']['fraction']:.3f} of states (pi puts most mass on actions the data "
              f"took with probability < {m['behaviour']['support_violations']['threshold']}).</p>",
              _table(ope_rows, ["estimator", "estimate", "interval", "interval_method", "ess", "rollout_error", "warnings"])]
    ws = m["worst_step"]
    parts += ["<h2>Distribution shift</h2>",
              f"<p>Worst step by effective sample size: t = {ws['step']}, ESS/n = {ws['ess_fraction']:.3f}. "
              "The raw maximum of the ratio is never a reliable number on its own; read it next to the supported sup "
              "(regions with at least 20 data samples), its bootstrap upper bound and the mass in poorly covered regions.</p>"]
    for name, block in m["shift"].items():
        d = block["per_step"]
        cols = [c for c in ("step", "n", "ess_fraction", "tv", "q50", "q90", "q99", "max", "supported_sup", "sup_ucb",
                            "poorly_covered_mass", "auc", "uncovered") if d and c in d[0]]
        parts += [f"<h3>{html.escape(name)}</h3><p>{html.escape(block['method'])}</p>", _table(d, cols)]
        if block["warnings"]:
            parts.append("<ul>" + "".join(f"<li>{html.escape(w)}</li>" for w in block["warnings"]) + "</ul>")
    b = m["psdp_bound"]
    parts += ["<h2>PSDP performance bound</h2>",
              f"<p>{html.escape(b['label'])}: J(pi) - J(pi_ref) &le; sum_t eps_t &middot; UCB_t(sup mu_ref^t / mu^t), with "
              "mu^t the data's distribution. An estimate, not a guarantee.</p>",
              _table([{"reference": k, **v} for k, v in b["references"].items()],
                     ["reference", "per_step", "averaged", "poorly_covered_mass", "method"]),
              f"<p>eps_t (residual advantage per step): {', '.join(f'{e:.3g}' for e in b['eps'][:20])}"
              + (" ..." if len(b["eps"]) > 20 else "") + "</p>"]
    parts += ["<h2>Per source</h2>", _table([{"source": k, **v} for k, v in m["per_source"].items()],
                                          ["source", "episodes", "transitions", "logged_mean_discounted_cost", "data_mass",
                                           "policy_mass", "mean_ratio"])]
    parts.append("<h2>Figures</h2>")
    for name, caption, path in figs.items:
        data = base64.b64encode(path.read_bytes()).decode()
        parts.append(f'<figure id="{name}"><img alt="{html.escape(name)}" src="data:image/png;base64,{data}">'
                     f"<figcaption>{html.escape(caption)} (<code>figures/{name}.png</code>)</figcaption></figure>")
    style = ("body{font-family:sans-serif;max-width:1100px;margin:auto;padding:1em}table{border-collapse:collapse;"
             "font-size:12px;margin:.5em 0}td,th{border:1px solid #ccc;padding:2px 6px}img{max-width:100%}"
             "figcaption{font-size:12px;color:#444}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>offline_adp report</title><style>{style}</style>"
            f"</head><body>{''.join(parts)}</body></html>")
