"""The one discount rule: explicit settings, else the dataset's hints, else stated defaults;
fitting and evaluation agree on it."""

from __future__ import annotations

import json

import pytest

from offline_adp.cli import main
from offline_adp.data.discount import DEFAULT_GAMMA, resolve_discount
from offline_adp.data.info import DatasetInfo
from offline_adp.errors import SpecError
from offline_adp.simulate import simulate


def _info(gamma, horizon):
    ds = simulate("tabular", 2, 2, seed=0)
    return DatasetInfo(**{**ds.info.__dict__, "gamma": gamma, "horizon": horizon})


@pytest.mark.parametrize(("hints", "explicit", "terminates", "want"), [
    ((None, None), (None, None), False, (DEFAULT_GAMMA, None)),      # nothing said: the stated default
    ((0.9, 200), (None, None), False, (0.9, None)),                  # a discounted time limit is not T
    ((1.0, 10), (None, None), False, (1.0, 10)),                     # undiscounted with a horizon: the T-step problem
    ((1.0, 100), (None, None), True, (1.0, None)),                   # undiscounted shortest path: infinite horizon
    ((0.9, 10), (0.5, None), False, (0.5, None)),                    # explicit gamma wins
    ((0.9, None), (None, 7), False, (0.9, 7)),                       # explicit horizon, hinted gamma
    ((None, None), (None, 7), False, (1.0, 7)),                      # finite horizon default gamma = 1
])
def test_rule(hints, explicit, terminates, want):
    d = resolve_discount(_info(*hints), gamma=explicit[0], horizon=explicit[1], terminates=terminates)
    assert (d.gamma, d.horizon) == want


@pytest.mark.parametrize("bad", [{"gamma": 0.0}, {"gamma": 1.5}, {"horizon": 0}, {"horizon": 2.5}])
def test_bad_values(bad):
    with pytest.raises(SpecError):
        resolve_discount(None, **bad)


def test_fit_uses_the_datasets_horizon_hint(tmp_path, capsys):
    """simulate tabular (gamma 1, horizon 10) then fit with no config: the 10-step problem,
    not a traceback asking for the horizon the dataset declares."""
    ds = tmp_path / "tab"
    assert main(["simulate", "tabular", "--out", str(ds), "--demonstrations", "20", "--exploration", "20", "-q"]) == 0
    out = tmp_path / "run"
    assert main(["fit", str(ds), "--out", str(out), "-q"]) == 0
    hist = json.loads((out / "run.json").read_text())
    assert hist["status"] == "completed" and hist["iterations"] == 10
    meta = json.loads((out / "model" / "q.json").read_text())
    assert meta["horizon"] == 10 and meta["gamma"] == 1.0
