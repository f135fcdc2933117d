"""The figures of the evaluation report (:mod:`offline_adp.evaluation.report`) and of the
comparison report (:mod:`offline_adp.evaluation.compare_report`): each draws from
``metrics.json`` and the run's files into a :class:`Figures` collection (PNG files, embedded
in the HTML page)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from offline_adp.data.files import read_table_file
from offline_adp.evaluation.ope import is_finite_number
from offline_adp.evaluation.verdict import behaviour_not_comparable, logged_interval

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


def convergence_figure(figs: Figures, run: Path) -> None:
    h_path = run / "model" / "history.csv"
    if not h_path.exists():
        return
    h = read_table_file(h_path)
    cols = [c for c in ("sup_dq", "bellman_residual", "mean_dq") if c in h]
    if not cols or "iteration" not in h:
        return
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    for c, lab in (("sup_dq", "sup |Q_k - Q_{k-1}|"), ("mean_dq", "mean |Q_k - Q_{k-1}|"),
                   ("bellman_residual", "Bellman residual (RMS)")):
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


def _grid(ratios: pd.DataFrame, features: list[str], axes: tuple[str, str],
          n: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def policy_maps(figs: Figures, run: Path, ratios: pd.DataFrame, features: list[str], axes: tuple[str, str],
          units: dict[str, str], action_values: np.ndarray, action_names: list[str] | None = None,
          action_label: str = "action") -> None:
    from matplotlib.colors import BoundaryNorm, ListedColormap

    from offline_adp.artifacts import load_index_policy, load_q
    from offline_adp.qfunctions import q_support, restrict_to_support

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
        v = restrict_to_support(q.values(obs, 0), q_support(q, obs, 0)).min(axis=1)  # lookup tables: logged actions
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


def ope_figure(figs: Figures, m: dict[str, Any], ranking: list[dict[str, Any]]) -> None:
    """Usable estimators on one readable scale; the unusable ones listed, not plotted."""
    plt = pyplot()
    shown = [e for e in ranking if e["tier"] < 2 and e["estimate"] is not None]
    if not shown:
        return
    truth = m.get("rollout", {}).get("policy", {}).get("mean_discounted_cost")
    demo = m.get("rollout", {}).get("demonstrator", {}).get("mean_discounted_cost")
    beh = (m.get("behaviour_value") or {}).get("mean")
    pts = [e["estimate"] for e in shown] + [v for e in shown for v in (e["interval"] or e.get("shown_interval") or [])]
    pts += [v for v in (truth, demo, beh) if v is not None]
    lo, hi = min(pts), max(pts)
    pad = 0.08 * (hi - lo) if hi > lo else 1.0
    fig, ax = plt.subplots(figsize=(8.5, 0.55 * len(shown) + 2.0))
    y = np.arange(len(shown))[::-1]
    for yi, e in zip(y, shown, strict=True):
        c = TIER_COLOURS[e["tier"]]
        if e["interval"]:
            ax.plot(e["interval"], [yi, yi], color=c, lw=3, solid_capstyle="butt", alpha=0.8)
        elif e.get("shown_interval"):  # an interval without a level: drawn thin and dashed, never as a level's
            ax.plot(e["shown_interval"], [yi, yi], color=c, lw=1.5, ls="--")
        ax.plot([e["estimate"]], [yi], "o", color=c, ms=7)
    if truth is not None:
        ax.axvline(truth, color="k", ls="--", lw=1.5, label="policy: simulator truth")
    if demo is not None:
        ax.axvline(demo, color="#2ca02c", ls=":", lw=1.5, label="demonstrator: simulator")
    band = behaviour_line(ax, m.get("behaviour_value") or {})
    paired = _paired_words(m, shown[0])
    ax.set_yticks(y, [e["label"] for e in shown], fontsize=9)
    ax.set_ylim(-0.6, len(shown) - 0.4)
    ax.set_xlim(lo - pad, hi + pad)
    est = m.get("estimand", {})
    ax.set_xlabel(f"expected discounted cost over {est.get('horizon', m.get('horizon'))} steps "
                  f"(gamma = {est.get('gamma', m.get('gamma')):g}; lower is better)")
    levels = sorted({f"{e['level']:.0%}" for e in shown if e["interval"] and e.get("level")})
    blue = f"blue: with a {'/'.join(levels)} interval; " if levels else ""
    ax.set_title(f"Off-policy estimates ({blue}grey: interval without a level, dashed, or withheld)", fontsize=10)
    if truth is not None or demo is not None or beh is not None:
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.grid(axis="x", alpha=0.3)
    bad = [e for e in ranking if e["tier"] == 2]
    against = [w for w, v in (("the simulator truth", truth), ("the demonstrator in the simulator", demo),
                              ("the behaviour's logged cost", beh)) if v is not None]
    nolevel = [e for e in shown if not e["interval"] and e.get("shown_interval")]
    notes = {e.get("level_note") or "" for e in nolevel}  # one reason for all, or each its own
    said = (", ".join(e["name"].upper() for e in nolevel) + (f" ({notes.pop()})" if notes != {""} else "")
            if len(notes) == 1 else "; ".join(e["name"].upper() + (f" ({e['level_note']})" if e.get("level_note")
                                                                   else "") for e in nolevel))
    caption = ("Off-policy estimates ranked by reliability (most reliable at the top) with their bootstrap intervals"
               + (f" ({', '.join(levels)})" if levels else "")
               + (", against " + " and ".join(against) if against else "") + "."
               + (f" Dashed, without a level: {said}." if nolevel else ""))
    if bad:
        caption += " Not plotted (not usable here): " + "; ".join(f"{e['name'].upper()} "
                                                                  f"({e['reason']})" for e in bad) + "."
    figs.save(fig, "ope", caption + band + paired)


def behaviour_line(ax: Any, beh: dict[str, Any]) -> str:
    """Draw the behaviour's logged cost (dash-dotted) and shade its own interval, the one the verdict
    reads a side against (:func:`~offline_adp.evaluation.verdict.logged_side`); returns the
    caption's words on the shading ('' when there is no interval to shade)."""
    if not is_finite_number(beh.get("mean")):
        return ""
    ax.axvline(beh["mean"], color="#9467bd", ls="-.", lw=1.2, label="behaviour: logged cost")
    iv = logged_interval(beh)
    if iv is None:
        return ""
    ax.axvspan(iv[0], iv[1], color="#9467bd", alpha=0.12, lw=0, label="behaviour: logged cost's interval")
    off = behaviour_not_comparable(beh)
    return (f" Shaded: the logged cost's own 95% interval [{iv[0]:.4g}, {iv[1]:.4g}]; a side against the behaviour "
            "is claimed only where an interval lies clear of it" + (f" (not here: {off})" if off else "") + ".")


def _paired_words(m: dict[str, Any], top: dict[str, Any]) -> str:
    """Where the top estimator leads on the logging policy's own weights (``on_policy``), the
    caption's words on the paired difference the verdict reads instead (not drawn); else ''."""
    if not top.get("vs_logged") or logged_interval(m.get("behaviour_value") or {}) is None:
        return ""
    d = top["vs_logged"]
    return (f" {top['name'].upper()} leads on the logging policy's own weights: the logged cost is a mean of the same "
            f"episodes, so the verdict reads {top['name'].upper()}'s interval of the difference from it on the same "
            f"episodes, [{d[0]:.4g}, {d[1]:.4g}] (not drawn), against 0.")


def ratios_figure(figs: Figures, m: dict[str, Any], headline_method: str) -> None:
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
    figs.save(fig, "ratios",
              "Density ratios mu_pi^t / mu_data^t per step. Left: effective sample size by every method; "
              f"the headline quotes {head.get(headline_method, headline_method)}. The logs-only recursion shrinks "
              "towards 1 where a step has few states. Right: quantiles and max of the "
              f"{names.get(shown, shown)} ratios at single data states, and the max over regions of at least 20 "
              "states of the region's mean ratio up to its bootstrap 95% upper bound (the ratio PSDP's bound uses, "
              "for the recursion). A region mean can be below single-state quantiles: the upper bound bounds the "
              "region max, not single states.")


def coverage_figure(figs: Figures, run: Path, ratios: pd.DataFrame, features: list[str], axes: tuple[str, str],
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
        a1.scatter(xs[:, features.index(xa)], xs[:, features.index(ya)], s=2, alpha=0.4, color="k",
                   label="policy (simulator)")
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
                  + {"w_classifier": "classifier", "w_pooled": "pooled over time"}.get(wcol, "recursion") + ")",
                  fontsize=10)
    method = {"w_classifier": "classifier ratios from the simulator's rollouts", "w_pooled": "ratios pooled over time, "
              "from the logs alone"}.get(wcol, "the ratio recursion, from the logs alone")
    left = ("data by source with the policy's simulated states (left)" if simulated else
            "the data by source (left; no simulator was used, so the policy's own states are not shown)")
    figs.save(fig, "coverage", f"Coverage map: {left}; the density ratio w_t at every data state (right; {method}; "
              "bright = the policy goes there more often than the data).")


def sources_figure(figs: Figures, m: dict[str, Any]) -> None:
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


def traced_figure(figs: Figures, run: Path, features: list[str], traced: dict[str, str], dt: float | None,
                  sim: str) -> None:
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


#: The cost distributions of ``metrics.json`` ``cost_distribution``, in the order shown.
DISTRIBUTIONS = {"policy_rollouts": "policy (simulator rollouts)", "policy_logs": "policy (logs, importance-weighted)",
                 "demonstrator_rollouts": "demonstrator (simulator rollouts)", "behaviour_logged": "behaviour (logged)"}


DIST_COLOURS = {"policy_rollouts": "k", "policy_logs": "#1f77b4", "demonstrator_rollouts": "#2ca02c",
                "behaviour_logged": "#9467bd"}


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
    figs.save(fig, name,
              caption or (f"Distribution of the episode cost. Dot: the mean; thick bar at the top: CVaR_{alpha:g}"
                                     f", the mean of the worst {alpha:.0%} of episodes (dotted line: where that tail "
                                     "starts)."))


def cost_distribution_figure(figs: Figures, m: dict[str, Any]) -> None:
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
    distribution_figure(figs, dists,
                        f"episode cost sum_t gamma^t c_t over {est.get('horizon', m.get('horizon'))} steps",
                        caption="Distribution of the episode cost (the estimand per episode). Dot: the "
                        f"mean; thick bar at the top: CVaR_{a:g}, the mean of the worst {a:.0%} of episodes (dotted "
                                "line: where that tail starts)." + missing)


def command_figures(figs: Figures, policy: Any, ratios: pd.DataFrame, features: list[str], axes: tuple[str, str] | None,
                    units: dict[str, str], table: Any, logged: np.ndarray | None) -> None:
    """A continuous policy's figures: the policy map of each command component (continuous
    colours within the component's bounds, unsupported cells hatched) and, per component,
    the distribution of the policy's commands at the logged states against the logged ones."""
    plt = pyplot()
    dims, aunits = list(table.dims), [*table.units, *[""] * len(table.dims)]
    lo, hi = table.bounds()
    if axes is not None and all(a in features for a in axes):
        gx, gy, obs = _grid(ratios, features, axes)
        mask = _support_mask(ratios, axes, gx, gy)
        note = " (other features at their data medians)" if len(features) > 2 else ""
        u = np.asarray(policy.commands(obs, 0), np.float64)
        for j, d in enumerate(dims):
            fig, ax = plt.subplots(figsize=(6.6, 4.8))
            vmin, vmax = (lo[j], hi[j]) if np.isfinite(lo[j]) and np.isfinite(hi[j]) else (None, None)
            im = ax.pcolormesh(gx, gy, u[:, j].reshape(gx.shape), shading="auto", cmap="RdBu_r", vmin=vmin, vmax=vmax)
            _shade_unsupported(ax, gx, gy, mask)
            fig.colorbar(im, ax=ax).set_label(f"commanded {d}" + (f" [{aunits[j]}]" if aunits[j] else ""))
            ax.set_xlabel(_label(axes[0], units))
            ax.set_ylabel(_label(axes[1], units))
            ax.set_title(f"Policy map of {d} at t = 0" + note, fontsize=10)
            figs.save(fig, f"policy_map_{j}", f"Policy map of the command component {d!r} over two state features"
                      + note + "; colours span the component's bounds. Hatched grey: no logged state nearby (outside "
                      "the data's support, where the policy is extrapolated).")
    if logged is None or not len(logged):
        return
    mine = np.asarray(policy.commands(ratios[features].to_numpy(np.float64), ratios["step"].to_numpy()), np.float64)
    fig, axs = plt.subplots(1, len(dims), figsize=(4.2 * len(dims), 3.4), squeeze=False)
    for j, d in enumerate(dims):
        ax = axs[0, j]
        edges = np.histogram_bin_edges(np.r_[logged[:, j], mine[:, j]], bins=30)
        ax.hist(logged[:, j], bins=edges, alpha=0.55, label="logged", color="#888888", density=True)
        ax.hist(mine[:, j], bins=edges, alpha=0.55, label="policy at the logged states", color="#c0392b", density=True)
        ax.set_xlabel(f"{d}" + (f" [{aunits[j]}]" if aunits[j] else ""))
        ax.legend(fontsize=7)
    figs.save(fig, "commands", "Each command component: the policy's commands at the logged states against the "
              "logged commands (densities).")
