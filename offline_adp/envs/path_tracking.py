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
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from scipy.special import ndtr

from offline_adp.access import Simulator, StepResult
from offline_adp.data.info import ActionTable, Feature
from offline_adp.envs.base import ReferenceProblem
from offline_adp.policies import EpsilonPolicy, Policy, StochasticFunctionPolicy

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

    def __init__(self, horizon: int | None = 200, heading_noise: float = HEADING_NOISE) -> None:
        self.horizon = horizon
        self.heading_noise = heading_noise

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
        cmd = STEERING_COMMANDS[np.asarray(actions, dtype=np.int64)]
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
            if k == N_SUB - 1:
                e_psi = e_psi + noise
            if substeps:
                hist.append(np.column_stack([np.mod(s, self.course.length), e, e_psi, delta, v]))
        return self.observe(s, e, e_psi, delta, v), (np.stack(hist) if substeps else None)

    def step_seeded(self, states: np.ndarray, actions: np.ndarray, seed: int) -> StepResult:
        nxt, _ = self.integrate(states, actions, seed)
        cmd = STEERING_COMMANDS[np.asarray(actions, dtype=np.int64)]
        off_road = np.abs(nxt[:, 1]) > ROAD_HALF_WIDTH
        cost = np.where(off_road, FAILURE_COST, np.abs(nxt[:, 1]) + CONTROL_WEIGHT * cmd**2)
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
        """Stanley-style human-like driver (see module docstring), stochastic with known probabilities."""
        edges = np.r_[-np.inf, (STEERING_COMMANDS[1:] + STEERING_COMMANDS[:-1]) / 2, np.inf]

        def probs(x: np.ndarray, t: object) -> np.ndarray:
            target = -(x[:, 2] + np.arctan(gain * x[:, 1] / np.maximum(x[:, 4], 0.1)))
            cdf = ndtr((edges[None, :] - target[:, None]) / noise)
            return np.diff(cdf, axis=1)

        return EpsilonPolicy(StochasticFunctionPolicy(probs, self.n_actions, name="stanley"), epsilon)
