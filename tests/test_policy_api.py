"""The user-facing policy API (dicts, DataFrames, arrays; values vs indices) and the
library's logging and progress (package logger, -v/-q/--log-level, fit(verbose=...))."""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.errors import SchemaError
from offline_adp.policies import FunctionPolicy, PolicySignature, attach_signature

INFO = DatasetInfo(features=(Feature("p", "m"), Feature("s", "m/s"), Feature("k", "1/m")),
                   action_table=ActionTable.from_values([[-1.0, 0.5], [0.0, 0.0], [1.0, -0.5]], dims=("u", "w")))


def _rule(obs, t=0):
    """Independent reference: action 2 if p > s, 1 if p == s, else 0; k is ignored except its sign flips."""
    p, s, k = obs[:, 0], obs[:, 1], obs[:, 2]
    a = np.where(p > s, 2, np.where(p == s, 1, 0))
    return np.where(k < 0, 2 - a, a)


@pytest.fixture
def pi():
    return attach_signature(FunctionPolicy(_rule, 3), INFO)


def test_dataframe_columns_are_matched_by_name(pi):
    rng = np.random.default_rng(0)
    X = rng.normal(size=(200, 3))
    df = pd.DataFrame(X, columns=["p", "s", "k"])
    expected = INFO.action_table.values[_rule(X)]
    np.testing.assert_array_equal(pi.act(df), expected)
    np.testing.assert_array_equal(pi.act(df[["k", "s", "p"]]), expected)  # reversed: same actions
    np.testing.assert_array_equal(pi.act(df, return_index=True), _rule(X))
    np.testing.assert_array_equal(pi.act(X), expected)
    cols = {"s": X[:, 1], "k": X[:, 2], "p": X[:, 0]}
    np.testing.assert_array_equal(pi.act(cols), expected)


def test_single_observations(pi):
    one = {"p": 2.0, "s": 1.0, "k": 1.0}
    np.testing.assert_array_equal(pi.act(one), [1.0, -0.5])
    assert pi.act(one, return_index=True) == 2
    assert pi.act(np.array([0.0, 1.0, 1.0]), return_index=True) == 0
    np.testing.assert_array_equal(pi.act(pd.Series({"k": -1.0, "s": 1.0, "p": 2.0})), [-1.0, 0.5])


def test_one_dimensional_action_tables_give_flat_values():
    info = INFO.replace(action_table=ActionTable.from_values([-4.0, 4.0], dims=("u",)))
    p2 = attach_signature(FunctionPolicy(lambda x, t: (x[:, 0] > 0).astype(int), 2), info)
    np.testing.assert_array_equal(p2.act(np.array([[1.0, 0, 0], [-1.0, 0, 0]])), [4.0, -4.0])
    assert p2.act({"p": 1.0, "s": 0.0, "k": 0.0}) == 4.0


@pytest.mark.parametrize("obs,match", [
    (pd.DataFrame({"p": [1.0], "s": [0.0]}), r"missing \['k'\]"),
    (pd.DataFrame({"p": [1.0], "s": [0.0], "k": [1.0], "v": [0.0]}), r"unexpected \['v'\]"),
    ({"p": 1.0, "s": 0.0, "kappa": 1.0}, r"missing \['k'\], unexpected \['kappa'\]"),
    (np.zeros((4, 2)), r"2 columns, the policy expects 3: \['p', 's', 'k'\]"),
    (np.zeros(4), r"4 columns, the policy expects 3"),
    (np.zeros((2, 2, 3)), "shape"),
    ({"p": [1.0, 2.0], "s": [0.0], "k": [1.0, 1.0]}, "one length"),
    ([["a", "b", "c"]], "numbers"),
])
def test_misuse_is_an_error_naming_what_is_wrong(pi, obs, match):
    with pytest.raises(SchemaError, match=match):
        pi.act(obs)


def test_policy_without_signature_refuses_names_and_returns_indices():
    bare = FunctionPolicy(_rule, 3)
    with pytest.raises(SchemaError, match="no feature names"):
        bare.act(pd.DataFrame(np.zeros((2, 3)), columns=["p", "s", "k"]))
    np.testing.assert_array_equal(bare.act(np.array([[2.0, 1.0, 1.0]])), [2])


def test_signature_round_trips_through_json():
    sig = PolicySignature.from_info(INFO)
    assert PolicySignature.from_dict(sig.to_dict()) == sig
    with pytest.raises(SchemaError, match="malformed"):
        PolicySignature.from_dict({"feature_names": ["a"]})


def test_fitted_policies_carry_the_dataset_signature(small_pt):
    from offline_adp.algorithms.fqi import FittedQIteration

    f = FittedQIteration(regressor="extra_trees", regressor_params={"n_estimators": 3, "n_jobs": 1},
                         n_iterations=2).fit(small_pt)
    obs = small_pt.arrays().obs[:50]
    frame = pd.DataFrame(obs, columns=small_pt.feature_names)
    idx = f.policy_.act_index(obs)
    np.testing.assert_array_equal(f.policy_.act(frame[frame.columns[::-1]]), small_pt.info.action_table.values[idx, 0])


# ----------------------------------------------------------------------------- logging and progress
def test_fit_verbose_logs_one_record_per_iteration(small_pt, caplog):
    from offline_adp.algorithms.fqi import FittedQIteration

    with caplog.at_level(logging.INFO, logger="offline_adp"):
        FittedQIteration(regressor="extra_trees", regressor_params={"n_estimators": 2, "n_jobs": 1},
                         n_iterations=3).fit(
            small_pt, verbose=True)
    recs = [r for r in caplog.records if r.name == "offline_adp.algorithms.fqi"]
    assert [r.getMessage().split()[1] for r in recs] == ["1/3", "2/3", "3/3"]
    assert all("sup_dq=" in r.getMessage() for r in recs)


def test_fit_verbose_prints_without_logging_configured_and_progress_bar(small_pt, capsys, monkeypatch):
    from offline_adp.algorithms.fqi import FittedQIteration

    monkeypatch.setattr(logging.getLogger(), "handlers", [])  # as in a fresh notebook (pytest adds its own)
    monkeypatch.setattr(logging.getLogger("offline_adp"), "level", logging.NOTSET)  # earlier CLI calls set it

    est = FittedQIteration(regressor="extra_trees", regressor_params={"n_estimators": 2, "n_jobs": 1}, n_iterations=2)
    est.fit(small_pt)
    assert capsys.readouterr().err == ""  # silent by default
    est.fit(small_pt, verbose=True, show_progress=True)
    err = capsys.readouterr().err
    assert "FittedQIteration 2/2" in err
    assert "it" in err and "%" in err  # the tqdm bar
    assert logging.getLogger("offline_adp").level == logging.NOTSET  # restored


@pytest.mark.parametrize("argv,level", [
    (["-v", "inspect", "D"], logging.INFO),
    (["inspect", "D", "-v"], logging.INFO),
    (["inspect", "-vv", "D"], logging.DEBUG),
    (["-q", "inspect", "D"], logging.ERROR),
    (["inspect", "D", "--log-level", "debug"], logging.DEBUG),
    (["--log-level", "error", "inspect", "D", "-v"], logging.ERROR),
    (["ingest", "mcap", "x.mcap", "--spec", "s", "--out", "o", "-v"], logging.INFO),
    (["fit", "D", "--out", "o", "-q"], logging.ERROR),
    (["-q", "fit", "D", "--out", "o"], logging.ERROR),
])
def test_global_logging_options_before_or_after_the_subcommand(argv, level):
    from offline_adp.cli import build_parser
    from offline_adp.progress import apply_logging_options

    args = build_parser().parse_args([a.replace("D", "data") for a in argv])
    try:
        assert apply_logging_options(args) == level
        assert logging.getLogger("offline_adp").level == level
        assert args.quiet == ("-q" in argv)
    finally:
        from offline_adp.progress import configure_logging

        configure_logging(logging.WARNING)
        logging.getLogger("offline_adp").setLevel(logging.NOTSET)


def test_bad_log_level_is_a_usage_error(capsys):
    from offline_adp.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["inspect", "data", "--log-level", "loud"])
    assert exc.value.code == 2
    assert "--log-level" in capsys.readouterr().err


@settings(max_examples=60)
@given(perm=st.permutations(["p", "s", "k"]), n=st.integers(1, 30), seed=st.integers(0, 2**16))
def test_any_column_order_gives_the_same_actions(perm, n, seed):
    """Property: a DataFrame or dict in any column order gives the actions of the rule on
    the canonically ordered array."""
    pi = attach_signature(FunctionPolicy(_rule, 3), INFO)
    X = np.random.default_rng(seed).integers(-2, 3, size=(n, 3)).astype(float)  # small ints: many p == s ties
    df = pd.DataFrame(X, columns=["p", "s", "k"])[list(perm)]
    np.testing.assert_array_equal(pi.act(df, return_index=True), _rule(X))
    np.testing.assert_array_equal(pi.act({c: df[c].to_numpy() for c in perm}, return_index=True), _rule(X))
