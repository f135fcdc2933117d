"""Model rollouts of the logs (docs/evaluation.md, section 2, "Model rollouts").

A lane-keeping system with a known simulator: the lateral offset ``x`` drifts outward
on its own (``x' = 1.03 x + 0.05 a + noise``, actions {-1, 0, +1}), each step costs
``|x'| + 0.01 a^2``, and leaving the lane (``|x'| > 1``) ends the episode at cost 5. The
logs come from a stabilising driver (10% random commands) and from uniformly random
commands, which drift out and fail (as path_tracking's exploration does). The truth is
Monte-Carlo rollouts of the simulator itself.
"""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp.access import ResetModel, StepResult
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.errors import InvalidArgumentError
from offline_adp.evaluation.fqe_interval import widen_fqe
from offline_adp.evaluation.model_rollouts import (
    EXIT_FRACTION,
    SUPPORT_QUANTILE,
    LoggedDynamics,
    model_rollout_value,
    model_rollouts,
    remainder_ranges,
)
from offline_adp.evaluation.offpolicy import off_policy
from offline_adp.evaluation.ope import OPEResult
from offline_adp.policies import EpsilonPolicy, FunctionPolicy, Policy, UniformPolicy
from offline_adp.rollout import collect, rollout

GAMMA, T = 0.95, 100


class Lane(ResetModel):
    n_actions, obs_dim, gamma, horizon, name = 3, 1, GAMMA, T, "lane"

    def dataset_info(self, **_: object) -> DatasetInfo:
        return DatasetInfo(features=(Feature("x", "m"),), action_table=ActionTable.from_values([-1.0, 0.0, 1.0]),
                           gamma=GAMMA, horizon=T)

    def initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return rng.uniform(-0.3, 0.3, (n, 1))

    def step(self, states: np.ndarray, actions: np.ndarray, rng: np.random.Generator) -> StepResult:
        u = np.asarray(actions, dtype=np.float64) - 1.0
        nxt = 1.03 * states[:, 0] + 0.05 * u + rng.normal(0.0, 0.01, len(states))
        out = np.abs(nxt) > 1.0
        return StepResult(nxt[:, None], np.where(out, 5.0, np.abs(nxt) + 0.01 * u**2), out)


def _policy(rule) -> FunctionPolicy:
    return FunctionPolicy(lambda x, t=0: rule(np.asarray(x)[:, 0]).astype(np.int64), 3)


STABILISE = _policy(lambda x: np.where(x > 0.02, 0, np.where(x < -0.02, 2, 1)))
PUSH = _policy(lambda x: np.full(len(x), 2))  # steers out of the lane
COAST = _policy(lambda x: np.ones(len(x)))  # no steering: the open-loop drift


def _truth(policy: Policy, seed: int = 5) -> float:
    return rollout(Lane(), policy, 4000, np.random.default_rng(seed), horizon=T, gamma=GAMMA).mean


@pytest.fixture(scope="module")
def logs() -> TransitionDataset:
    demo = collect(Lane(), EpsilonPolicy(STABILISE, 0.1), 60, np.random.default_rng(0), horizon=T, source="demo")
    explore = collect(Lane(), UniformPolicy(3), 30, np.random.default_rng(1), horizon=T, source="explore",
                      episode_prefix="x")
    return TransitionDataset.concat([demo, explore])


@pytest.fixture(scope="module")
def model(logs) -> LoggedDynamics:
    return LoggedDynamics(random_state=0).fit(logs)


def _value_range(ds: TransitionDataset) -> tuple[np.ndarray, np.ndarray]:
    a = ds.arrays()
    return remainder_ranges(a.cost, a.terminated, GAMMA, T)


POLICIES = {"exploration": UniformPolicy(3), "behaviour": EpsilonPolicy(STABILISE, 0.1), "stabilise": STABILISE,
            "coast": COAST, "push": PUSH}


@pytest.mark.parametrize("name", list(POLICIES))
def test_the_models_reading_follows_the_simulator(logs, model, name):
    """Within 15% of the simulator's value, for policies that stay (stabilise) and that
    drift out and fail (coast, push); the bounds hold the reading."""
    truth = _truth(POLICIES[name])
    mr = model_rollout_value(model, POLICIES[name], T, GAMMA, _value_range(logs), n=2000, seed=1)
    assert mr["estimate"] == pytest.approx(truth, rel=0.15)
    assert mr["interval"][0] <= mr["estimate"] <= mr["interval"][1]


def test_a_drifting_policy_leaves_the_data_and_one_that_stays_does_not(logs, model):
    vr = _value_range(logs)
    push = model_rollout_value(model, PUSH, T, GAMMA, vr, n=2000, seed=1)
    stay = model_rollout_value(model, STABILISE, T, GAMMA, vr, n=2000, seed=1)
    assert push["exit_share"] > stay["exit_share"] and push["exit_mass"] > stay["exit_mass"]
    # what leaves the data is not read as known
    assert push["upper"] - push["lower"] > 5 * (stay["upper"] - stay["lower"])
    assert stay["exit_mass"] < 0.01 and stay["upper"] - stay["lower"] < 0.05 * stay["estimate"]


@pytest.mark.parametrize("name", ["coast", "push"])
def test_off_policy_widens_fqe_to_hold_both_readings_and_the_truth(logs, name):
    truth = _truth(POLICIES[name])
    res = off_policy(logs, POLICIES[name], n_boot=20, n_boot_fqe=40, psdp_folds=0, seed=0)
    fq = res.estimates["fqe"]
    mr = fq.model_rollouts
    assert mr is not None and fq.level == 0.95
    assert fq.interval[0] <= mr["interval"][0] and mr["interval"][1] <= fq.interval[1]
    assert fq.interval[0] <= truth <= fq.interval[1]
    assert "model rollouts" in fq.interval_method
    assert any("drives where the logs do not go" in w for w in fq.warnings) == (mr["exit_mass"] >= EXIT_FRACTION)
    assert "model_rollouts" in fq.as_dict()


def test_a_discrete_coordinate_beside_continuous_ones_stays_on_its_levels():
    """A mode flag in {0, 1} that flips now and then: the model's next flag is a logged
    level, so the logging policy itself does not look as if it left the data."""
    class Mode(Lane):
        obs_dim = 2

        def dataset_info(self, **_: object) -> DatasetInfo:
            return DatasetInfo(features=(Feature("x", "m"), Feature("mode")), gamma=GAMMA, horizon=T,
                               action_table=ActionTable.from_values([-1.0, 0.0, 1.0]))

        def initial_states(self, n, rng):
            return np.column_stack([rng.uniform(-0.3, 0.3, n), rng.integers(0, 2, n)]).astype(np.float64)

        def step(self, states, actions, rng):
            r = super().step(states[:, :1], actions, rng)
            mode = np.where(rng.random(len(states)) < 0.1, 1.0 - states[:, 1], states[:, 1])
            x = r.next_states[:, 0] + 0.01 * (2 * mode - 1)
            return StepResult(np.column_stack([x, mode]), r.costs, r.terminated)

    beh = EpsilonPolicy(STABILISE, 0.1)
    ds = collect(Mode(), beh, 60, np.random.default_rng(0), horizon=T)
    model = LoggedDynamics(random_state=0).fit(ds)
    assert 1 in model.levels_ and 0 not in model.levels_
    mr = model_rollouts(ds, beh, T, GAMMA, n=500, seed=1)
    assert mr["exit_mass"] < EXIT_FRACTION


def test_noise_is_drawn_from_held_out_rows_however_few_the_episodes(logs):
    a = logs.arrays()
    one = logs.take(a.episode == 0)
    four = logs.take(a.episode < 4)
    assert "halves" in LoggedDynamics(random_state=0).fit(one).noise_source_
    m = LoggedDynamics(random_state=0).fit(four)
    assert "two folds" in m.noise_source_ and len(m.residuals_) == len(four)


def test_the_drift_warning_does_not_need_fqes_interval():
    fq = OPEResult("fqe", 1.0, (float("nan"), float("nan")), None)
    fq = widen_fqe(fq, {"interval": [0.0, 2.0], "estimate": 1.0, "exit_mass": 0.6, "exit_share": 0.9})
    assert any("drives where the logs do not go" in w for w in fq.warnings)


def test_widen_fqe_keeps_an_interval_it_cannot_read():
    fq = OPEResult("fqe", 1.0, (float("nan"), float("nan")), None)
    fq = widen_fqe(fq, {"interval": [0.0, 2.0], "estimate": 1.0, "exit_mass": 0.0, "exit_share": 0.0})
    assert np.isnan(fq.interval[0]) and fq.model_rollouts is not None


@pytest.mark.parametrize("gamma", [0.9, 1.0])
def test_remainder_ranges_are_exact(gamma):
    """Every path of 1..L steps (non-terminal costs from the logged ones, at most one
    terminating cost, last) lies within the range for L steps, and each end is reached."""
    rng = np.random.default_rng(3)
    cost = np.r_[rng.uniform(-1.0, 2.0, 20), [7.0, -3.0]]
    term = np.r_[np.zeros(20, bool), [True, True]]
    H = 6
    lo, hi = remainder_ranges(cost, term, gamma, H)
    c, k = cost[~term], cost[term]
    assert lo[0] == hi[0] == 0.0
    for L in range(1, H + 1):
        values = []
        for steps in range(1, L + 1):  # non-terminal steps 0..steps-1, or a terminating one at steps-1
            disc = gamma ** np.arange(steps)
            for pick in (c.min(), c.max()):
                if steps == L:
                    values.append(pick * disc.sum())
                values += [pick * disc[:-1].sum() + disc[-1] * kk for kk in k]
        assert min(values) == pytest.approx(lo[L]) and max(values) == pytest.approx(hi[L])


class _Stub:
    """x' = x + 1 from x = 0, cost 1 + x, termination probability 1/2 per step; in the data
    while x < 2: a known exit at step 2 (with survival 1/4) and known discounted masses."""

    start_states_ = np.zeros((1, 1))
    radius_ = 1.0

    def step(self, x, a, rng=None):
        return StepResult(x + 1.0, 1.0 + x[:, 0], np.full(len(x), 0.5))

    def in_data(self, x, radius=None):
        return x[:, 0] < 2


def test_the_bounds_bookkeeping_against_a_hand_computed_path():
    H, g = 5, 0.8
    lo_r, hi_r = -np.arange(H + 1, dtype=float), 10.0 * np.arange(H + 1)
    out = model_rollout_value(_Stub(), COAST, H, g, (lo_r, hi_r), n=4, seed=0)
    w = (g * 0.5) ** np.arange(H)  # gamma^t times survival 0.5^t
    cost = 1.0 + np.arange(H)
    assert out["estimate"] == pytest.approx(np.sum(w * cost))
    known = w[0] * cost[0] + w[1] * cost[1]  # steps 0, 1 in the data; at step 2 the state x = 2 is not
    assert out["lower"] == pytest.approx(known + w[2] * lo_r[H - 2])
    assert out["upper"] == pytest.approx(known + w[2] * hi_r[H - 2])
    assert out["exit_mass"] == pytest.approx(w[2:].sum() / w.sum())
    assert out["exit_share"] == pytest.approx(0.5**2)  # the survival when it leaves
    assert out["past_data_cost"] == pytest.approx(np.sum(w[2:] * cost[2:]))  # the reading from the exit on
    assert out["interval"] == [pytest.approx(out["lower"]), pytest.approx(out["upper"])]  # identical particles


class _Rewarding(_Stub):
    """The stub's path with negative costs (rewards logged as costs): the reading past the
    data is counted by its size."""

    def step(self, x, a, rng=None):
        return StepResult(x + 1.0, -(1.0 + x[:, 0]), np.full(len(x), 0.5))


def test_the_reading_past_the_data_is_counted_by_its_size_whatever_the_sign():
    H, g = 5, 0.8
    lo_r, hi_r = -10.0 * np.arange(H + 1), np.zeros(H + 1)
    out = model_rollout_value(_Rewarding(), COAST, H, g, (lo_r, hi_r), n=4, seed=0)
    w = (g * 0.5) ** np.arange(H)
    cost = -(1.0 + np.arange(H))
    assert out["estimate"] == pytest.approx(np.sum(w * cost))
    assert out["past_data_cost"] == pytest.approx(np.sum(w[2:] * np.abs(cost[2:]))) and out["past_data_cost"] > 0


def test_states_on_a_lattice_are_left_to_fqe(logs):
    a = logs.arrays()
    grid = TransitionDataset.from_arrays(
        logs.info, episode_id=logs.episode_ids[a.episode], step=a.step, obs=np.round(a.obs, 1),
        action=a.action, cost=a.cost, next_obs=np.round(a.next_obs, 1), terminated=a.terminated,
        truncated=a.truncated)
    assert "skipped" in model_rollouts(grid, STABILISE, T, GAMMA)
    lattice = LoggedDynamics(random_state=0).fit(grid)
    assert lattice.radius_ == 0
    with pytest.raises(InvalidArgumentError, match="not fitted"):
        lattice.step(grid.arrays().obs[:2], np.zeros(2, np.int64))


@pytest.mark.parametrize("count", [-1, 1])
def test_off_policy_refuses_a_particle_count_without_an_interval(logs, count):
    with pytest.raises(InvalidArgumentError, match="model_particles"):
        off_policy(logs, STABILISE, model_particles=count)


def test_a_noisy_system_is_read_with_its_noise():
    """With process noise ten times larger, the logging policy's cost is mostly the noise's:
    the mean increment alone read a quarter of it (review, 2026-11-26)."""
    class Noisy(Lane):
        def step(self, states, actions, rng):
            u = np.asarray(actions, dtype=np.float64) - 1.0
            nxt = 1.03 * states[:, 0] + 0.05 * u + rng.normal(0.0, 0.1, len(states))
            out = np.abs(nxt) > 1.0
            return StepResult(nxt[:, None], np.where(out, 5.0, np.abs(nxt) + 0.01 * u**2), out)

    beh = EpsilonPolicy(STABILISE, 0.1)
    ds = collect(Noisy(), beh, 80, np.random.default_rng(0), horizon=T)
    truth = rollout(Noisy(), beh, 4000, np.random.default_rng(5), horizon=T, gamma=GAMMA).mean
    mr = model_rollouts(ds, beh, T, GAMMA, n=2000, seed=1)
    assert mr["estimate"] == pytest.approx(truth, rel=0.15)




@pytest.mark.parametrize("d, scale", [(1, 1.0), (3, 1.5), (8, 1.2), (17, 1.1)])
def test_the_fast_support_check_equals_an_exact_nearest_neighbour_search(d, scale):
    """``in_data`` settles most states with an approximate search; it must answer exactly
    what an exact nearest-neighbour search against the radius answers (states near the
    data, far from it, and on the border alike)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(d)
    X = rng.standard_normal((3000, d)) * rng.uniform(0.5, 2.0, d)
    model = LoggedDynamics()
    model.sd_ = X.std(axis=0)
    model.tree_ = cKDTree(X / model.sd_)
    dist, _ = model.tree_.query(X / model.sd_, k=2)
    model.radius_ = float(np.quantile(dist[:, 1], SUPPORT_QUANTILE))
    Q = np.vstack([X[:300] + 0.3 * rng.standard_normal((300, d)) * model.sd_,
                   rng.standard_normal((700, d)) * scale * model.sd_])
    exact, _ = cKDTree(X / model.sd_).query(Q / model.sd_)
    got = model.in_data(Q)
    assert np.array_equal(got, exact <= model.radius_)
    assert 0 < got.sum() < len(Q)  # both answers occur


def _linear_log(d: int, n_ep: int, seed: int, H: int = 100) -> TransitionDataset:
    """Episodes of a stable linear system in d dimensions under uniformly random actions
    (consecutive states close, as in any logged trajectory)."""
    rng = np.random.default_rng(seed)
    B = np.random.default_rng(99).standard_normal(d)
    x = rng.standard_normal((n_ep, d))
    obs, nxt, act = [], [], []
    for _ in range(H):
        a = rng.integers(0, 3, n_ep)
        y = 0.9 * x + 0.1 * np.outer(a - 1.0, B) + 0.3 * rng.standard_normal((n_ep, d))
        obs, nxt, act = obs + [x], nxt + [y], act + [a]
        x = y
    o, n2 = np.stack(obs, 1).reshape(-1, d), np.stack(nxt, 1).reshape(-1, d)
    step = np.tile(np.arange(H), n_ep)
    info = DatasetInfo(features=tuple(Feature(f"x{j}") for j in range(d)), gamma=GAMMA, horizon=H,
                       action_table=ActionTable.from_values([-1.0, 0.0, 1.0]))
    return TransitionDataset.from_arrays(
        info, episode_id=np.char.zfill(np.repeat(np.arange(n_ep), H).astype(str), 5), step=step, obs=o,
        action=np.stack(act, 1).ravel(), cost=np.linalg.norm(n2, axis=1), next_obs=n2,
        terminated=np.zeros(len(step), bool), truncated=step == H - 1)


@pytest.mark.parametrize("d", [2, 12])
def test_fresh_episodes_of_the_logging_policy_are_in_the_data(d):
    """The radius is set on distances to *other* episodes: new episodes of the policy that
    wrote the logs lie outside about as often as the quantile says (here < 1%), in few
    dimensions and in many. Measured against own-episode neighbours (the rule before), 12
    dimensions put ~10x more of them outside."""
    ds = _linear_log(d, 200, seed=0)
    model = LoggedDynamics(random_state=0).fit(ds)
    fresh = _linear_log(d, 100, seed=1).arrays().obs
    outside = 1.0 - model.in_data(fresh).mean()
    assert outside < 0.01
    z = ds.arrays().obs / model.sd_
    own, _ = model.tree_.query(z[::7], k=2)  # the rule before: nearest other row, its own episode included
    before = float(np.quantile(own[:, 1], SUPPORT_QUANTILE))
    dist, _ = model.tree_.query(fresh / model.sd_)
    if d >= 12:
        assert (dist > before).mean() > 5 * max(outside, 1e-3)


def test_one_episode_that_went_elsewhere_does_not_set_the_radius():
    """The radius is the median over folds of each fold's quantile: one logged episode that
    drifted where no other went (all its states in one fold) leaves it about where it was
    (review: the pooled quantile went from 1.5 to 6.7 sd, and a drifting policy's exit
    mass from 0.19 to 0)."""
    ds = _linear_log(4, 200, seed=0)
    a = ds.arrays()
    base = LoggedDynamics(random_state=0).fit(ds).radius_
    obs, nxt = a.obs.copy(), a.next_obs.copy()
    odd = (a.episode == 7) & (a.step >= 50)
    drift = 0.3 * (a.step[odd] - 49.0)
    obs[odd, 0] += drift
    nxt[odd, 0] += drift + 0.3
    odd_ds = TransitionDataset.from_arrays(ds.info, episode_id=ds.episode_ids[a.episode], step=a.step, obs=obs,
                                           action=a.action, cost=a.cost, next_obs=nxt, terminated=a.terminated,
                                           truncated=a.truncated)
    with_odd = LoggedDynamics(random_state=0).fit(odd_ds)
    assert with_odd.radius_ < 1.3 * base


@pytest.mark.parametrize("n_ep", [1, 3])
def test_too_few_episodes_for_folds_take_the_stricter_rule(n_ep):
    ds = _linear_log(3, n_ep, seed=0)
    model = LoggedDynamics(random_state=0).fit(ds)
    z = ds.arrays().obs / model.sd_
    own, _ = model.tree_.query(z, k=2)
    assert model.radius_ == pytest.approx(np.quantile(own[:, 1], SUPPORT_QUANTILE))


def test_the_support_check_on_a_lattice_is_exact(logs):
    model = LoggedDynamics(random_state=0).fit(logs)
    model.radius_ = 0.0
    x = logs.arrays().obs[:5]
    assert model.in_data(x).all() and not model.in_data(x + 1e-3).any()


def test_turned_off_model_rollouts_are_said(logs):
    res = off_policy(logs, STABILISE, n_boot=5, n_boot_fqe=0, psdp_folds=0, model_particles=0)
    assert res.estimates["fqe"].model_rollouts == {"skipped": "model_particles=0: model rollouts turned off"}


class _TwoRadii(_Stub):
    radius_ = 10.0  # the support judgement: the path never leaves it
    trust_radius_ = 2.0  # the bounds: they stop reading the model at x = 2

    def in_data(self, x, radius=None):
        return x[:, 0] < (self.radius_ if radius is None else radius)


def test_the_bounds_stop_trusting_at_the_trust_radius_and_the_exit_mass_at_the_support_radius():
    H, g = 5, 0.8
    lo_r, hi_r = -np.arange(H + 1, dtype=float), 10.0 * np.arange(H + 1)
    out = model_rollout_value(_TwoRadii(), COAST, H, g, (lo_r, hi_r), n=4, seed=0)
    same = model_rollout_value(_Stub(), COAST, H, g, (lo_r, hi_r), n=4, seed=0)  # one rule for both: out at x = 2
    assert (out["lower"], out["upper"]) == (pytest.approx(same["lower"]), pytest.approx(same["upper"]))
    assert out["exit_mass"] == 0.0 and out["exit_share"] == 0.0 and same["exit_mass"] > 0
    assert out["trust_radius"] == 2.0 and out["radius"] == 10.0


class _LeavesBoth(_TwoRadii):
    radius_ = 4.0  # leaves the support later, at x = 4


def test_leaving_trust_then_support_sets_the_tails_once_and_the_exit_at_the_support():
    H, g = 6, 0.8
    lo_r, hi_r = -np.arange(H + 1, dtype=float), 10.0 * np.arange(H + 1)
    out = model_rollout_value(_LeavesBoth(), COAST, H, g, (lo_r, hi_r), n=4, seed=0)
    w = (g * 0.5) ** np.arange(H)
    cost = 1.0 + np.arange(H)
    known = w[0] * cost[0] + w[1] * cost[1]  # trusted at x = 0, 1; the tails from step 2 on, set once
    assert out["lower"] == pytest.approx(known + w[2] * lo_r[H - 2])
    assert out["upper"] == pytest.approx(known + w[2] * hi_r[H - 2])
    assert out["exit_mass"] == pytest.approx(w[4:].sum() / w.sum())  # out of the support at x = 4
    assert out["exit_share"] == pytest.approx(0.5**4)
    assert out["past_data_cost"] == pytest.approx(np.sum(w[4:] * cost[4:]))  # past the support, not the trust radius


def test_the_trust_radius_is_the_data_own_spacing():
    """The bounds' radius is the rule they were validated with: the 99.9% quantile of each
    logged state's distance to its nearest other logged state (own episode included)."""
    ds = _linear_log(3, 40, seed=2)
    model = LoggedDynamics(random_state=0).fit(ds)
    z = ds.arrays().obs / model.sd_
    own, _ = model.tree_.query(z, k=2)
    assert model.trust_radius_ == pytest.approx(min(model.radius_, np.quantile(own[:, 1], SUPPORT_QUANTILE)))
    assert model.trust_radius_ < model.radius_


def test_widen_is_a_hull_that_says_so_and_leaves_what_it_cannot_read():
    r = OPEResult("fqe", 5.0, (4.0, 6.0), None, 0.95)
    w, before = r.widened(3.0, 5.5, "widened to X")
    assert before == (4.0, 6.0) and r.interval == (4.0, 6.0)  # a new result: r is unchanged
    assert w.interval == (3.0, 6.0) and w.interval_method.endswith("; widened to X")
    same, before = w.widened(float("nan"), 9.0, "never")
    assert before is None and same is w and "never" not in w.interval_method
