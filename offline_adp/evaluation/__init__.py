"""Evaluation of a fitted policy: rollouts, off-policy estimates, shift diagnostics,
report and comparison (see ``docs/evaluation.md``).

Only plain constants (and a check of one of them) live here, so the CLI's parser and the
pipeline file's model can share them without importing numpy.
"""

from __future__ import annotations

#: FQE bootstrap replicates when none are asked for: the one default of
#: ``offline-adp evaluate --fqe-bootstrap``, a pipeline's ``[evaluate] fqe_bootstrap`` and
#: :func:`offline_adp.evaluation.run.evaluate_run`. ``None`` is the replicate rule of
#: :func:`offline_adp.evaluation.fqe_interval.fqe_replicates`: the floor (200) when
#: replicates are cheap, else 50.
FQE_BOOTSTRAP_DEFAULT: int | None = None
#: Particles of the model rollouts of the logs (``model_rollouts.N_PARTICLES``), the one
#: default of ``offline-adp evaluate --model-particles``, ``[evaluate] model_particles`` and
#: :func:`offline_adp.evaluation.run.evaluate_run`; 0 turns them off.
MODEL_PARTICLES_DEFAULT: int = 1000
#: ... and at most this many: far above any useful count, so a typo (1e12) is an error naming
#: the setting instead of an allocation that fails half-way through an evaluation
MAX_MODEL_PARTICLES: int = 1_000_000


def particle_count_error(n: int) -> str | None:
    """Why ``n`` is not a model-rollout particle count (None: it is): 0 turns them off,
    their Monte-Carlo interval needs at least 2, and at most :data:`MAX_MODEL_PARTICLES`. The one check of the CLI, a
    pipeline's
    ``[evaluate]``, ``evaluation_metrics`` and ``off_policy``."""
    if n < 0 or n == 1:
        return (
            f"model_particles must be 0 (no model rollouts) or at least 2 (a Monte-Carlo interval needs two), got {n}"
        )
    if n > MAX_MODEL_PARTICLES:
        return f"model_particles must be at most {MAX_MODEL_PARTICLES:,}, got {n:,}"
    return None
