"""What ``offline-adp inspect`` shows: a dataset's schema, counts, coverage and statistics."""

from __future__ import annotations

from os import PathLike
from typing import Any

import numpy as np

from offline_adp.data import schema as S
from offline_adp.data.dataset import read_dataset
from offline_adp.data.io import read_quarantine


def dataset_summary(path: str | PathLike[str]) -> dict[str, Any]:
    """Schema, counts per source, action coverage, episode lengths and cost statistics of
    the dataset directory ``path`` (JSON-serialisable)."""
    ds = read_dataset(path)
    info = ds.info
    ep = ds.episode_table()
    a = ds.table.column(S.ACTION).to_numpy()
    cost = ds.table.column(S.COST).to_numpy()
    n_actions = ds.n_actions
    in_range = (a >= 0) & (a < n_actions)
    report: dict[str, Any] = {
        "path": str(path),
        "name": info.name,
        "problem": info.problem,
        "format_version": info.format_version,
        "transitions": len(ds),
        "episodes": ds.n_episodes,
        "features": [f"{f.name} [{f.unit}]" if f.unit else f.name for f in info.features],
        "actions": {
            "kind": info.action_table.kind,
            "dims": list(info.action_table.dims),
            "table": {n: list(v) for n, v in zip(info.action_table.names, info.action_table.values.tolist(),
                                                 strict=True)},
            "coverage": {n: int(c) for n, c in zip(info.action_table.names,
                                                   np.bincount(a[in_range], minlength=n_actions), strict=True)},
            "out_of_range": int((~in_range).sum()),
        },
        "per_source": {
            str(src): {
                "episodes": int(len(g)),
                "transitions": int(g["length"].sum()),
                "mean_total_cost": float(g["total_cost"].mean()),
                "terminated": int(g[S.TERMINATED].sum()),
            }
            for src, g in ep.groupby(S.SOURCE, observed=True)
        },
        "episode_length": {q: float(v) for q, v in zip(("min", "p25", "median", "p75", "max"),
                                                        np.quantile(ep["length"], [0, 0.25, 0.5, 0.75, 1]),
                                                        strict=True)}
        if len(ep) else {},
        "cost": {"mean": float(cost.mean()), "std": float(cost.std()), "min": float(cost.min()),
                 "max": float(cost.max())}
        if len(cost) else {},
        "gamma": info.gamma,
        "horizon": info.horizon,
        "propensities": info.propensity_source if ds.has_propensities else "none",
        "fingerprint": ds.fingerprint()[:16],
    }
    cmds = ds.commands() if info.action_table.kind == "continuous" else None
    if cmds is not None and len(cmds):
        t = info.action_table
        report["actions"]["commands"] = {
            "distinct": _distinct_rows(cmds),
            "logged_min": [float(x) for x in cmds.min(axis=0)], "logged_max": [float(x) for x in cmds.max(axis=0)],
            "low": None if t.low is None else list(t.low), "high": None if t.high is None else list(t.high)}
    q = read_quarantine(path)
    if q is not None:
        report["quarantined_rows"] = q.num_rows
    return report


def summary_text(report: dict[str, Any]) -> str:
    """The human form of :func:`dataset_summary`."""
    acts = report["actions"]
    lines = [f"{report['path']}  ({report['transitions']} transitions, {report['episodes']} episodes, "
             f"format {report['format_version']})",
             f"  features    {', '.join(report['features'])}", *_action_lines(acts)]
    for src, d in report["per_source"].items():
        lines.append(f"  {src:<13} {d['episodes']} episodes, {d['transitions']} transitions, mean episode cost "
                     f"{d['mean_total_cost']:.4g}, terminated {d['terminated']}")
    el = report["episode_length"]
    if el:
        lines.append(f"  ep. length  min {el['min']:.0f}  p25 {el['p25']:.0f}  median {el['median']:.0f}  "
                     f"p75 {el['p75']:.0f}  max {el['max']:.0f}")
    c = report["cost"]
    if c:
        lines.append(f"  cost/step   mean {c['mean']:.4g}  std {c['std']:.4g}  min {c['min']:.4g}  max {c['max']:.4g}")
    lines.append(f"  hints       gamma={report['gamma']} horizon={report['horizon']}; propensities: "
                 f"{report['propensities']}")
    if "quarantined_rows" in report:
        lines.append(f"  quarantine  {report['quarantined_rows']} rows (see quarantine/)")
    return "\n".join(lines)


def _distinct_rows(x: np.ndarray) -> int:
    """The number of distinct rows of a 2-D float array: a lexicographic sort and one pass
    (``np.unique(axis=0)`` took 2 s on 2M commands of 2 components)."""
    if len(x) == 0:
        return 0
    x = x + 0.0  # -0.0 == 0.0, as np.unique counts them
    o = np.lexsort(x.T[::-1])
    s = x[o]
    return int(1 + np.any(s[1:] != s[:-1], axis=1).sum())


#: entries of an action table listed one by one by ``inspect`` (``--json`` lists them all)
LISTED_ACTIONS = 24


def _action_lines(acts: dict[str, Any]) -> list[str]:
    """The action table and its coverage in a line each: every entry of a small table; for
    continuous commands the logged range and bounds of each component, and the coarse
    bins (kept for counts and behaviour models) summarised."""
    out = (f", (outside the action table): {acts['out_of_range']} (run offline-adp validate)"
           if acts["out_of_range"] else "")
    counts = np.asarray(list(acts["coverage"].values()), dtype=np.int64)
    if "commands" in acts:
        c = acts["commands"]
        dims = ", ".join(f"{d} logged [{lo:.4g}, {hi:.4g}]" + (f" of [{c['low'][i]:.4g}, {c['high'][i]:.4g}]"
                                                                 if c["low"] is not None else "")
                         for i, (d, lo, hi) in enumerate(zip(acts["dims"], c["logged_min"], c["logged_max"],
                                                             strict=True)))
        return [f"  actions     continuous, exact as logged ({c['distinct']} distinct commands): {dims}",
                f"  coverage    {len(counts)} coarse bins for counts and behaviour models: rows per bin min "
                f"{counts.min()}, median {np.median(counts):.0f}, max {counts.max()}; {int((counts == 0).sum())} "
                f"empty{out}"]
    entries = [f"{i}:{n} {v}" for i, (n, v) in enumerate(acts["table"].items())]
    cover = [f"{n}: {k}" for n, k in acts["coverage"].items()]
    more = len(entries) - LISTED_ACTIONS
    tail = f", ... ({more} more: inspect --json lists them)" if more > 0 else ""
    return [f"  actions     {acts['kind']} over {acts['dims']}: " + ", ".join(entries[:LISTED_ACTIONS]) + tail,
            "  coverage    " + ", ".join(cover[:LISTED_ACTIONS]) + tail + out]
