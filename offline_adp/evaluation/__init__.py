"""Evaluation of a fitted policy: rollouts, off-policy estimates, shift diagnostics,
report and comparison (see ``docs/evaluation.md``).

Only plain constants live here, so the CLI's parser and the pipeline file's model can
share them without importing numpy.
"""

from __future__ import annotations

#: FQE bootstrap replicates when none are asked for: the one default of
#: ``offline-adp evaluate --fqe-bootstrap``, a pipeline's ``[evaluate] fqe_bootstrap`` and
#: :func:`offline_adp.evaluation.run.evaluate_run`. ``None`` is the replicate rule of
#: :func:`offline_adp.evaluation.offpolicy.fqe_replicates`: the floor (200) when
#: replicates are cheap, else 50.
FQE_BOOTSTRAP_DEFAULT: int | None = None
#: Particles of the model rollouts of the logs (``model_rollouts.N_PARTICLES``), the one
#: default of ``offline-adp evaluate --model-particles``, ``[evaluate] model_particles`` and
#: :func:`offline_adp.evaluation.run.evaluate_run`; 0 turns them off.
MODEL_PARTICLES_DEFAULT: int = 1000
