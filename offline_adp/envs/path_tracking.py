"""Path tracking: the driving case study (a kinematic bicycle following a curvy course).

The course is a closed loop of waypoints every 0.5 m (about 407 m; curvature between
-0.042 and +0.029 1/m, so it bends both ways), given in a local east-north frame as
GPS waypoints would be after projection. The vehicle is a kinematic bicycle (wheelbase
2.7 m) written in path coordinates (Frenet frame), integrated with 5 Euler sub-steps of
0.02 s per 0.1 s control step::

    ds/dt    = v cos(e_psi) / (1 - kappa(s) e)
    de/dt    = v sin(e_psi)
    de_psi/dt = v tan(delta) / L - kappa(s) ds/dt
    d delta/dt = (delta_cmd - delta) / tau          (steering actuator lag, tau = 0.2 s)

plus Gaussian heading noise (road and wind; std 0.01 rad per control step). Speed is
constant within an episode (drawn in [6, 10] m/s).

Observation (all float64): ``s`` progress along the course [m], ``e`` cross-track error
[m, positive left], ``e_psi`` heading error [rad], ``delta`` steering angle [rad], ``v``
speed [m/s], ``kappa`` course curvature here [1/m], ``kappa_ahead`` curvature 1 s ahead
[1/m]. The curvature features are functions of ``s`` and ``v``, so the observation is the
full state. Actions: steering commands {-0.3, -0.2, ..., 0.3} rad.
Cost per step: ``|e'| + 0.1 delta_cmd^2``; leaving the road (``|e'| > 2 m``) is terminal
with the constant cost ``c^- = 50`` (the chapter's infeasible-state cost). Episodes
truncate at 200 steps (20 s). gamma = 0.95.

The demonstrator is a Stanley-style driver without curvature feed-forward and with
Gaussian steering noise (std 0.04 rad) quantised to the action set, plus 5% random
commands: human-like, safe, but it lags in curves, which a learned policy can beat.
Its action probabilities are known exactly (Gaussian mass of each command's bin).

Continuous commands (problem option ``commands``; ``--problem-options '{"commands":
"continuous"}'``):

- ``"discrete"`` (default): the seven steering commands above, bit-identical to the
  original problem.
- ``"continuous"``: steering ``delta_cmd`` [rad] is any number in [-0.3, 0.3] (clipped
  there). The action table is of kind ``continuous``: the exact command of every logged
  row is kept in ``action_value.delta_cmd``; its seven entries (the commands above) are
  coarse bins (edges halfway between them) for the discrete views. Dynamics and cost are
  those of the default problem, so a command equal to one of the seven steps exactly as
  its index does. The demonstrator is the same Stanley driver with its Gaussian noise
  *not* quantised (std 0.04 rad) and 5% uniform commands in the bounds; exploration draws
  uniform commands in the bounds.
- ``"steer_accel"``: commands ``(delta_cmd [rad], accel_cmd [m/s^2])`` in [-0.3, 0.3] x
  [-2, 2]; the speed becomes controlled, ``dv/dt = accel_cmd`` integrated in the same
  sub-steps and kept within [4, 12] m/s. The cost adds a speed term and an acceleration
  term: ``|e'| + 0.1 delta_cmd^2 + 0.02 (v' - 8)^2 + 0.01 accel_cmd^2`` (8 m/s the target
  speed; without the speed term the best policy would crawl). Coarse bins: the product of
  the seven steering commands and {-2, 0, 2} m/s^2 (21 entries). The demonstrator adds a
  speed keeper ``accel = -0.5 (v - 8)`` with noise (std 0.3 m/s^2) to the Stanley steering.

In the continuous modes ``step`` takes commands ``(n, m)`` (``accepts_commands``) as well
as indices (the entries' values), and the behaviour policies are continuous
(:class:`~offline_adp.policies.GaussianCommandPolicy`), so ``simulate`` logs exact
commands (no ``behavior_prob``: a density, not a probability).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from scipy.special import ndtr

from offline_adp.access import Simulator, StepResult, command_matrix, is_command_array
from offline_adp.data.info import Action, ActionTable, DatasetInfo, Feature
from offline_adp.envs.base import ReferenceProblem
from offline_adp.errors import InvalidArgumentError
from offline_adp.policies import (
    EpsilonPolicy,
    GaussianCommandPolicy,
    Policy,
    StochasticFunctionPolicy,
)

WHEELBASE = 2.7
TAU_STEER = 0.2
DT = 0.1
N_SUB = 5
HEADING_NOISE = 0.01
ROAD_HALF_WIDTH = 2.0
FAILURE_COST = 50.0
CONTROL_WEIGHT = 0.1
PREVIEW_S = 1.0
STEERING_COMMANDS = np.round(np.arange(-0.3, 0.31, 0.1), 10)
#: Command modes (problem option ``commands``).
COMMAND_MODES = ("discrete", "continuous", "steer_accel")
STEER_LIMIT = 0.3
ACCEL_LIMIT = 2.0
ACCEL_BINS = np.array([-2.0, 0.0, 2.0])
V_MIN, V_MAX, V_TARGET = 4.0, 12.0, 8.0
SPEED_WEIGHT = 0.02
ACCEL_WEIGHT = 0.01


def _continuous_table(mode: str) -> ActionTable:
    """The continuous action table of a command mode (coarse bins as entries)."""
    steer_edges = tuple(float(e) for e in np.r_[-STEER_LIMIT, (STEERING_COMMANDS[1:] + STEERING_COMMANDS[:-1]) / 2,
                                                 STEER_LIMIT])
    if mode == "continuous":
        actions = tuple(Action(f"delta_cmd={v:g}", (float(v),)) for v in STEERING_COMMANDS)
        return ActionTable(actions=actions, dims=("delta_cmd",), kind="continuous", units=("rad",),
                           bin_edges=steer_edges, low=(-STEER_LIMIT,), high=(STEER_LIMIT,))
    actions = tuple(Action(f"delta_cmd={d:g},accel_cmd={a:g}", (float(d), float(a)))
                    for d in STEERING_COMMANDS for a in ACCEL_BINS)
    return ActionTable(actions=actions, dims=("delta_cmd", "accel_cmd"), kind="continuous", units=("rad", "m/s^2"),
                       low=(-STEER_LIMIT, -ACCEL_LIMIT), high=(STEER_LIMIT, ACCEL_LIMIT))


@dataclass(frozen=True)
class Course:
    """A closed course sampled every ``ds`` metres: positions, heading, curvature."""

    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    curvature: np.ndarray
    ds: float

    @property
    def length(self) -> float:
        return self.ds * len(self.x)

    def _interp(self, values: np.ndarray, s: np.ndarray) -> np.ndarray:
        grid = np.arange(len(values)) * self.ds
        return np.interp(np.mod(s, self.length), grid, values, period=self.length)

    def kappa(self, s: np.ndarray) -> np.ndarray:
        return self._interp(self.curvature, s)

    def pose(self, s: np.ndarray, e: np.ndarray, e_psi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World pose (x, y, yaw) of a vehicle at path coordinates (s, e, e_psi)."""
        psi = self._interp(np.unwrap(self.heading), s)
        cx, cy = self._interp(self.x, s), self._interp(self.y, s)
        return cx - e * np.sin(psi), cy + e * np.cos(psi), np.arctan2(np.sin(psi + e_psi), np.cos(psi + e_psi))


def make_course(radius: float = 60.0, a2: float = 0.25, a3: float = 0.1, ds: float = 0.5) -> Course:
    """The default course: polar curve r = R (1 + a2 sin 2t + a3 cos 3t), resampled by arc length."""
    th = np.linspace(0.0, 2 * np.pi, 40000, endpoint=False)
    r = radius * (1 + a2 * np.sin(2 * th) + a3 * np.cos(3 * th))
    dr = radius * (2 * a2 * np.cos(2 * th) - 3 * a3 * np.sin(3 * th))
    ddr = radius * (-4 * a2 * np.sin(2 * th) - 9 * a3 * np.cos(3 * th))
    x, y = r * np.cos(th), r * np.sin(th)
    kappa = (r * r + 2 * dr * dr - r * ddr) / (r * r + dr * dr) ** 1.5  # polar curvature
    seg = np.hypot(np.diff(np.r_[x, x[0]]), np.diff(np.r_[y, y[0]]))
    s = np.r_[0.0, np.cumsum(seg)[:-1]]
    total = float(seg.sum())
    n = int(round(total / ds))
    ds = total / n
    su = np.arange(n) * ds
    xu = np.interp(su, s, x, period=total)
    yu = np.interp(su, s, y, period=total)
    ku = np.interp(su, s, kappa, period=total)
    dx = np.roll(xu, -1) - np.roll(xu, 1)
    dy = np.roll(yu, -1) - np.roll(yu, 1)
    return Course(xu, yu, np.arctan2(dy, dx), ku, ds)


class PathTracking(ReferenceProblem, Simulator):
    """The driving case study as a seeded simulator (noise from the seed)."""

    name = "path_tracking"
    features = (
        Feature("s", "m", "progress along the course"),
        Feature("e", "m", "cross-track error, positive to the left"),
        Feature("e_psi", "rad", "heading error"),
        Feature("delta", "rad", "steering angle"),
        Feature("v", "m/s", "speed"),
        Feature("kappa", "1/m", "course curvature at s"),
        Feature("kappa_ahead", "1/m", "course curvature 1 s ahead"),
    )
    action_table = ActionTable.from_values(STEERING_COMMANDS, dims=("delta_cmd",), units=("rad",))
    gamma = 0.95
    n_actions = len(STEERING_COMMANDS)
    obs_dim = 7

    def __init__(self, horizon: int | None = 200, heading_noise: float = HEADING_NOISE,
                 commands: str = "discrete") -> None:
        if commands not in COMMAND_MODES:
            raise InvalidArgumentError(f"commands must be one of {list(COMMAND_MODES)}, got {commands!r}")
        self.horizon = horizon
        self.heading_noise = heading_noise
        self.commands = commands
        if commands != "discrete":  # instance attributes: the default problem keeps the class's
            self.action_table = _continuous_table(commands)
            self.n_actions = len(self.action_table)
            self.accepts_commands = True

    def command_values(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The steering command (n,) and, with ``commands = "steer_accel"``, the acceleration
        command (n,) of ``actions``: indices (n,) or, in a continuous mode, commands (n, m)."""
        if self.commands == "discrete":
            return STEERING_COMMANDS[np.asarray(actions, dtype=np.int64)], None
        table = self.action_table
        if is_command_array(actions):
            lo, hi = table.bounds()
            u = command_matrix(actions, len(actions), lo, hi, self.name)
        else:
            u = table.values[np.asarray(actions, dtype=np.int64)]
        return u[:, 0], (u[:, 1] if self.commands == "steer_accel" else None)

    def dataset_info(self, **provenance: Any) -> DatasetInfo:
        """As every problem's; with continuous commands the propensity source is
        ``unknown`` (the logs hold commands drawn from a density, no ``behavior_prob``)."""
        info = super().dataset_info(**provenance)
        return info if self.commands == "discrete" else info.replace(propensity_source="unknown")

    @cached_property
    def course(self) -> Course:
        return make_course()

    def observe(self, s: np.ndarray, e: np.ndarray, e_psi: np.ndarray, delta: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Observation vectors from the dynamic state."""
        s = np.mod(s, self.course.length)
        return np.column_stack([s, e, e_psi, delta, v, self.course.kappa(s), self.course.kappa(s + v * PREVIEW_S)])

    def initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        s = rng.uniform(0, self.course.length, n)
        e = np.clip(rng.normal(0, 0.3, n), -1.0, 1.0)
        e_psi = rng.normal(0, 0.05, n)
        delta = np.arctan(WHEELBASE * self.course.kappa(s))
        v = rng.uniform(6.0, 10.0, n)
        return self.observe(s, e, e_psi, delta, v)

    def integrate(
        self, states: np.ndarray, actions: np.ndarray, seed: int, substeps: bool = False
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Advance one control step; optionally also return the (N_SUB, n, 5) sub-step states."""
        x = np.asarray(states, dtype=np.float64).reshape(-1, self.obs_dim)
        s, e, e_psi, delta, v = (x[:, i].copy() for i in range(5))
        cmd, acc = self.command_values(actions)
        noise = np.random.default_rng(seed).normal(0.0, self.heading_noise, len(x)) if self.heading_noise else 0.0
        h = DT / N_SUB
        lag = 1.0 - np.exp(-h / TAU_STEER)
        hist = []
        for k in range(N_SUB):
            kap = self.course.kappa(s)
            s_dot = v * np.cos(e_psi) / (1.0 - kap * e)
            e_dot = v * np.sin(e_psi)
            psi_dot = v * np.tan(delta) / WHEELBASE - kap * s_dot
            s, e, e_psi = s + h * s_dot, e + h * e_dot, e_psi + h * psi_dot
            delta = delta + lag * (cmd - delta)
            if acc is not None:  # steer_accel: the speed is controlled (within bounds)
                v = np.clip(v + h * acc, V_MIN, V_MAX)
            if k == N_SUB - 1:
                e_psi = e_psi + noise
            if substeps:
                hist.append(np.column_stack([np.mod(s, self.course.length), e, e_psi, delta, v]))
        return self.observe(s, e, e_psi, delta, v), (np.stack(hist) if substeps else None)

    def step_seeded(self, states: np.ndarray, actions: np.ndarray, seed: int) -> StepResult:
        nxt, _ = self.integrate(states, actions, seed)
        cmd, acc = self.command_values(actions)
        off_road = np.abs(nxt[:, 1]) > ROAD_HALF_WIDTH
        running = np.abs(nxt[:, 1]) + CONTROL_WEIGHT * cmd**2
        if acc is not None:
            running = running + SPEED_WEIGHT * (nxt[:, 4] - V_TARGET) ** 2 + ACCEL_WEIGHT * acc**2
        cost = np.where(off_road, FAILURE_COST, running)
        return StepResult(nxt, cost, off_road)

    dt = DT
    mcap_layout = "vehicle"
    traced_features = {"e": "mean |cross-track error| [m]"}
    map_features = ("e", "e_psi")

    @classmethod
    def summary_line(cls, policy: dict[str, Any], demonstrator: dict[str, Any]) -> str:
        if "mean_abs_cross_track_error_m" not in policy:
            return ""
        return (f"mean |cross-track error| {policy['mean_abs_cross_track_error_m']:.3f} m vs "
                f"{demonstrator['mean_abs_cross_track_error_m']:.3f} m, failures {policy['failures']} vs "
                f"{demonstrator['failures']}")

    def rollout_summary(self, states: list[np.ndarray], terminated: np.ndarray) -> dict[str, float]:
        """Mean |cross-track error| over every visited state [m], and failures (left the road)."""
        e = np.abs(np.concatenate([x[:, 1] for x in states])) if states else np.zeros(0)
        return {"mean_abs_cross_track_error_m": float(e.mean()) if len(e) else float("nan"),
                "failures": int(np.sum(terminated)), "failure_fraction": float(np.mean(terminated))}

    def demonstrator(self, gain: float = 1.5, noise: float = 0.04, epsilon: float = 0.05) -> Policy:
        """Stanley-style human-like driver (see module docstring), stochastic with known probabilities.

        With continuous commands: the same driver, its Gaussian steering noise not quantised
        (a :class:`~offline_adp.policies.GaussianCommandPolicy`; ``commands()`` is the
        noise-free Stanley controller), plus the speed keeper with ``steer_accel``."""
        if self.commands != "discrete":
            return self._continuous_behaviour(gain, noise, epsilon)
        edges = np.r_[-np.inf, (STEERING_COMMANDS[1:] + STEERING_COMMANDS[:-1]) / 2, np.inf]

        def probs(x: np.ndarray, t: object) -> np.ndarray:
            target = -(x[:, 2] + np.arctan(gain * x[:, 1] / np.maximum(x[:, 4], 0.1)))
            cdf = ndtr((edges[None, :] - target[:, None]) / noise)
            return np.diff(cdf, axis=1)

        return EpsilonPolicy(StochasticFunctionPolicy(probs, self.n_actions, name="stanley"), epsilon)

    def exploration(self) -> Policy:
        """Uniformly random commands: over the seven indices (discrete), or uniform within
        the bounds (continuous modes)."""
        if self.commands == "discrete":
            return super().exploration()
        return self._continuous_behaviour(0.0, 0.0, 1.0, name="uniform")

    def _continuous_behaviour(self, gain: float, noise: float, epsilon: float, name: str = "stanley") -> Policy:
        two = self.commands == "steer_accel"

        def mean(x: np.ndarray, t: object) -> np.ndarray:
            steer = -(x[:, 2] + np.arctan(gain * x[:, 1] / np.maximum(x[:, 4], 0.1)))
            if not two:
                return steer[:, None]
            return np.column_stack([steer, -0.5 * (x[:, 4] - V_TARGET)])

        lo, hi = self.action_table.bounds()
        grid = [STEERING_COMMANDS, ACCEL_BINS] if two else [STEERING_COMMANDS]
        std = [noise, 0.3 if noise > 0 else 0.0] if two else [noise]
        return GaussianCommandPolicy(mean, std, lo, hi, epsilon=epsilon, grid=grid, name=name)
