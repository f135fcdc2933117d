"""Output a CI log can hold: no progress bars off a terminal, a few lines per stage, library
warnings summarised once at the end, -q / --log-level honoured by every command."""

from __future__ import annotations

import functools
import warnings
from pathlib import Path

import pytest

from offline_adp.cli import main

ROOT = Path(__file__).resolve().parents[1]
NOISE = "X does not have valid feature names, but ExtraTreesRegressor was fitted with feature names"


def _noisy(monkeypatch, module, name, n=300):
    """Make ``module.name`` raise ``n`` UserWarnings from outside the package first (as
    scikit-learn does on every predict of a model fitted on a DataFrame)."""
    original = getattr(module, name)

    @functools.wraps(original)
    def wrapper(*args, **kwargs):
        for _ in range(n):
            warnings.warn(NOISE, UserWarning, stacklevel=1)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, wrapper)


def _lines(cap) -> list[str]:
    return [ln for ln in (cap.out + cap.err).splitlines() if ln.strip()]


def _summary(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if "library warnings" in ln]


# `run` of the demo pipeline in a log (< 60 lines, warnings summarised, -q): tests/test_readme_demo.py


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory, small_pt):
    root = tmp_path_factory.mktemp("out")
    small_pt.save(root / "ds")
    for k in (2, 5):
        (root / f"fqi{k}.toml").write_text(f'[fqi]\nmode = "frozen"\nn_iterations = {k}\n'
                                           "[fqi.regressor_params]\nn_estimators = 5\nn_jobs = 1\n")
        assert main(["fit", str(root / "ds"), "--config", str(root / f"fqi{k}.toml"), "--out", str(root / f"fqi{k}"),
                     "-q"]) == 0
    return root


@pytest.mark.integration
def test_compare_with_a_simulator_in_a_log_is_short(two_runs, capfd, monkeypatch):
    from offline_adp.evaluation import offpolicy, run

    monkeypatch.setattr(run, "evaluate_run", functools.partial(run.evaluate_run, n_boot=20, n_boot_fqe=4))  # small
    _noisy(monkeypatch, offpolicy, "estimate_behaviour")
    capfd.readouterr()
    runs = [str(two_runs / "fqi2"), str(two_runs / "fqi5")]
    assert main(["compare", *runs, "--simulator", "path_tracking", "--episodes", "20", "--force"]) == 0
    cap = capfd.readouterr()
    lines = _lines(cap)
    assert len(lines) < 60, "\n".join(lines)
    assert "Spearman" in cap.out and "evaluating" in cap.err
    summary = _summary(cap.err)
    assert len(summary) == 1 and int(summary[0].split("warning: ", 1)[1].split()[0]) >= 600  # both evaluations'
    assert main(["compare", *runs, "--simulator", "path_tracking", "--episodes", "20", "-q"]) == 0
    assert capfd.readouterr().err == ""


def test_fit_log_levels(two_runs, capfd):
    cfg, ds = str(two_runs / "fqi2.toml"), str(two_runs / "ds")
    capfd.readouterr()
    assert main(["fit", ds, "--config", cfg, "--out", str(two_runs / "f-debug"), "--log-level", "DEBUG"]) == 0
    err = capfd.readouterr().err
    assert "debug: fit fqi iteration 1: sup|dQ|" in err and "debug: fit fqi iteration 2:" in err
    assert main(["fit", ds, "--config", cfg, "--out", str(two_runs / "f-default")]) == 0
    cap = capfd.readouterr()
    assert "debug:" not in cap.err and "fit fqi: iteration 2/2" in cap.err and "verdict: " in cap.out
    assert main(["fit", ds, "--config", cfg, "--out", str(two_runs / "f-quiet"), "-q"]) == 0
    cap = capfd.readouterr()
    assert cap.err == "" and "verdict: " in cap.out
    assert main(["fit", ds, "--config", cfg, "--out", str(two_runs / "f-warn"), "--log-level", "WARNING"]) == 0
    assert "fit fqi: iteration" not in capfd.readouterr().err


def test_a_failing_command_still_reports_its_warnings_and_the_error(tmp_path, capfd, monkeypatch):
    import offline_adp.cli as cli

    def boom(args):
        warnings.warn("a library complaint", RuntimeWarning, stacklevel=1)
        from offline_adp.errors import OfflineADPError

        raise OfflineADPError("no such thing")

    parser = cli.build_parser
    monkeypatch.setattr(cli, "build_parser", lambda: _with_func(parser(), boom))
    assert main(["inspect", str(tmp_path)]) == 2
    err = capfd.readouterr().err
    assert "error: no such thing" in err and "1 library warning (1 distinct; first: RuntimeWarning" in err
    assert main(["inspect", str(tmp_path), "-q"]) == 2
    err = capfd.readouterr().err
    assert "error: no such thing" in err and "library warning" not in err


def _with_func(parser, func):
    for a in parser._subparsers._group_actions[0].choices.values():
        if a.prog.endswith(" inspect"):
            a.set_defaults(func=func)
    return parser


def test_inspect_summarises_continuous_commands_and_long_action_tables(tmp_path, capsys):
    """A continuous log's line says its commands are exact and gives each component's logged
    range and bounds (not its coarse bins one by one: 17,000 characters for 256 bins);
    a long discrete table lists its first entries and says how many more --json holds."""
    import numpy as np

    from offline_adp.data.summary import LISTED_ACTIONS
    from offline_adp.simulate import simulate

    ds = simulate("path_tracking", 6, 6, seed=2, horizon=20, problem_options={"commands": "steer_accel"})
    ds.save(tmp_path / "sa")
    assert main(["inspect", str(tmp_path / "sa")]) == 0
    out = capsys.readouterr().out
    act = next(ln for ln in out.splitlines() if ln.lstrip().startswith("actions"))
    cmds = ds.commands()
    assert f"exact as logged ({len(np.unique(cmds, axis=0))} distinct commands)" in act
    assert f"delta_cmd logged [{cmds[:, 0].min():.4g}, {cmds[:, 0].max():.4g}]" in act and len(act) < 300
    assert "coarse bins for counts and behaviour models" in out
    from offline_adp.data.summary import _action_lines

    n = LISTED_ACTIONS + 6
    acts = {"kind": "discrete", "dims": ["a"], "table": {f"a{i}": [float(i)] for i in range(n)},
            "coverage": {f"a{i}": 1 for i in range(n)}, "out_of_range": 0}
    lines = _action_lines(acts)
    assert all(ln.endswith("... (6 more: inspect --json lists them)") for ln in lines)
    assert f"{LISTED_ACTIONS - 1}:a{LISTED_ACTIONS - 1}" in lines[0] and f"a{LISTED_ACTIONS}" not in lines[0]
