"""The chapter's access models, strongest first, and what each can simulate.

==================  =============================================  ===================
access model        what it offers                                  used by
==================  =============================================  ===================
``FullModel``       transition and cost arrays ``P[a, s, s']``,     exact DP (oracle)
                    ``C[s, a]`` of a finite MDP
``Simulator``       deterministic ``step_seeded(x, a, seed)``       rollouts with common
                    from any state                                  random numbers
``GenerativeModel`` ``step(x, a, rng)``: sample x' from any state   PSDP, iterated FQI
``ResetModel``      ``initial_states(n, rng)`` then ``step`` from   CPI line search,
                    states reached that way                         iterated PSDP
trace data          a :class:`~offline_adp.data.dataset.            FQI, FQE, API, OPE
                    TransitionDataset` of logged transitions
==================  =============================================  ===================

Each class derives from the next weaker one, so a stronger model *is* a weaker one
(the downward adapters are the inherited implementations): a ``FullModel`` samples
next states by inverse CDF, a ``Simulator`` draws its seed from the caller's
generator, and a ``GenerativeModel`` with a start distribution is a ``ResetModel``.
Everything is batched: states are ``(n, d)`` float arrays, actions ``(n,)`` int arrays.
A model whose ``accepts_commands`` is true also steps continuous commands: an ``(n, m)``
float array of command vectors in place of the indices (see :func:`command_matrix`).
Algorithms type-hint the weakest model they need and call :func:`require`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import AccessModelError, InvalidArgumentError

#: Trace data: the weakest access model, a dataset of logged transitions.
TraceData = TransitionDataset


@dataclass(frozen=True)
class StepResult:
    """Outcome of a batched step: next states (n, d), costs (n,), terminated (n,)."""

    next_states: np.ndarray
    costs: np.ndarray
    terminated: np.ndarray


class ResetModel(ABC):
    """Reset to the start distribution, then simulate forward.

    Contract: ``step`` is called only on states reached from ``initial_states`` (a
    physical system or a simulator that cannot be teleported).

    Attributes
    ----------
    n_actions : int
    obs_dim : int
    gamma : float
        Discount factor of the problem (1.0 for undiscounted episodic problems).
    horizon : int or None
        Episode time limit T (truncation), if any.
    accepts_commands : bool
        Whether ``step`` also takes continuous commands, an ``(n, m)`` float array (one
        command vector per row), besides ``(n,)`` action indices. Rollouts of a continuous
        policy (``policy.continuous``) need it: they pass the policy's commands, never its
        binned view.
    """

    n_actions: int
    obs_dim: int
    gamma: float = 1.0
    horizon: int | None = None
    accepts_commands: bool = False

    @abstractmethod
    def initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` start states drawn from the start distribution, shape (n, obs_dim)."""

    @abstractmethod
    def step(self, states: np.ndarray, actions: np.ndarray, rng: np.random.Generator) -> StepResult:
        """Sample one transition per row."""


class GenerativeModel(ResetModel):
    """Sample a next state and cost from *any* state and action (``step`` has no
    reachability contract)."""


class Simulator(GenerativeModel):
    """Deterministic simulative model: the outcome is a function of (x, a, seed).

    Calling ``step_seeded`` twice with the same seed gives the same rows, which gives
    common random numbers across actions (row i's noise depends only on seed and i).
    """

    @abstractmethod
    def step_seeded(self, states: np.ndarray, actions: np.ndarray, seed: int) -> StepResult:
        """One deterministic transition per row."""

    def step(self, states: np.ndarray, actions: np.ndarray, rng: np.random.Generator) -> StepResult:
        return self.step_seeded(states, actions, int(rng.integers(2**63 - 1)))


class FullModel(Simulator):
    """A finite MDP given by its arrays; observations are ``[[s]]`` state indices.

    Parameters
    ----------
    P : ndarray, shape (A, S, S)
        ``P[a, s, s']`` transition probabilities (rows sum to 1).
    C : ndarray, shape (S, A)
        Expected cost of taking ``a`` in ``s``.
    initial_distribution : ndarray, shape (S,)
    gamma : float
    horizon : int or None
    terminal : ndarray of bool, shape (S,), optional
        Absorbing zero-cost states; reaching one marks the transition ``terminated``.
    """

    def __init__(
        self,
        P: np.ndarray,
        C: np.ndarray,
        initial_distribution: np.ndarray,
        gamma: float = 1.0,
        horizon: int | None = None,
        terminal: np.ndarray | None = None,
    ) -> None:
        P = np.asarray(P, dtype=np.float64)
        C = np.asarray(C, dtype=np.float64)
        A, S, S2 = P.shape
        if S != S2 or C.shape != (S, A):
            raise InvalidArgumentError(f"P must be (A, S, S) and C (S, A); got P {P.shape}, C {C.shape}")
        if not np.allclose(P.sum(-1), 1.0, atol=1e-10):
            raise InvalidArgumentError("rows of P must sum to 1")
        self.P, self.C = P, C
        self.initial_distribution = np.asarray(initial_distribution, dtype=np.float64)
        self.gamma, self.horizon = float(gamma), horizon
        self.terminal = np.zeros(S, bool) if terminal is None else np.asarray(terminal, bool)
        self.n_states, self.n_actions, self.obs_dim = S, A, 1
        self._cdf = np.cumsum(P, axis=-1)

    def initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return rng.choice(self.n_states, size=n, p=self.initial_distribution).astype(np.float64)[:, None]

    def step_seeded(self, states: np.ndarray, actions: np.ndarray, seed: int) -> StepResult:
        s = np.asarray(states).reshape(-1).astype(np.int64)
        a = np.asarray(actions).astype(np.int64)
        u = np.random.default_rng(seed).random(len(s))
        cdf = self._cdf[a, s]  # (n, S)
        nxt = np.minimum((u[:, None] >= cdf).sum(axis=1), self.n_states - 1)
        return StepResult(nxt.astype(np.float64)[:, None], self.C[s, a], self.terminal[nxt])


def is_command_array(actions: np.ndarray) -> bool:
    """Whether ``actions`` passed to ``step`` are command vectors ``(n, m)`` (two axes),
    not ``(n,)`` action indices."""
    return np.ndim(actions) == 2


def command_matrix(actions: np.ndarray, n: int, low: np.ndarray, high: np.ndarray, name: str) -> np.ndarray:
    """Commands ``(n, m)`` for a model's ``step``, checked and clipped into ``[low, high]``.

    Raises :class:`~offline_adp.errors.IncompatibleError` when the array does not hold one
    command of ``m = len(low)`` components per state and
    :class:`~offline_adp.errors.InvalidArgumentError` when a command is not a finite number;
    ``name`` (the simulator) heads the message.
    """
    from offline_adp.errors import IncompatibleError, InvalidArgumentError

    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    try:
        u = np.asarray(actions, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidArgumentError(f"simulator {name!r}: commands must be numbers ({exc})") from None
    if u.shape != (n, len(low)):
        raise IncompatibleError(f"simulator {name!r}: commands must be an array of shape ({n}, {len(low)}) "
                                f"(one command of {len(low)} components per state), got {u.shape}")
    bad = ~np.isfinite(u).all(axis=1)
    if bad.any():
        rows = np.flatnonzero(bad)
        raise InvalidArgumentError(f"simulator {name!r}: {len(rows)} command(s) are not finite, e.g. row "
                                   f"{int(rows[0])}: {u[rows[0]].tolist()}")
    return np.clip(u, low, high)


def require(model: object, needed: type) -> None:
    """Raise :class:`AccessModelError` unless ``model`` offers the ``needed`` access.

    ``needed`` is one of :class:`ResetModel`, :class:`GenerativeModel`,
    :class:`Simulator`, :class:`FullModel`, or :data:`TraceData`.
    """
    if not isinstance(model, needed):
        have = [c.__name__ for c in (FullModel, Simulator, GenerativeModel, ResetModel,
                                     TransitionDataset) if isinstance(model, c)]
        raise AccessModelError(
            f"this algorithm needs a {needed.__name__} access model; got {type(model).__name__}"
            + (f" (which offers {have[0]})" if have else "")
        )
