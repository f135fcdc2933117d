"""Saving and loading fitted Q-functions without executing code from the files.

Everything is JSON, ``.npz`` arrays (loaded with ``allow_pickle=False``) or LightGBM's
text model format. scikit-learn forests are exported to :class:`TreeEnsemble` arrays;
other scikit-learn estimators go through an explicit allow-list: their constructor
parameters (JSON) and fitted array attributes are stored, and loading rebuilds the
estimator from the allow-listed class and sets those attributes. Anything else raises
:class:`ArtifactError` naming the type, rather than falling back to pickle.

The parts, each importable on its own (everything is re-exported here):

- :mod:`~offline_adp.artifacts.storage`: the ``.json`` + ``.npz`` files, format versions,
  the model hashes a run records and loading checks;
- :mod:`~offline_adp.artifacts.kinds`: the registries of savable kinds;
- :mod:`~offline_adp.artifacts.q_kinds`: Q-functions (:func:`save_q`, :func:`load_q`,
  :func:`register_q_kind`);
- :mod:`~offline_adp.artifacts.policy_kinds`: policies (:func:`save_policy`,
  :func:`load_index_policy`, :func:`register_policy_kind`);
- :mod:`~offline_adp.artifacts.estimators`: estimators inside them (tree ensembles,
  LightGBM, the scikit-learn allow-list);
- :mod:`~offline_adp.artifacts.checks`: the checks every untrusted member passes.
"""

# ruff: noqa: F401  (besides __all__, every name this module held before it was split still imports from it)

from __future__ import annotations

from offline_adp.artifacts.estimators import (
    ALLOWED,
    Arrays,
    _Booster,
    _export_estimator,
    _guard,
    _import_estimator,
    _width,
)
from offline_adp.artifacts.kinds import (
    _Kinds,
)
from offline_adp.artifacts.policy_kinds import (
    _POLICY_KINDS,
    _export_policy,
    _import_policy,
    _read_classifier,
    _read_distilled,
    _read_greedy_command,
    _read_mixture,
    _read_parts,
    _read_tabular,
    _register_policies,
    _write_classifier,
    _write_distilled,
    _write_tabular,
    load_index_policy,
    register_policy_kind,
    save_policy,
)
from offline_adp.artifacts.q_kinds import (
    _Q_KINDS,
    _export_q,
    _import_q,
    _model_width,
    _probe,
    _read_boosted_sum,
    _read_candidates,
    _read_encoded,
    _read_regressor,
    _read_time_indexed,
    _write_boosted_sum,
    _write_encoder,
    _write_regressor,
    _write_time_indexed,
    load_q,
    register_q_kind,
    save_q,
)
from offline_adp.artifacts.storage import (
    ARTIFACT_VERSION,
    HASHED,
    READABLE_VERSIONS,
    _read,
    _write,
    check_recorded_hashes,
    model_hashes,
    versions,
)
from offline_adp.errors import (
    ArtifactError,
    FormatVersionWarning,
)

__all__ = ["ALLOWED", "ARTIFACT_VERSION", "HASHED", "READABLE_VERSIONS", "Arrays", "check_recorded_hashes",
           "load_index_policy", "load_q", "model_hashes", "register_policy_kind", "register_q_kind", "save_policy",
           "save_q", "versions"]
