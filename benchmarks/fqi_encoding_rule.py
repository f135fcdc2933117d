"""Can a cheap statistic of the data choose the action encoding per problem? (issue #44)

Per-action structures (``mode="frozen", action_encoding="per_action"``: trees that split on the
action first) beat the joint default on car-on-the-hill and lose CartPole-v1
(docs/fqi-modes.md, "Car-on-the-hill against mushroom-rl"). This probes candidate rules for
choosing between them, all on the default frozen fit's own targets ``y_k = c + gamma (1 -
terminated) min_a Q_{k-1}(x', a)`` (the joint default's iterates, ``fit_iter``):

- ``first``: at the first build on non-constant targets (iteration 1, or 2 after constant
  costs; up to there both encodings run the same backups, so choosing there would cost one
  encoding's fit), the 5-fold cross-validated squared error (folds of whole episodes) of a
  joint and of an action-first forest of 10 trees (the early builds' count, the compiled
  builder, ``y`` without jitter); printed: their ratio per_action / joint for ``--draws``
  draws of the folds and the trees' seeds (a ratio below 1 would choose per_action).
- ``last``: the same at the last build (iteration 8 at gamma 0.95, 64 at 0.99), with a
  state-only forest too: the action's held-out share ``1 - MSE_joint / MSE_state`` and the
  ratio per_action / joint; and the action column's impurity importance (MDI) in a
  10-tree scikit-learn extra-trees forest on those targets.
- ``--fits``: the default (joint), ``per_action`` and ``hybrid`` (joint builds, then the last
  build and the settling with action-first trees) fits, in-process, one thread, and their
  scores (car-on-the-hill: the 289-state score; path tracking: minus the mean discounted
  cost of 200 rollouts; gymnasium: the mean return over 20 episodes, Pendulum 100, seeded
  10,000 + i) and CPU seconds.

Data: car-on-the-hill as ``benchmarks/fqi_vs_mushroom.py`` (1000 episodes, gamma 0.95); path
tracking as ``benchmarks/fqi_suite.py`` (50 + 150 episodes, gamma 0.95); gymnasium tasks as
``benchmarks/fqi_auto_iterations.py`` (50,000 random-play transitions, gamma 0.99), written
once under ``--out``.

    nice -n 10 python benchmarks/fqi_encoding_rule.py --tasks car_on_hill CartPole-v1 \
        [--data-seeds 0 1 2 3 4] [--learner-seeds 0 1] [--probes first last] [--draws 8] [--fits]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):  # one thread, before numpy loads
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
FOLDS, TREES = 5, 10


def load(task: str, seed: int, out: Path):
    """The task's dataset and gamma."""
    from offline_adp.simulate import simulate

    if task == "car_on_hill":
        return simulate("car_on_hill", 0, 1000, seed=seed, horizon=100), 0.95
    if task == "path_tracking":
        return simulate("path_tracking", 50, 150, seed=seed, horizon=100), 0.95
    from fqi_auto_iterations import collect

    from offline_adp.data.dataset import TransitionDataset

    return TransitionDataset.load(collect(task, 50_000, seed, out / f"{task}-s{seed}")), 0.99


def scorer(task: str, ds):
    """``policy -> (score, standard error)``."""
    if task == "car_on_hill":
        from offline_adp.envs.car_on_hill import score

        return lambda pi: (score(pi), 0.0)
    if task == "path_tracking":
        from offline_adp.envs import make_problem
        from offline_adp.rollout import rollout

        model = make_problem("path_tracking")
        return lambda pi: (-rollout(model, pi, 200, np.random.default_rng(123), horizon=100, gamma=0.95).mean, 0.0)
    from gym_returns import returns

    values = np.asarray(ds.info.action_table.values, np.float64).reshape(ds.info.n_actions, -1)

    def gym(pi):
        r, _ = returns(task, lambda x, t: values[pi.act_index(x, t)], 100 if task == "Pendulum-v1" else 20)
        return float(r.mean()), float(r.std(ddof=1) / np.sqrt(len(r)))

    return gym


def forest(kind: str, X: np.ndarray, y: np.ndarray, seed: int, n_action_columns: int) -> list:
    """``TREES`` compiled extra-trees (all features, fully grown) of one kind on ``(X, y)``."""
    from offline_adp.trees import builder as compiled
    from offline_adp.trees.action_first import grow_action_first
    from offline_adp.trees.compact import CompactTree

    p = compiled.TreeParams(n_estimators=TREES, max_features=X.shape[1], min_samples_split=2, min_samples_leaf=1,
                            max_depth=2**31 - 1, bootstrap=False, n_bootstrap=len(X), random_state=seed, n_jobs=1)
    if kind == "per_action":
        return [t for t, _ in grow_action_first(X, y, None, p, range(TREES), n_action_columns, record_leaves=False)]
    return compiled.grow_trees(X, y, None, p, finish=CompactTree.from_grown, record_leaves=False)


def cv_errors(X: np.ndarray, y: np.ndarray, episode: np.ndarray, seed: int, n_action_columns: int,
              kinds: tuple[str, ...]) -> dict[str, float]:
    """Each kind's held-out mean squared error over ``FOLDS`` folds of whole episodes (drawn with ``seed``);
    ``state``: a joint forest without the action columns."""
    eps, idx = np.unique(episode, return_inverse=True)
    folds = np.random.default_rng([seed, 44]).integers(0, FOLDS, len(eps))[idx]
    sse = dict.fromkeys(kinds, 0.0)
    for f in range(FOLDS):
        tr, va = folds != f, folds == f
        for kind in kinds:
            Xk = np.ascontiguousarray(X[:, :-n_action_columns] if kind == "state" else X)
            trees = forest("joint" if kind == "state" else kind, Xk[tr], y[tr], seed, n_action_columns)
            pred = np.mean([t.values[t.apply(Xk[va])] for t in trees], axis=0)
            sse[kind] += float(((pred - y[va]) ** 2).sum())
    return {k: v / len(y) for k, v in sse.items()}


def targets_at(ds, gamma: float, seed: int, ks: list[int]) -> dict[int, np.ndarray]:
    """The joint default fit's targets ``y_k`` at the iterations ``ks`` (``y_1 = c``)."""
    from offline_adp.algorithms.fqi import FittedQIteration

    a = ds.arrays()
    out = {1: a.cost.astype(np.float64)} if 1 in ks else {}
    f = FittedQIteration(gamma=gamma, random_state=seed, regressor_params={"n_jobs": 1})
    for row in f.fit_iter(ds):
        k = row["iteration"] + 1
        if k in ks:
            out[k] = a.cost + gamma * (1 - a.terminated.astype(np.float64)) * f.q_function_.values(a.next_obs).min(1)
        if k >= max(ks):
            break
    return out


def probes(task: str, ds, gamma: float, seed: int, which: list[str], draws: int) -> list[dict]:
    from sklearn.ensemble import ExtraTreesRegressor

    a = ds.arrays()
    values = np.asarray(ds.info.action_table.values, np.float64).reshape(ds.info.n_actions, -1)
    X = np.c_[a.obs, values[a.action]].astype(np.float32)
    na = values.shape[1]
    first = 1 if np.ptp(a.cost) > 0 else 2
    last = 8 if gamma == 0.95 else 64
    ys = targets_at(ds, gamma, seed, sorted({first, last} if "last" in which else {first}))
    recs = []
    if "first" in which:
        c0 = time.process_time()
        ratios = []
        for d in range(draws):
            e = cv_errors(X, ys[first], a.episode, 1000 * seed + d + 1, na, ("joint", "per_action"))
            ratios.append(e["per_action"] / e["joint"])
        recs.append({"probe": "first", "k": first, "ratios": [round(r, 3) for r in ratios],
                     "mean_ratio": round(float(np.mean(ratios)), 3), "below_1": int(np.sum(np.array(ratios) < 1)),
                     "cpu_per_draw": round((time.process_time() - c0) / draws, 2)})
    if "last" in which:
        y = ys[last]
        e = cv_errors(X, y, a.episode, 1000 * seed, na, ("state", "joint", "per_action"))
        mdi = ExtraTreesRegressor(n_estimators=TREES, max_features=1.0, random_state=seed + last).fit(X, y)
        recs.append({"probe": "last", "k": last, "action_share": round(1 - e["joint"] / e["state"], 4),
                     "per_action_over_joint": round(e["per_action"] / e["joint"], 4),
                     "action_mdi": round(float(mdi.feature_importances_[-na:].sum()), 4)})
    return recs


def fits(task: str, ds, gamma: float, seed: int) -> list[dict]:
    from offline_adp.algorithms.fqi import FittedQIteration
    from offline_adp.learn import frozen

    score, recs = scorer(task, ds), []
    build = frozen.FrozenTreesLearner._build
    for arm in ("joint", "per_action", "hybrid"):
        def hybrid(self, y, k, _build=build):  # the last scheduled build and after: action first
            if k == max(self.restructure_at):
                self.action_first = True
            return _build(self, y, k)

        frozen.FrozenTreesLearner._build = hybrid if arm == "hybrid" else build
        try:
            f = FittedQIteration(gamma=gamma, random_state=seed, regressor_params={"n_jobs": 1},
                                 **({"mode": "frozen", "action_encoding": "per_action"} if arm == "per_action" else {}))
            c0 = time.process_time()
            f.fit(ds)
            cpu = time.process_time() - c0
        finally:
            frozen.FrozenTreesLearner._build = build
        m, se = score(f.policy_)
        recs.append({"fit": arm, "score": round(m, 4), "se": round(se, 2), "cpu_s": round(cpu, 1)})
    return recs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", nargs="+", default=["car_on_hill", "CartPole-v1"])
    ap.add_argument("--data-seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--learner-seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--probes", nargs="*", default=["first", "last"], choices=["first", "last"])
    ap.add_argument("--draws", type=int, default=8)
    ap.add_argument("--fits", action="store_true")
    ap.add_argument("--out", default="/tmp/fqi_encoding_rule")
    args = ap.parse_args()
    for task in args.tasks:
        for s in args.data_seeds:
            ds, gamma = load(task, s, Path(args.out))
            for ls in args.learner_seeds:
                recs = probes(task, ds, gamma, ls, args.probes, args.draws) if args.probes else []
                recs += fits(task, ds, gamma, ls) if args.fits else []
                for r in recs:
                    print(json.dumps({"task": task, "data_seed": s, "learner_seed": ls, **r}), flush=True)


if __name__ == "__main__":
    main()
