"""Learning over continuous commands (issue #41), against closed forms.

The oracle is a scalar linear-quadratic problem: ``x' = x + u``, cost ``q x^2 + r u^2``,
discount gamma. Its optimal value is ``P x^2`` with ``P`` the fixed point of the discounted
Riccati map, its optimal command ``u* = -K x`` with ``K = gamma P / (r + gamma P)``, and a
linear policy ``u = -k x`` has value ``(q + r k^2) x^2 / (1 - gamma (1 - k)^2)``.
"""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp.algorithms.api import ApproximatePolicyIteration
from offline_adp.algorithms.cpi import ConservativePolicyIteration
from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.algorithms.fqi import FittedQIteration, load_fqi, save_fqi
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import ACTION_VALUE_PREFIX, Action, ActionTable, DatasetInfo, Feature
from offline_adp.errors import IncompatibleError, InvalidArgumentError
from offline_adp.policies import CommandPolicy, attach_signature

Q_X, R_U, GAMMA, U_MAX = 1.0, 0.5, 0.9, 1.5


def riccati() -> tuple[float, float]:
    """``(P, K)`` of the discounted scalar LQ problem (fixed-point iteration of the Riccati map)."""
    p = Q_X
    for _ in range(10_000):
        p = Q_X + GAMMA * p - (GAMMA * p) ** 2 / (R_U + GAMMA * p)
    return p, GAMMA * p / (R_U + GAMMA * p)


def linear_value(k: float) -> float:
    """``V(x) / x^2`` of the policy ``u = -k x``."""
    return (Q_X + R_U * k * k) / (1.0 - GAMMA * (1.0 - k) ** 2)


def lq_dataset(n_episodes: int = 200, steps: int = 20, seed: int = 0, continuous: bool = True) -> TransitionDataset:
    """Random play: ``x_0 ~ U(-2, 2)``, ``u ~ U(-1.5, 1.5)``, episodes of ``steps`` steps
    (truncated; states leaving [-4, 4] end the episode early, truncated too)."""
    rng = np.random.default_rng(seed)
    rows: dict[str, list] = {k: [] for k in ("ep", "t", "x", "u", "c", "x2", "trunc")}
    for e in range(n_episodes):
        x = rng.uniform(-2, 2)
        for t in range(steps):
            u = rng.uniform(-U_MAX, U_MAX)
            x2 = x + u
            last = t == steps - 1 or abs(x2) > 4
            for k, v in zip(rows, (f"{e:04d}", t, x, u, Q_X * x * x + R_U * u * u, x2, last), strict=True):
                rows[k].append(v)
            x = x2
            if last:
                break
    u = np.asarray(rows["u"])
    edges = np.linspace(-U_MAX, U_MAX, 6)
    idx = np.clip(np.searchsorted(edges, u, side="right") - 1, 0, 4)
    table = ActionTable(actions=tuple(Action(f"u{b}", (float((edges[b] + edges[b + 1]) / 2),)) for b in range(5)),
                        dims=("u",), kind="continuous" if continuous else "binned",
                        low=(-U_MAX,), high=(U_MAX,))
    info = DatasetInfo(features=(Feature("x"),), action_table=table, gamma=GAMMA, name="lq")
    n = len(u)
    return TransitionDataset.from_arrays(
        info, episode_id=np.asarray(rows["ep"]), step=np.asarray(rows["t"]), obs=np.asarray(rows["x"]), action=idx,
        cost=np.asarray(rows["c"]), next_obs=np.asarray(rows["x2"]), terminated=np.zeros(n, bool),
        truncated=np.asarray(rows["trunc"]), extra={ACTION_VALUE_PREFIX + "u": u})


class LinearPolicy(CommandPolicy):
    def __init__(self, k: float) -> None:
        self.k = k

    def commands(self, obs, t=0):
        return np.clip(-self.k * np.asarray(obs, np.float64)[:, :1], -U_MAX, U_MAX)


def discounted_cost(policy, x0: np.ndarray, steps: int = 120) -> np.ndarray:
    """The true discounted cost of ``policy`` from each ``x0`` (the system is known)."""
    x, total, g = x0.astype(np.float64).copy(), np.zeros(len(x0)), 1.0
    for _ in range(steps):
        u = np.asarray(policy.commands(x[:, None], 0), np.float64)[:, 0]
        total += g * (Q_X * x * x + R_U * u * u)
        x, g = x + u, g * GAMMA
    return total


@pytest.fixture(scope="module")
def lq() -> TransitionDataset:
    return lq_dataset()


@pytest.fixture(scope="module")
def fqi(lq) -> FittedQIteration:
    return FittedQIteration(n_iterations=80, n_candidates=32, random_state=0).fit(lq)


def test_fqe_of_a_continuous_policy_matches_the_closed_form(lq):
    k = 0.5
    fqe = FittedQEvaluation(policy=LinearPolicy(k), mode="frozen", n_iterations=100).fit(lq)
    assert fqe.commands_ == "continuous"
    x0 = lq.arrays().obs[lq.arrays().step == 0, 0]
    truth = float(np.mean(linear_value(k) * x0 ** 2))
    assert fqe.value_ == pytest.approx(truth, rel=0.1)


def test_greedy_commands_come_from_the_logged_neighbourhood_and_near_the_optimum(lq, fqi):
    assert fqi.commands_ == "continuous"
    pol = fqi.policy_
    xs = np.linspace(-1.8, 1.8, 41)[:, None]
    u = pol.commands(xs)
    assert u.shape == (41, 1)
    # the guarantee: every command was logged at one of the n_candidates nearest logged states,
    # or is one of the log's 16 representative commands (n_representatives)
    # (recomputed by brute force from the dataset, not read back from the fit's own candidate set)
    allowed = _allowed_commands(lq, xs, 32, reps=16)
    assert all(np.any(np.isclose(allowed[i], u[i, 0], rtol=1e-12, atol=0)) for i in range(len(xs)))
    _, K = riccati()
    assert np.mean(np.abs(u[:, 0] + K * xs[:, 0])) < 0.25
    # the learned policy's true cost is within 10% of the optimum from the data's start states
    P, _ = riccati()
    x0 = lq.arrays().obs[lq.arrays().step == 0, 0]
    assert discounted_cost(pol, x0).mean() <= 1.1 * float(np.mean(P * x0 ** 2))


def _representatives(u, n):
    """A second, plain implementation for one-component commands: n quantile bins, the logged
    command nearest the mean of each occupied one (ties to the first row)."""
    edges = np.quantile(u, np.linspace(0, 1, n + 1))
    out = []
    for b in range(n):
        lo, hi = edges[b], edges[b + 1]
        inside = (u >= lo) & ((u < hi) if b < n - 1 else (u <= hi))
        if b > 0 and lo == edges[b - 1]:
            continue
        if inside.any():
            vals = u[inside]
            out.append(vals[np.argmin(np.abs(vals - vals.mean()))])
    return np.array(out)


def _allowed_commands(ds, xs, k, reps):
    """By brute force: per query state, the commands logged at its k nearest logged states
    (distances in units of each feature's logged spread, ties to the lower row), plus the
    log's ``reps`` representative commands."""
    obs, logged = ds.arrays().obs, ds.commands()
    z = (obs - obs.mean(axis=0)) / obs.std(axis=0)
    zq = (xs - obs.mean(axis=0)) / obs.std(axis=0)
    d2 = ((zq[:, None, :] - z[None, :, :]) ** 2).sum(axis=2)
    nearest = np.argsort(d2, axis=1, kind="stable")[:, :k]
    r = _representatives(logged[:, 0], reps) if reps else np.zeros(0)
    return [np.r_[logged[nearest[i], 0], r] for i in range(len(xs))]


def test_representative_commands_agree_with_a_plain_implementation(lq):
    from offline_adp.algorithms.fqi_data import command_representatives

    u = lq.commands()
    for n in (1, 5, 16):
        np.testing.assert_allclose(command_representatives(u, n)[:, 0], _representatives(u[:, 0], n), rtol=1e-12)
    # two components: at most n cells, each represented by a command logged in it
    rng = np.random.default_rng(0)
    u2 = np.column_stack([rng.normal(size=500), rng.uniform(-1, 1, 500)])
    r = command_representatives(u2, 16)
    assert r.shape[1] == 2 and 1 <= len(r) <= 16
    assert all((u2 == x).all(axis=1).any() for x in r)
    # integer levels (an audit: 52% of the greedy commands were never logged, e.g. [-1, -3.375]):
    # every representative is a logged command, and a constant component takes no share of n
    ints = np.column_stack([rng.integers(-3, 4, 2000), rng.integers(0, 5, 2000)]).astype(float)
    r = command_representatives(ints, 16)
    assert len(r) == 16 and all((ints == x).all(axis=1).any() for x in r)
    const = np.column_stack([rng.uniform(-1, 1, 500), np.full(500, 0.3)])
    r = command_representatives(const, 16)
    assert len(r) == 16 and (r[:, 1] == 0.3).all()
    # a command logged at one value only: one representative
    assert len(command_representatives(np.zeros((50, 1)), 16)) == 1


def test_without_representatives_every_command_was_logged_nearby(lq):
    """n_representatives=0: C(x) is the neighbours' commands alone, and so is every greedy command."""
    est = FittedQIteration(n_iterations=20, n_candidates=8, n_representatives=0, random_state=0).fit(lq)
    xs = np.linspace(-2.5, 2.5, 31)[:, None]
    u = est.policy_.commands(xs)
    allowed = _allowed_commands(lq, xs, 8, reps=0)
    assert all(np.any(np.isclose(allowed[i], u[i, 0], rtol=1e-12, atol=0)) for i in range(len(xs)))
    with_reps = FittedQIteration(n_iterations=20, n_candidates=8, random_state=0).fit(lq)
    assert with_reps.q_function_.n_actions == 8 + len(_representatives(lq.commands()[:, 0], 16))


def test_continuous_beats_the_bins_on_the_same_logs(lq, fqi):
    """Five bins of [-1.5, 1.5] cannot command -K x exactly; the exact commands can."""
    binned = FittedQIteration(n_iterations=80, commands="binned", random_state=0).fit(lq)
    values = lq.info.action_table.values

    class Binned(CommandPolicy):
        def commands(self, obs, t=0):
            return values[binned.policy_.act_index(np.asarray(obs), t)]

    x0 = lq.arrays().obs[lq.arrays().step == 0, 0]
    assert discounted_cost(fqi.policy_, x0).mean() < discounted_cost(Binned(), x0).mean()


def test_act_returns_commands_and_survives_save_and_load(lq, fqi, tmp_path):
    attach_signature(fqi.policy_, lq)
    xs = np.random.default_rng(3).uniform(-2, 2, (50, 1))
    u = fqi.policy_.act(xs)
    assert u.shape == (50,) and np.all(np.abs(u) <= U_MAX)
    assert isinstance(fqi.policy_.act({"x": 0.3}), float)
    save_fqi(fqi, tmp_path / "m")
    back = load_fqi(tmp_path / "m")
    np.testing.assert_array_equal(back.policy_.commands(xs), fqi.policy_.commands(xs))
    np.testing.assert_array_equal(back.predict(xs), fqi.predict(xs))


def test_api_over_commands_improves_on_its_start(lq):
    api = ApproximatePolicyIteration(fqe=FittedQEvaluation(mode="frozen", n_iterations=60), n_iterations=3).fit(lq)
    h = api.history_
    assert h["value"].iloc[-1] < h["value"].iloc[0]
    # in the true system too: the last policy costs less than pi_0 (the nearest logged command)
    from offline_adp.policies import NearestCommandPolicy
    from offline_adp.qfunctions import NeighbourCommands

    a = lq.arrays()
    start = NearestCommandPolicy(NeighbourCommands.from_data(a.obs, lq.commands(), 1))
    x0 = a.obs[a.step == 0, 0]
    assert discounted_cost(api.policy_, x0).mean() < 0.8 * discounted_cost(start, x0).mean()
    # commands from C(x) only: the 16 nearest logged states' commands, then the log's representatives
    cand = NeighbourCommands.from_data(a.obs, lq.commands(), 16, _representatives(lq.commands()[:, 0], 16))(
        x0[:, None])
    u = api.policy_.commands(x0[:, None])
    assert all(np.any(np.isclose(cand[i, :, 0], u[i, 0], rtol=1e-12, atol=0)) for i in range(len(x0)))


def test_continuous_commands_need_the_exact_commands():
    ds = lq_dataset(20, continuous=False)
    plain = TransitionDataset(ds.table.drop_columns([ACTION_VALUE_PREFIX + "u"]), ds.info)
    with pytest.raises(InvalidArgumentError, match=r"action_value\.u"):
        FittedQIteration(n_iterations=2, commands="continuous").fit(plain)
    assert FittedQIteration(n_iterations=2).fit(ds).commands_ == "binned"  # "auto" on a binned table


def test_cpi_refuses_continuous_commands(lq):
    with pytest.raises(IncompatibleError, match="continuous commands"):
        ConservativePolicyIteration(n_iterations=1).fit(lq)


def test_two_component_commands_fit_in_the_default_frozen_mode():
    """A command of two components (the second ignored by the system): the default mode fits it
    and the greedy commands are two-component vectors from the logged neighbourhood."""
    ds = lq_dataset(60)
    u = ds.commands()[:, 0]
    w = np.random.default_rng(1).uniform(-1, 1, len(u))
    from dataclasses import replace

    at = ds.info.action_table
    table = ActionTable(actions=tuple(Action(a.name, (a.value[0], 0.0)) for a in at.actions), dims=("u", "w"),
                        kind="continuous", low=(-U_MAX, -1.0), high=(U_MAX, 1.0))
    two = TransitionDataset(ds.table.append_column(ACTION_VALUE_PREFIX + "w", [w]),
                            replace(ds.info, action_table=table))
    est = FittedQIteration(n_iterations=10).fit(two)
    assert est.mode_ == "frozen" and est.commands_ == "continuous"
    xs = np.linspace(-1.5, 1.5, 7)[:, None]
    c = est.policy_.commands(xs)
    cand = est.q_function_.encoder.commands(xs)
    assert c.shape == (7, 2)
    assert all((cand[i] == c[i]).all(axis=1).any() for i in range(7))


def test_finite_horizon_over_commands_saves_and_a_crafted_step_is_refused(tmp_path):
    """Algorithm 10 over commands: one Q per step, every step reading the same candidate set;
    a saved model whose steps read different candidate sets is refused on load."""
    from offline_adp.errors import ArtifactError

    ds = lq_dataset(40)
    est = FittedQIteration(horizon=3, n_iterations=2, regressor_params={"n_estimators": 5}).fit(ds)
    assert est.commands_ == "continuous" and est.policy_.time_varying
    save_fqi(est, tmp_path / "m")
    xs = np.linspace(-1, 1, 5)[:, None]
    np.testing.assert_array_equal(load_fqi(tmp_path / "m").policy_.commands(xs, 1), est.policy_.commands(xs, 1))
    with np.load(tmp_path / "m" / "q.npz") as z:
        arrays = {k: z[k].copy() for k in z.files}
    key = next(k for k in arrays if k.endswith(".candidates.commands") and ".t1" in k)
    arrays[key][0] += 0.25
    np.savez_compressed(tmp_path / "m" / "q.npz", **arrays)
    with pytest.raises(ArtifactError, match="different candidate sets"):
        load_fqi(tmp_path / "m")
