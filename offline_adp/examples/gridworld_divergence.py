"""Boyan & Moore's divergence demonstration, as in the chapter (and the FQI issue).

Data: one transition for every lattice state of the 2-D gridworld and every move (the
whole model, no sampling noise). True cost-to-go: ``J*(x, y) = 20 - 10 (x + y)``, linear.

- Fitted Q-iteration with *quadratic regression* (polynomial features of degree 2 over
  ``(x, y, dx, dy)`` + least squares) underestimates the values at the corner (0, 0)
  opposite the goal, and its error grows across iterations; the divergence monitor
  flags it (``DivergenceWarning``).
- With *extra-trees* or a *table*, the same iteration converges to ``J*`` exactly.

Run ``python -m offline_adp.examples.gridworld_divergence`` to print the error per
iteration for each learner.
"""

from __future__ import annotations

import warnings

import numpy as np

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.data.dataset import TransitionDataset
from offline_adp.envs.gridworld import Gridworld, optimal_cost_to_go
from offline_adp.qfunctions import q_support, restrict_to_support


def dataset() -> TransitionDataset:
    """Every (lattice state, move) pair once; the goal is absorbing."""
    gw = Gridworld()
    xy = gw.lattice_states()[:-1]
    X = np.repeat(xy, 4, axis=0)
    a = np.tile(np.arange(4), len(xy))
    r = gw.step_seeded(X, a)
    n = len(X)
    return TransitionDataset.from_arrays(
        gw.dataset_info(), episode_id=np.char.zfill(np.arange(n).astype(str), 7), step=np.zeros(n), obs=X, action=a,
        cost=r.costs, next_obs=r.next_states, terminated=r.terminated, truncated=~r.terminated,
    )


def run(regressor: str, n_iterations: int = 90, **params) -> tuple[list[float], list[float], FittedQIteration]:
    """Per iteration: max |V - J*| over the lattice and V at the corner (0, 0)."""
    lattice = Gridworld.lattice_states()
    J = optimal_cost_to_go(lattice)
    f = FittedQIteration(gamma=1.0, regressor=regressor, regressor_params=params or None, n_iterations=n_iterations,
                         on_divergence="warn")
    errors, corner = [], []
    for _ in f.fit_iter(dataset()):
        V = restrict_to_support(f.q_function_.values(lattice), q_support(f.q_function_, lattice)).min(axis=1)
        errors.append(float(np.abs(V - J)[:-1].max()))
        corner.append(float(V[0]))
    return errors, corner, f


if __name__ == "__main__":
    for reg, params in (("ridge", {}), ("extra_trees", {"n_estimators": 10, "n_jobs": 1}), ("tabular", {})):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            errors, corner, f = run(reg, **params)
        print(f"{reg:>12}: max|V - J*| at iterations 1, 20, 40, 60, 80: "
              + ", ".join(f"{errors[k]:.2f}" for k in (0, 19, 39, 59,
                                                       79)) + f"; V(0, 0) at 40: {corner[39]:.2f} (J* = 20)")
        for c in caught:
            print(f"{'':>14}{c.category.__name__}: {c.message}")
