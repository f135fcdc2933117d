"""Exact dynamic programming on a full model: the oracle every test compares against.

Conventions: ``P[a, s, s']`` transition probabilities, ``C[s, a]`` expected costs
(minimised), policies as probability tables ``(S, A)`` (stationary) or ``(T, S, A)``
(non-stationary; integer tables of actions are accepted and one-hot encoded).

Finite horizon T (undiscounted unless ``gamma`` is given)::

    V_T(s) = 0
    Q_t(s, a) = C(s, a) + gamma * sum_s' P(s' | s, a) V_{t+1}(s')
    V_t(s) = min_a Q_t(s, a)                       (value iteration)
    V^pi_t(s) = sum_a pi_t(a | s) Q^pi_t(s, a)    (policy evaluation)

Discounted: ``V = min_a C + gamma P V`` solved by policy iteration with exact linear
solves ``(I - gamma P_pi) V = c_pi``, so the answer is exact to round-off.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from offline_adp.errors import InvalidArgumentError


@dataclass(frozen=True)
class DPSolution:
    """Optimal (or policy) values.

    Attributes
    ----------
    V : ndarray
        ``(T + 1, S)`` for finite horizon (``V[T] = 0``), ``(S,)`` discounted.
    Q : ndarray
        ``(T, S, A)`` finite horizon, ``(S, A)`` discounted.
    policy : ndarray of int
        Greedy actions ``(T, S)`` or ``(S,)`` (lowest index on ties).
    """

    V: np.ndarray
    Q: np.ndarray
    policy: np.ndarray


def _as_probs(policy: np.ndarray, n_actions: int) -> np.ndarray:
    policy = np.asarray(policy)
    if np.issubdtype(policy.dtype, np.integer):
        return np.eye(n_actions)[policy]
    return policy.astype(np.float64)


def _backup(P: np.ndarray, C: np.ndarray, V_next: np.ndarray, gamma: float) -> np.ndarray:
    # Q(s, a) = C(s, a) + gamma * sum_s' P[a, s, s'] V(s')
    return C + gamma * np.einsum("ast,t->sa", P, V_next)


def value_iteration_finite(P: np.ndarray, C: np.ndarray, horizon: int, gamma: float = 1.0) -> DPSolution:
    """Optimal non-stationary values and policy for horizon ``T`` (backward induction)."""
    A, S, _ = P.shape
    V = np.zeros((horizon + 1, S))
    Q = np.zeros((horizon, S, A))
    for t in range(horizon - 1, -1, -1):
        Q[t] = _backup(P, C, V[t + 1], gamma)
        V[t] = Q[t].min(axis=1)
    return DPSolution(V, Q, Q.argmin(axis=2))


def policy_evaluation_finite(
    P: np.ndarray, C: np.ndarray, policy: np.ndarray, horizon: int, gamma: float = 1.0
) -> DPSolution:
    """Exact ``V^pi_t``, ``Q^pi_t`` of a (possibly non-stationary, stochastic) policy."""
    A, S, _ = P.shape
    pi = _as_probs(policy, A)
    if pi.ndim == 2:
        pi = np.broadcast_to(pi, (horizon, S, A))
    V = np.zeros((horizon + 1, S))
    Q = np.zeros((horizon, S, A))
    for t in range(horizon - 1, -1, -1):
        Q[t] = _backup(P, C, V[t + 1], gamma)
        V[t] = (pi[t] * Q[t]).sum(axis=1)
    return DPSolution(V, Q, Q.argmin(axis=2))


def policy_evaluation_discounted(P: np.ndarray, C: np.ndarray, policy: np.ndarray, gamma: float) -> DPSolution:
    """Exact discounted ``V^pi`` by a linear solve ``(I - gamma P_pi) V = c_pi``."""
    if not gamma < 1.0:
        raise InvalidArgumentError("discounted evaluation needs gamma < 1")
    A, S, _ = P.shape
    pi = _as_probs(policy, A)
    P_pi = np.einsum("sa,ast->st", pi, P)
    c_pi = (pi * C).sum(axis=1)
    V = np.linalg.solve(np.eye(S) - gamma * P_pi, c_pi)
    Q = _backup(P, C, V, gamma)
    return DPSolution(V, Q, Q.argmin(axis=1))


def value_iteration_discounted(P: np.ndarray, C: np.ndarray, gamma: float, max_iter: int = 1000) -> DPSolution:
    """Optimal discounted values by policy iteration (exact; terminates finitely).

    Ties in the improvement step keep the current action, so the loop cannot cycle.
    """
    A, S, _ = P.shape
    policy = C.argmin(axis=1)
    for _ in range(max_iter):
        sol = policy_evaluation_discounted(P, C, policy, gamma)
        q_cur = sol.Q[np.arange(S), policy]
        best = sol.Q.argmin(axis=1)
        improve = sol.Q[np.arange(S), best] < q_cur - 1e-12 * (1 + np.abs(q_cur))
        if not improve.any():
            return DPSolution(sol.V, sol.Q, sol.Q.argmin(axis=1))
        policy = np.where(improve, best, policy)
    raise RuntimeError(f"policy iteration did not converge in {max_iter} iterations")


def state_distributions(P: np.ndarray, policy: np.ndarray, mu0: np.ndarray, horizon: int) -> np.ndarray:
    """Exact per-step state distributions ``mu_t`` of a policy, shape (T + 1, S).

    ``mu_{t+1}(s') = sum_s mu_t(s) sum_a pi_t(a | s) P(s' | s, a)``.
    """
    A, S, _ = P.shape
    pi = _as_probs(policy, A)
    if pi.ndim == 2:
        pi = np.broadcast_to(pi, (horizon, S, A))
    mu = np.zeros((horizon + 1, S))
    mu[0] = mu0
    for t in range(horizon):
        mu[t + 1] = np.einsum("s,sa,ast->t", mu[t], pi[t], P)
    return mu


def discounted_occupancy(P: np.ndarray, policy: np.ndarray, mu0: np.ndarray, gamma: float) -> np.ndarray:
    """Normalised discounted occupancy ``d = (1 - gamma) mu0^T (I - gamma P_pi)^{-1}``."""
    A, S, _ = P.shape
    pi = _as_probs(policy, A)
    P_pi = np.einsum("sa,ast->st", pi, P)
    return (1.0 - gamma) * np.linalg.solve((np.eye(S) - gamma * P_pi).T, mu0)
