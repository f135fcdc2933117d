from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

# Property-based and fuzz tests: a bounded number of examples in CI ("ci", the default),
# many more by hand: `pytest --hypothesis-profile nightly`.
settings.register_profile(
    "ci",
    deadline=None,
    derandomize=True,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.register_profile(
    "nightly",
    deadline=None,
    max_examples=5000,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


#: Modules that drive whole CLI commands or pipelines end to end (marked ``integration``;
#: ``make test-fast`` leaves them out, ``make test`` and CI run everything).
INTEGRATION_MODULES = {"test_pipeline", "test_cli", "test_fit_run", "test_distributed", "test_notebooks", "test_report",
                       "test_concurrency"}

#: Files holding a test of about a minute or more (2026-11-26, `pytest -n 2 --durations`):
#: started first. Only the order depends on this list.
LONGEST_MODULES = {"test_ope_coverage", "test_readme_demo", "test_readme_tour", "test_distributed"}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.module.__name__.rsplit(".", 1)[-1] in INTEGRATION_MODULES:
            item.add_marker(pytest.mark.integration)
    # Long tests first: `make test` runs on two xdist workers, which take tests in this
    # order, so a minute-long test started last would leave one worker idle while the
    # other finishes it. A stable sort: within each group the files keep their order.
    def rank(item: pytest.Item) -> int:
        if item.module.__name__.rsplit(".", 1)[-1] in LONGEST_MODULES:
            return 0
        return 1 if item.get_closest_marker("slow") else 2 if item.get_closest_marker("integration") else 3

    items.sort(key=rank)


@pytest.fixture(scope="session")
def small_pt():
    """A small path_tracking dataset (demonstrations + exploration)."""
    from offline_adp.simulate import simulate

    return simulate("path_tracking", 8, 8, seed=11, horizon=60)


class EvaluateRunCalled(Exception):
    """Raised by the ``captured_evaluate_run`` fixture's stand-in for ``evaluate_run``."""


@pytest.fixture
def captured_evaluate_run(monkeypatch):
    """Replace ``evaluation.run.evaluate_run`` with a stand-in that records its keyword
    arguments and raises :class:`EvaluateRunCalled` (what the CLI and a pipeline pass)."""
    from offline_adp.evaluation import run as evaluation_run

    seen: list[dict] = []

    def fake_evaluate_run(run_dir, settings=None, **kw):
        if settings is not None:  # the settings object, read under the Python API's keyword names
            named = {"episodes": "n_episodes", "bootstrap": "n_boot", "fqe_bootstrap": "n_boot_fqe"}
            kw = {**{named.get(k, k): v for k, v in settings.model_dump().items()}, "settings": settings, **kw}
        seen.append(kw)
        raise EvaluateRunCalled

    monkeypatch.setattr(evaluation_run, "evaluate_run", fake_evaluate_run)
    return seen
