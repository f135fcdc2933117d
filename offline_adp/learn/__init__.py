"""How one fitted-Q step ``Q_k = LEARN({(x_i, a_i), y_i})`` is carried out.

Fitted Q-iteration and fitted Q evaluation share the same inner step; what differs is
the targets. A *learner* owns the regression inputs of the training pairs and of every
query set the algorithm needs (next states for the targets, start states, held-out
pairs) and answers ``fit(y)`` then ``predict(name)``:

- :class:`~offline_adp.learn.refit.RefitLearner` (the naive loop): clone and fit the regressor on every
  iteration; prediction is one batched call per query set.
- :class:`~offline_adp.learn.frozen.FrozenTreesLearner` (Ernst et al. 2005, section 4.3): fit a tree ensemble's
  *structure* once (and again on demand), precompute the leaf reached by every training
  and query input, and thereafter only re-average leaf values: an O(n * trees) gather,
  no tree fitting or traversal. With a fixed structure the update is a kernel averager,
  hence a gamma-contraction: it converges.
- :class:`~offline_adp.learn.warm_start.LightGBMWarmStartLearner`: each iteration adds a few boosted trees fitted to
  the change in targets, with the previous Q's predictions on the fixed training and
  query inputs cached, so only the new trees are evaluated.

Every learner is built from a :class:`~offline_adp.learn.base.LearnSpec` (the training
pairs, weights, seed and query sets) plus its mode's options (the frozen mode's
:class:`~offline_adp.learn.schedule.FrozenSchedule`). Query sets are ``(phi, actions)`` pairs: ``actions=None`` asks
for all actions (result (m, n_actions)), otherwise for the given action per row (result (m,)).
"""

from offline_adp.learn.base import Learner, LearnSpec, Query
from offline_adp.learn.frozen import FrozenTreesLearner
from offline_adp.learn.refit import RefitLearner
from offline_adp.learn.schedule import (
    EarlyBuilds,
    FrozenSchedule,
    TreeScreen,
    build_weight,
    check_structure_fractions,
    greedy_min_bias,
)
from offline_adp.learn.settle import Settle
from offline_adp.learn.warm_start import LightGBMWarmStartLearner

__all__ = ["EarlyBuilds", "FrozenSchedule", "FrozenTreesLearner", "Learner", "LearnSpec", "LightGBMWarmStartLearner",
           "Query", "RefitLearner", "Settle", "TreeScreen", "build_weight", "check_structure_fractions",
           "greedy_min_bias"]
