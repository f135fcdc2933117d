from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def small_pt():
    """A small path_tracking dataset (demonstrations + exploration)."""
    from offline_adp.simulate import simulate

    return simulate("path_tracking", 8, 8, seed=11, horizon=60)
