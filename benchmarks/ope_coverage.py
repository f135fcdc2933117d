"""Coverage suite: do the intervals labelled 95% cover the simulator's truth, and is any verdict contradicted?

For each problem and data seed: simulate logs, fit a set of candidates of varied quality
(FQI with varied settings, including poor ones, plus the behaviour's own components:
the problem's demonstrator and exploration policies), and for each candidate

- the **truth**: Monte-Carlo rollouts of the same estimand (the T-step discounted cost from
  the problem's initial states, T and gamma as :func:`off_policy` declares them);
- the **evaluation exactly as a user sees it**: the metrics of ``offline-adp evaluate``
  (:func:`offline_adp.evaluation.run.evaluation_metrics`, the same builder as
  :func:`evaluate_run`) and their headline (:func:`offline_adp.evaluation.summary.headline`);
- per estimator: estimate, interval, whether it is labelled 95% (tier 0 "reliable" in
  :func:`rank_estimators`) and whether it covers the truth;
- the verdict with the simulator (the rollouts decide) and the **logs-only** verdict (the
  same metrics without ``rollout`` and the classifier shift diagnostic, which need a
  simulator; the off-policy estimates themselves do not depend on the simulator), each
  checked against the truth: *contradicted* when it claims better (worse) while the
  rollouts' 95% interval lies above (below) the behaviour's logged cost.

The fit's convergence enters the verdict (from ``run.json``): each FQI candidate gets a
run directory with its own fit verdict; the fixed policies (demonstrator, exploration)
are recorded as ``converged`` ("a fixed policy, not fitted").

Report per problem: coverage of every labelled interval (per estimator, and pooled over
the headline estimator), the share of candidates whose headline has a labelled interval,
and the verdicts contradicted (with and without the simulator).

    python benchmarks/ope_coverage.py --problems path_tracking --seeds 1 --size small --json cov.json
    python benchmarks/ope_coverage.py --problems path_tracking car_on_hill cartpole --seeds 1 2 --size full

Sizes: ``tiny`` (the CI test), ``small``, ``medium``, ``full`` (path_tracking 100+100 logged
episodes as ``offline-adp simulate path_tracking``, 500 truth rollouts). The gymnasium task
(``cartpole``: CartPole-v1 through :class:`offline_adp.envs.gym.GymResetModel`, uniformly
random logged actions, horizon 100) has no demonstrator; its candidates are the FQI fits,
the logging policy and a hand-written balancing heuristic.

**Continuous commands** (issue #41): ``path_tracking_steer`` (problem option ``commands =
"continuous"``: steering in [-0.3, 0.3] rad) and ``path_tracking_steer_accel`` (``"steer_accel"``:
steering and acceleration in [-2, 2] m/s^2), logged with the exact commands (the Stanley
demonstrator with unquantised noise, uniform exploration; 200 steps at ``small``). Their
candidates are deterministic command policies, evaluated by :mod:`offline_adp.evaluation.continuous`
through the same :func:`evaluation_metrics`: FQI over commands (``commands="continuous"``) with
the suite's settings (``fqi``, ``fqi_5it``, ``fqi_1it``, ``fqi_leaf50``, ``fqi_linear``) and 4
candidates (``fqi_cand4``), the demonstrator's noise-free controller (``demonstrator``) and the
command logged at the nearest logged state (``nearest``); held out (``--candidates holdout``):
FQI with another seed, LightGBM, ``min_samples_leaf = 20``, 3 iterations, 64 candidates, and
drivers the logs never saw (``sluggish``: Stanley gain 0.5 and speed gain 0.2; ``sharp``: 4.0
and 1.5; ``feedforward``: the demonstrator's gains plus the course's curvature ahead). The
uniform exploration and an epsilon-mixed fit sample their commands: not evaluable over
commands (refused), so not candidates. Each row also records FQE's interval as shown,
labelled or not (``fqe``: coverage, level or the reason it has none, width over the value
range, unsupported share). Measured (docs/continuous-commands.md, "Coverage"; seed 1 was the
design seed, 2-3 and the held-out set on 4 were run once the rules were fixed):

=========================  ==========  ==========  ===============  ====================  ===================
problem                    seed (set)  labelled    labelled         FQE as shown          logs-only claims
                                       covered     width / range    (labelled or not)     (agree); contradicted
=========================  ==========  ==========  ===============  ====================  ===================
path_tracking_steer        1 (design)  6/7         0.11             7/8                   3 (3); 0
path_tracking_steer        2           5/6         0.07             6/8                   4 (3); 0
path_tracking_steer        3           6/6         0.09             7/8                   3 (3); 0
path_tracking_steer        4 (holdout) 6/6         0.10             8/8                   4 (4); 0
path_tracking_steer_accel  1 (design)  7/7         0.14             8/8                   3 (3); 0
path_tracking_steer_accel  2           6/6         0.11             7/8                   4 (4); 0
path_tracking_steer_accel  3           6/6         0.14             8/8                   4 (4); 0
path_tracking_steer_accel  4 (holdout) 6/6         0.12             8/8                   4 (4); 0
=========================  ==========  ==========  ===============  ====================  ===================

On seeds 2-4: steering 17/18 (0.94), steering + acceleration 18/18. Seed 1 ran before the
replay rule (evaluation/continuous.py): its labelled miss is the nearest-command clone, whose
level that rule now withdraws.

    python benchmarks/ope_coverage.py --problems path_tracking_steer path_tracking_steer_accel --seeds 1 --size small
    python benchmarks/ope_coverage.py --problems path_tracking_steer path_tracking_steer_accel --seeds 2 3 --size small
    python benchmarks/ope_coverage.py --problems path_tracking_steer path_tracking_steer_accel --seeds 4 --size small \
        --candidates holdout
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.evaluation.fqe_interval import q_value_range
from offline_adp.evaluation.run import evaluation_metrics, json_safe
from offline_adp.evaluation.summary import ESTIMATOR_NAMES, headline
from offline_adp.evaluation.summary import side_of_behaviour as _side
from offline_adp.policies import CommandPolicy, EpsilonPolicy, attach_signature

#: (demonstration episodes, exploration episodes, truth rollouts, horizon cap or None). The truth's
#: own Monte-Carlo error must be small against the intervals it checks: car_on_hill's logging
#: policy has DR intervals ~0.013 wide, and 200 rollouts read its value at 0.1395 and 0.1207
#: (4000: 0.127), so car_on_hill takes 2000 (its rollouts are cheap). Horizons keep
#: gamma^T < 0.01 so the evaluation takes the stationary FQE with its cheap structure-conditional
#: bootstrap (estimand.TAIL_NEGLIGIBLE); a shorter T refits FQE per replicate (minutes per candidate).
SIZES = {
    "tiny": {"path_tracking": (10, 10, 40, None), "car_on_hill": (0, 60, 40, None), "cartpole": (0, 30, 40, 100),
             "path_tracking_steer": (8, 8, 40, 100), "path_tracking_steer_accel": (8, 8, 40, 100)},
    "small": {"path_tracking": (30, 30, 200, None), "car_on_hill": (0, 200, 2000, None), "cartpole": (0, 60, 200, 100),
              "path_tracking_steer": (30, 30, 200, None), "path_tracking_steer_accel": (30, 30, 200, None)},
    "medium": {"path_tracking": (60, 60, 300, None), "car_on_hill": (0, 400, 2000, None),
               "cartpole": (0, 100, 300, 100),
               "path_tracking_steer": (60, 60, 300, None), "path_tracking_steer_accel": (60, 60, 300, None)},
    "full": {"path_tracking": (100, 100, 500, None), "car_on_hill": (0, 1000, 500, None),
             "cartpole": (0, 200, 500, 100),
             "path_tracking_steer": (100, 100, 500, None), "path_tracking_steer_accel": (100, 100, 500, None)},
}
#: continuous-command problems: name -> (reference problem, its options). Their candidates are
#: deterministic command policies (FittedQEvaluation over commands evaluates ``pi(x)``; a
#: stochastic behaviour such as the uniform exploration is refused, so it is no candidate).
CONTINUOUS = {"path_tracking_steer": ("path_tracking", {"commands": "continuous"}),
              "path_tracking_steer_accel": ("path_tracking", {"commands": "steer_accel"})}
PROBLEMS = ["path_tracking", "car_on_hill", "cartpole", *CONTINUOUS]
#: FQI settings as the problem's pipeline uses them (pipelines/driving.toml, car_on_hill.toml)
FIT = {"path_tracking": {"gamma": 0.95, "infeasible_cost": 50.0, "tol": 1e-3},
       "car_on_hill": {"gamma": 0.95, "tol": 1e-3},
       "cartpole": {"gamma": 0.95, "tol": 1e-3},
       # over the exact commands (FittedQIteration(commands="continuous"), 16 candidates unless a candidate says)
       "path_tracking_steer": {"gamma": 0.95, "infeasible_cost": 50.0, "tol": 1e-3, "commands": "continuous"},
       "path_tracking_steer_accel": {"gamma": 0.95, "infeasible_cost": 50.0, "tol": 1e-3, "commands": "continuous"}}
#: candidate name -> FQI settings on top of FIT (None: a fixed policy of the problem)
CANDIDATES: dict[str, dict[str, Any] | None] = {
    "fqi": {},
    "fqi_5it": {"n_iterations": 5},
    "fqi_1it": {"n_iterations": 1},
    "fqi_leaf50": {"regressor_params": {"min_samples_leaf": 50}},
    "fqi_linear": {"regressor": "linear"},
    "fqi_knn": {"regressor": "knn"},
    "demonstrator": None,
    "exploration": None,
    # continuous-command problems only (a FQI setting the discrete problems have no use for, and
    # the one-nearest-neighbour clone of the logged commands)
    "fqi_cand4": {"n_candidates": 4},
    "nearest": None,
}
#: candidates of the continuous problems (``fqi_eps30`` and ``exploration`` are stochastic: not evaluable
#: over commands; ``demonstrator`` is its noise-free controller)
CONTINUOUS_CANDIDATES = ["fqi", "fqi_5it", "fqi_1it", "fqi_leaf50", "fqi_linear", "fqi_cand4", "demonstrator",
                         "nearest"]
CONTINUOUS_HOLDOUT = ["fqi_seed7", "fqi_lightgbm", "fqi_leaf20", "fqi_3it", "fqi_cand64", "sluggish", "sharp",
                      "feedforward"]
#: a second set, never used to choose a rule (``--set holdout``): other learners and settings, an
#: epsilon-mixed fit, and (path_tracking) drivers with other gains than the logged demonstrator's
HOLDOUT: dict[str, dict[str, Any] | None] = {
    "fqi_seed7": {"random_state": 7},
    "fqi_lightgbm": {"regressor": "lightgbm"},
    "fqi_leaf20": {"regressor_params": {"min_samples_leaf": 20}},
    "fqi_3it": {"n_iterations": 3},
    "fqi_eps30": {"epsilon": 0.3},
    "sluggish": None,
    "sharp": None,
    # continuous-command problems only: more candidates, and a driver with curvature feed-forward
    "fqi_cand64": {"n_candidates": 64},
    "feedforward": None,
}


class _CartPole:
    """CartPole-v1 as a logging problem: the gymnasium reset model plus what ``collect`` needs."""

    name = "gym:CartPole-v1"

    def __init__(self, horizon: int) -> None:
        from offline_adp.data.info import ActionTable, DatasetInfo, Feature
        from offline_adp.envs.gym import GymResetModel

        self.info = DatasetInfo(features=tuple(Feature(n) for n in ("cart_x", "cart_v", "pole", "pole_rate")),
                                action_table=ActionTable.from_values([0.0, 1.0]), gamma=0.95, horizon=horizon)
        self.model = GymResetModel("CartPole-v1", self.info)
        self.horizon = horizon

    def dataset_info(self, **_: Any) -> Any:
        return self.info

    def initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return self.model.initial_states(n, rng)

    def step(self, states: np.ndarray, actions: np.ndarray, rng: np.random.Generator) -> Any:
        return self.model.step(states, actions, rng)

    def exploration(self) -> Any:
        from offline_adp.policies import UniformPolicy

        return UniformPolicy(2)

    def heuristic(self) -> Any:
        from offline_adp.policies import FunctionPolicy

        return FunctionPolicy(lambda x, t=0: (np.asarray(x)[:, 2] + 0.5 * np.asarray(x)[:, 3] > 0).astype(np.int64), 2)


class _Driver(CommandPolicy):
    """A deterministic driver over path_tracking's commands: Stanley steering
    ``-(e_psi + atan(gain e / v))`` plus, with ``feedforward``, the course's curvature
    ``atan(L kappa_ahead)``; with acceleration, the speed keeper ``-speed_gain (v - 8)``.
    ``gain=1.5, speed_gain=0.5`` without feed-forward is the demonstrator's noise-free
    controller (its ``commands``)."""

    def __init__(self, gain: float, two: bool, speed_gain: float = 0.5, feedforward: bool = False) -> None:
        self.gain, self.two, self.speed_gain, self.feedforward = gain, two, speed_gain, feedforward

    def commands(self, obs: np.ndarray, t: Any = 0) -> np.ndarray:
        from offline_adp.envs.path_tracking import V_TARGET, WHEELBASE

        x = np.asarray(obs, np.float64)
        steer = -(x[:, 2] + np.arctan(self.gain * x[:, 1] / np.maximum(x[:, 4], 0.1)))
        if self.feedforward:
            steer = steer + np.arctan(WHEELBASE * x[:, 6])
        u = np.column_stack([steer, -self.speed_gain * (x[:, 4] - V_TARGET)]) if self.two else steer[:, None]
        return self.clip(u)


def _continuous_fixed(prob: Any, ds: Any) -> dict[str, Any]:
    """The fixed candidates of a continuous-command problem: the demonstrator's noise-free
    controller, the one-nearest-neighbour clone of the logged commands, and (held out) drivers
    the logs never saw: a lazier and a sharper Stanley gain (and speed keeper), and a driver
    with curvature feed-forward."""
    from offline_adp.policies import NearestCommandPolicy
    from offline_adp.qfunctions import NeighbourCommands

    two = prob.commands == "steer_accel"
    a = ds.arrays()
    fixed = {"demonstrator": _Driver(1.5, two),
             "nearest": NearestCommandPolicy(NeighbourCommands.from_data(a.obs, ds.commands(), 1)),
             "sluggish": _Driver(0.5, two, speed_gain=0.2), "sharp": _Driver(4.0, two, speed_gain=1.5),
             "feedforward": _Driver(1.5, two, feedforward=True)}
    return {k: attach_signature(v, ds) for k, v in fixed.items()}


def logs_and_problem(problem: str, size: str, seed: int) -> tuple[Any, Any, dict[str, Any]]:
    """(dataset, simulator, fixed policies) for one problem and data seed."""
    from offline_adp.envs import make_problem
    from offline_adp.simulate import simulate

    n_demo, n_expl, _, H = SIZES[size][problem]
    if problem in CONTINUOUS:
        base, opts = CONTINUOUS[problem]
        ds = simulate(base, n_demo, n_expl, seed=seed, horizon=H, problem_options=opts)
        prob = make_problem(base, **opts, **({"horizon": H} if H is not None else {}))
        return ds, prob, _continuous_fixed(prob, ds)
    if problem == "cartpole":
        from offline_adp.rollout import collect

        prob = _CartPole(H)
        ds = collect(prob, prob.exploration(), n_expl, np.random.default_rng(seed), horizon=H, source="exploration")
        return ds, prob.model, {"exploration": prob.exploration(), "heuristic": prob.heuristic()}
    ds = simulate(problem, n_demo, n_expl, seed=seed, horizon=H)
    prob = make_problem(problem, **({"horizon": H} if H is not None else {}))
    # car_on_hill logs exploration only (as its pipeline); its demonstrator is still a candidate
    fixed = {"demonstrator": prob.demonstrator(), "exploration": prob.exploration()}
    if problem == "path_tracking":  # drivers the logs never saw: a lazier and a sharper Stanley gain
        fixed.update(sluggish=prob.demonstrator(gain=0.5, epsilon=0.0), sharp=prob.demonstrator(gain=4.0, epsilon=0.0))
    return ds, prob, fixed


def _covers(iv: list[float] | None, truth: float) -> bool | None:
    """Does the interval hold the truth (up to float rounding: a clipped bound equals the
    possible range's end, which deterministic rollouts reach exactly)?"""
    if iv is None:
        return None
    tol = 1e-9 * max(1.0, abs(truth))
    return bool(iv[0] - tol <= truth <= iv[1] + tol)


def _recover(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Recompute the coverage flags of stored rows (rows from older outputs)."""
    for r in rows:
        for e in r["estimators"].values():
            e["covers"] = _covers(e["interval"], r["truth"])
        if r.get("fqe"):
            r["fqe"]["covers"] = _covers(r["fqe"]["interval"], r["truth"])
        r["headline_covers"] = None if r["headline"] is None else r["estimators"][r["headline"]]["covers"]
    return rows


def _check(performance: str, truth_side: str) -> str:
    """'contradicted' (claimed the opposite side of the truth), 'unconfirmed' (claimed a side,
    the truth cannot tell), 'agrees', or 'no claim'."""
    if performance not in ("better", "worse"):
        return "no claim" if performance != truth_side else "agrees"
    if truth_side == performance:
        return "agrees"
    return "unconfirmed" if truth_side == "indistinguishable" else "contradicted"


def _logs_only(m: dict[str, Any]) -> dict[str, Any]:
    """The metrics a user without a simulator gets: no rollouts, no classifier ratios, no
    reference-policy ratios (the off-policy estimates do not depend on them)."""
    out = {k: v for k, v in m.items() if k not in ("rollout", "named", "headline")}
    out["shift"] = {k: v for k, v in m["shift"].items() if k == "recursion"}
    out["ope"] = {k: _level_back({kk: vv for kk, vv in v.items() if kk != "rollout_error"})
                  for k, v in m["ope"].items()}
    return out


def _level_back(r: dict[str, Any]) -> dict[str, Any]:
    """An estimator's entry with a level withdrawn by the support findings (``withdrawn_by:
    "support"``, set by ``evaluation.run``: they read the simulator's ratios) restored: a user
    without a simulator never had those findings, and ``headline`` withdraws again whatever the
    logs alone show. A level withdrawn from the logs alone (``withdrawn_by: "replay"``: a
    continuous policy replaying the logged commands) stays withdrawn."""
    if "nominal_level" not in r or r.get("withdrawn_by") != "support":
        return r
    drop = ("nominal_level", "level_note", "withdrawn_by", "nominal_vs_logged")
    paired = {"vs_logged": r["nominal_vs_logged"]} if r.get("nominal_vs_logged") is not None else {}
    return {**{k: v for k, v in r.items() if k not in drop}, **paired, "level": r["nominal_level"]}


def _model_summary(mr: dict[str, Any]) -> dict[str, Any]:
    """The model rollouts' reading and what its interval is made of (the bootstrap's spread,
    its parts and its bias), for a row."""
    boot = mr.get("bootstrap") or {}
    return {**{k: mr.get(k) for k in ("estimate", "interval", "exit_mass", "exit_share", "past_data_cost", "skipped",
                                      "fqe_interval", "fqe_bootstrap_interval")},
            "bootstrap": {k: boot.get(k) for k in ("interval", "spread", "bias", "particles", "skipped")}}


def _run_dir(tmp: Path, name: str, est: Any | None) -> Path:
    """A run directory holding only what the headline reads: the fit's convergence verdict."""
    d = tmp / name
    (d / "model").mkdir(parents=True, exist_ok=True)
    if est is None:
        info = {"verdict": "converged", "verdict_message": "a fixed policy, not fitted"}
    else:
        info = {"verdict": getattr(est, "verdict_", None), "verdict_message": getattr(est, "verdict_message_", None)}
    (d / "run.json").write_text(json.dumps(info))
    (d / "config.json").write_text(json.dumps({"params": {"tol": getattr(est, "tol", None)}}))
    return d


def evaluate_candidates(problem: str, size: str, seed: int, candidates: list[str] | None = None,
                        n_boot: int = 200, say: Any = print,
                        options: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """One row per candidate (see the module docstring). ``options``: evaluation settings over
    the defaults a user gets (the tests' fewer replicates and particles; never for a measurement)."""
    ds, sim, fixed = logs_and_problem(problem, size, seed)
    n_truth, H = SIZES[size][problem][2], SIZES[size][problem][3]
    if problem in CONTINUOUS:
        names = list(CONTINUOUS_HOLDOUT if candidates == ["holdout"] else candidates or CONTINUOUS_CANDIDATES)
    else:
        names = list(candidates or [c for c in CANDIDATES if CANDIDATES[c] is not None or c in fixed])
        if candidates == ["holdout"]:
            names = [c for c in HOLDOUT if HOLDOUT[c] is not None or c in fixed]
        names = [c for c in names if c not in ("fqi_cand4", "fqi_cand64", "nearest", "feedforward")]
        if problem == "cartpole" and candidates is None:  # (the holdout set's fits apply to every problem)
            names = [c for c in names if c != "demonstrator"] + ["heuristic"]
    say(f"{problem} seed {seed}: {len(ds)} transitions, {len(ds.episode_ids)} episodes; candidates {names}")
    a = ds.arrays()
    # the range any discounted value can take (the width of an interval is read against it)
    value_range = q_value_range(a.cost, a.terminated, FIT[problem]["gamma"], FIT[problem].get("infeasible_cost"))
    value_span = value_range[1] - value_range[0]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            t0 = time.perf_counter()
            spec = CANDIDATES.get(name, HOLDOUT.get(name))
            est = None
            if spec is None:
                policy = fixed[name]
            else:
                spec = dict(spec)
                eps = spec.pop("epsilon", None)
                params = {"random_state": seed, **FIT[problem], **spec}
                est = FittedQIteration(**params).fit(ds)
                policy = est.policy_ if eps is None else EpsilonPolicy(est.policy_, eps)
                if problem in CONTINUOUS and not getattr(policy, "continuous", False):
                    raise ValueError(f"{problem}: candidate {name} is not a command policy")
            run = _run_dir(Path(tmp), name, est)
            # the horizon the logs were made with (a gym simulator would otherwise roll out to its own
            # time limit, 500 steps for CartPole, while the documented estimand is H steps)
            m, _res, _s, _d = evaluation_metrics(ds, policy, sim, sim_name=problem, horizon=H, seed=seed, run_dir=run,
                                                 **{"n_episodes": n_truth, "n_boot": n_boot, "n_boot_fqe": None,
                                                    **(options or {})})
            m = json_safe(m)
            h = m["headline"]
            lo_only = _logs_only(m)
            h_logs = headline(lo_only, run)
            ro = m["rollout"]["policy"]
            truth, (t_lo, t_hi) = ro["mean_discounted_cost"], ro["interval"]
            b = m["behaviour_value"]["mean"] if m.get("behaviour_value") else None
            truth_side = _side(t_lo, t_hi, b) if b is not None else "unknown"
            ests = {}
            for e in h["ranking"]:
                iv = e["interval"]
                ests[e["name"]] = {"estimate": e["estimate"], "interval": iv, "tier": e["tier"],
                                   "labelled_95": e["tier"] == 0 and e.get("level") == 0.95,
                                   "covers": _covers(iv, truth)}
            best = h["best"]
            best_logs = h_logs["best"]
            logs_iv = best_logs["interval"] if best_logs and best_logs.get("level") == 0.95 else None
            fq = m["ope"].get("fqe") or {}
            shown = fq.get("interval") if fq.get("interval") and all(np.isfinite(fq["interval"])) else None
            row_fqe = {"estimate": fq.get("estimate"), "interval": shown, "covers": _covers(shown, truth),
                       "level": fq.get("level"), "nominal_level": fq.get("nominal_level"),
                       "level_note": fq.get("level_note"), "percentile_interval": fq.get("percentile_interval"),
                       "width_over_range": None if shown is None else (shown[1] - shown[0]) / value_span,
                       "unsupported": ((m.get("behaviour") or {}).get("support_violations") or {}).get("fraction")}
            row = {"problem": problem, "seed": seed, "candidate": name, "truth": truth, "truth_interval": [t_lo, t_hi],
                   "behaviour_logged": b, "truth_side": truth_side,
                   "fit_verdict": None if est is None else est.verdict_,
                   "headline": None if best is None else best["name"],
                   "headline_estimate": None if best is None else best["estimate"],
                   "headline_interval": None if best is None else best["interval"],
                   "headline_covers": None if best is None else ests[best["name"]]["covers"],
                   "headline_width_over_range": None if best is None or best["interval"] is None
                   else (best["interval"][1] - best["interval"][0]) / value_span,
                   # what a user without a simulator reads: the logs-only headline's labelled interval
                   "logs_only_headline": None if logs_iv is None else
                   {"name": best_logs["name"], "estimate": best_logs["estimate"], "interval": logs_iv,
                    "covers": _covers(logs_iv, truth), "width_over_range": (logs_iv[1] - logs_iv[0]) / value_span},
                   "estimators": ests, "fqe": row_fqe, "value_range": list(value_range),
                   "model_rollouts": _model_summary(m["ope"]["fqe"].get("model_rollouts") or {}),
                   "verdict": {"performance": h["verdict"]["performance"], "text": h["verdict"]["text"],
                               "check": _check(h["verdict"]["performance"], truth_side)},
                   "verdict_logs_only": {"performance": h_logs["verdict"]["performance"],
                                         "text": h_logs["verdict"]["text"],
                                         "check": _check(h_logs["verdict"]["performance"], truth_side)},
                   "seconds": time.perf_counter() - t0}
            rows.append(row)
            say(f"  {name:13s} truth {truth:9.4g} [{t_lo:.4g}, {t_hi:.4g}]  headline "
                + (f"{best['name'].upper()} {best['estimate']:.4g} [{best['interval'][0]:.4g}, "
                   f"{best['interval'][1]:.4g}] "
                   f"{'covers' if row['headline_covers'] else 'MISSES'}" if best else "none labelled")
                + f"  verdict {row['verdict']['performance']} ({row['verdict']['check']}), logs-only "
                  f"{row['verdict_logs_only']['performance']} ({row['verdict_logs_only']['check']})  "
                  f"{row['seconds']:.0f} s")
    return rows


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per problem: coverage of labelled intervals (per estimator; pooled over the headline
    estimator), share of candidates with a labelled headline, verdict checks."""
    out: dict[str, Any] = {}
    for p in dict.fromkeys(r["problem"] for r in rows):
        rs = [r for r in rows if r["problem"] == p]
        per: dict[str, list[int]] = {}
        for r in rs:
            for name, e in r["estimators"].items():
                c = per.setdefault(name, [0, 0])
                if e["labelled_95"]:
                    c[0] += int(bool(e["covers"]))
                    c[1] += 1
        head = [r for r in rs if r["headline"] is not None and r["estimators"][r["headline"]]["labelled_95"]]
        count = lambda key, what, rs=rs: sum(r[key]["check"] == what for r in rs)  # noqa: E731
        out[p] = {"candidates": len(rs),
                  "labelled_share": len(head) / len(rs) if rs else None,
                  "headline_coverage": (sum(bool(r["headline_covers"]) for r in head) / len(head)) if head else None,
                  "headline_covered": sum(bool(r["headline_covers"]) for r in head), "headline_labelled": len(head),
                  "per_estimator": {k: {"covered": v[0], "labelled": v[1], "coverage": v[0] / v[1] if v[1] else None}
                                    for k, v in per.items()},
                  "contradicted_with_simulator": count("verdict", "contradicted"),
                  "contradicted_logs_only": count("verdict_logs_only", "contradicted"),
                  "unconfirmed_logs_only": count("verdict_logs_only", "unconfirmed"),
                  # "not distinguishable" from the logs while the rollouts put the policy on one side
                  "missed_logs_only": sum(r["verdict_logs_only"]["performance"] == "indistinguishable"
                                          and r["truth_side"] in ("better", "worse") for r in rs),
                  "claims_logs_only": sum(r["verdict_logs_only"]["performance"] in ("better", "worse") for r in rs)}
        # the candidates whose true value differs from the behaviour's logged cost by more than 20%, and how
        # many of them the logs alone put on the right side
        apart = [r for r in rs if r["behaviour_logged"] is not None
                 and abs(r["truth"] - r["behaviour_logged"]) > 0.2 * abs(r["behaviour_logged"])]
        lo_head = [r["logs_only_headline"] for r in rs if r.get("logs_only_headline")]
        out[p].update(apart=len(apart), apart_claimed_right=sum(r["verdict_logs_only"]["check"] == "agrees"
                                                               and r["verdict_logs_only"]["performance"]
                                                               in ("better", "worse") for r in apart),
                      logs_only_labelled=len(lo_head), logs_only_covered=sum(bool(x["covers"]) for x in lo_head),
                      logs_only_median_width=float(np.median([x["width_over_range"] for x in lo_head]))
                      if lo_head else None,
                      median_headline_width_over_range=_median([r.get("headline_width_over_range") for r in head]))
        # FQE's interval as shown, labelled or not (how the continuous interval's coverage was measured
        # before it carried a level), and the widths of the labelled headline intervals
        shown = [r["fqe"] for r in rs if (r.get("fqe") or {}).get("interval") is not None]
        widths = [r["fqe"]["width_over_range"] for r in head if r["headline"] == "fqe" and r.get("fqe")]
        out[p].update(fqe_shown_covered=sum(bool(f["covers"]) for f in shown), fqe_shown=len(shown),
                      fqe_shown_coverage=sum(bool(f["covers"]) for f in shown) / len(shown) if shown else None,
                      median_width_over_range=float(np.median(widths)) if widths else None,
                      median_shown_width_over_range=float(np.median([f["width_over_range"] for f in shown]))
                      if shown else None)
    return out


def _median(xs: list[Any]) -> float | None:
    """The median of the values that are there (rows of earlier runs may lack a field)."""
    xs = [x for x in xs if x is not None]
    return float(np.median(xs)) if xs else None


def _fmt(x: Any) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def table(summary: dict[str, Any], rows: list[dict[str, Any]]) -> str:
    lines = ["| problem | candidates | labelled share | headline coverage | per-estimator coverage (covered/labelled) "
             "| contradicted (sim) | contradicted (logs only) | logs-only claims (unconfirmed) | logs-only 'not "
             "distinguishable', "
             "truth one-sided | FQE interval as shown, labelled or not: covered | median labelled FQE width / "
             "value range |",
             "|" + "---|" * 11]
    for p, s in summary.items():
        per = ", ".join(f"{k.upper()} {v['covered']}/{v['labelled']}" for k, v in s["per_estimator"].items()
                        if v["labelled"])
        lines.append(f"| {p} | {s['candidates']} | {_fmt(s['labelled_share'])} | {_fmt(s['headline_coverage'])} "
                     f"({s['headline_covered']}/{s['headline_labelled']}) | {per or 'none'} | "
                     f"{s['contradicted_with_simulator']} | {s['contradicted_logs_only']} | "
                     f"{s['claims_logs_only']} ({s['unconfirmed_logs_only']}) | {s['missed_logs_only']} | "
                     f"{s.get('fqe_shown_covered', 'n/a')}/{s.get('fqe_shown', 'n/a')} | "
                     f"{_fmt(s.get('median_width_over_range'))} |")
    lines += ["", "| problem | median labelled headline width / value range | logs only: labelled headline covered "
              "| logs only: median labelled width / range | true value >20% from the behaviour's | of them, claimed "
              "right from the logs |", "|" + "---|" * 6]
    for p, s in summary.items():
        lines.append(f"| {p} | {_fmt(s.get('median_headline_width_over_range'))} | "
                     f"{s.get('logs_only_covered', 'n/a')}/{s.get('logs_only_labelled', 'n/a')} | "
                     f"{_fmt(s.get('logs_only_median_width'))} | {s.get('apart', 'n/a')} | "
                     f"{s.get('apart_claimed_right', 'n/a')} |")
    lines += ["",
              "| problem | seed | candidate | truth [95%] | behaviour logged | headline estimate [interval] | covers "
              "| verdict (sim) | verdict (logs only) |", "|" + "---|" * 9]
    for r in rows:
        iv = r["headline_interval"]
        f = r.get("fqe") or {}
        est = (f"{r['headline'].upper()} {r['headline_estimate']:.3g} [{iv[0]:.3g}, {iv[1]:.3g}]" if r["headline"]
               else f"none labelled (FQE {f['estimate']:.3g} [{f['interval'][0]:.3g}, {f['interval'][1]:.3g}], "
                    f"{'covers' if f['covers'] else 'MISSES'}; unsupported {f['unsupported']})"
               if f.get("interval") else "none labelled")
        lines.append(f"| {r['problem']} | {r['seed']} | {r['candidate']} | {r['truth']:.3g} "
                     f"[{r['truth_interval'][0]:.3g}, {r['truth_interval'][1]:.3g}] | "
                     f"{r['behaviour_logged']:.3g} | {est} | "
                     f"{'-' if r['headline_covers'] is None else 'yes' if r['headline_covers'] else 'NO'} | "
                     f"{r['verdict']['performance']} ({r['verdict']['check']}) | "
                     f"{r['verdict_logs_only']['performance']} ({r['verdict_logs_only']['check']}) |")
    return "\n".join(lines)


def run_suite(problems: list[str], seeds: list[int], size: str, candidates: list[str] | None = None,
              n_boot: int = 200, say: Any = print, options: dict[str, Any] | None = None) -> dict[str, Any]:
    rows = [
        r for p in problems for s in seeds for r in evaluate_candidates(p, size, s, candidates, n_boot, say, options)
    ]
    return {"size": size, "problems": problems, "seeds": seeds, "summary": summarise(rows), "rows": rows,
            "estimator_names": ESTIMATOR_NAMES}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problems", nargs="+", default=["path_tracking", "car_on_hill", "cartpole"], choices=PROBLEMS)
    ap.add_argument("--seeds", nargs="+", type=int, default=[1])
    ap.add_argument("--size", choices=list(SIZES), default="small")
    ap.add_argument("--candidates", nargs="+", default=None,
                    help=f"subset of {list(CANDIDATES)} (+ heuristic for cartpole), or 'holdout' for the "
                         f"second set {list(HOLDOUT)}; continuous problems: {CONTINUOUS_CANDIDATES}, holdout "
                         f"{CONTINUOUS_HOLDOUT}")
    ap.add_argument("--bootstrap", type=int, default=200, help="bootstrap replicates of the IS family")
    ap.add_argument("--json", type=Path, default=None, help="write every row and the summary here")
    ap.add_argument("--rows-from", type=Path, nargs="+", default=None,
                    help="re-summarise the rows of earlier --json outputs instead of running")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    if args.rows_from:
        rows = _recover([r for f in args.rows_from for r in json.loads(f.read_text())["rows"]])
        out = {"size": None, "problems": list(dict.fromkeys(r["problem"] for r in rows)), "rows": rows,
               "summary": summarise(rows), "estimator_names": ESTIMATOR_NAMES}
    else:
        out = run_suite(args.problems, args.seeds, args.size, args.candidates, args.bootstrap)
    print()
    print(table(out["summary"], out["rows"]))
    print(f"\n{time.perf_counter() - t0:.0f} s")
    if args.json:
        args.json.write_text(json.dumps(json_safe(out), indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
