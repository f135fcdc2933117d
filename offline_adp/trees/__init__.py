"""Tree ensembles: the array engine, the compiled extra-trees builder, and the conversion
to and from scikit-learn's tree objects.

- :mod:`offline_adp.trees.ensemble`: :class:`~offline_adp.trees.ensemble.TreeEnsemble`
  (flat arrays, prediction, leaf lookups, ``.npz`` storage) and the leaf-lookup helpers.
- :mod:`offline_adp.trees.builder`: extremely randomized trees grown by a compiled (numba)
  builder, for the frozen-structure LEARN step.
- :mod:`offline_adp.trees.averaging`: the frozen averager's threaded kernels (leaf sums,
  means over trees).
- :mod:`offline_adp.trees.sklearn`: the one module that reads or sets scikit-learn's
  private tree state.
"""

from offline_adp.trees.ensemble import TreeEnsemble, ensemble_predict

__all__ = ["TreeEnsemble", "ensemble_predict"]
