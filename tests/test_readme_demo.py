"""The README's "What the demo produced" block is what `make demo` prints.

`make demo` runs ``offline-adp run pipelines/driving.toml --runs demo_out/runs``. This test
runs the same pipeline (same file, same seed, same data) and compares its output with
the README's block line by line. Tolerance: 0 for every number the pipeline computes
(the fit and every estimate are deterministic for a seed, on any x86-64 CPU; see
docs/fqi-modes.md, "What is reproducible"); masked are only what depends on the machine
or the clock: the stage times and the run directory's timestamp. When the code changes a
number on purpose, regenerate the block with `make demo` and paste it into the README.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from offline_adp.cli import main

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.slow, pytest.mark.integration]


def readme_block() -> list[str]:
    text = (ROOT / "README.md").read_text()
    section = text.split("## What the demo produced", 1)[1]
    block = section.split("```", 2)[1]
    return block.strip("\n").splitlines()


def normalise(lines: list[str]) -> list[str]:
    out = []
    for line in lines:
        line = re.sub(r"completed +[0-9.]+ s$", "completed <t> s", line)
        line = re.sub(r"^\S*driving__0__[0-9T]+/", "demo_out/runs/driving__0__<timestamp>/", line)
        out.append(line.rstrip())
    return out


def test_readme_block_has_the_demo_headlines():
    block = readme_block()
    for head in ("estimand:", "simulator:", "off-policy", "verdict:"):
        assert any(line.startswith(head) for line in block), head
    assert block[-1].endswith("report.html")


def test_the_demo_prints_the_readme_block(tmp_path, capfd, monkeypatch):
    """Also what `make demo > log 2>&1` holds (issue #34): fewer than 60 lines, no progress
    bar off a terminal, a line per stage, and library warnings (here 300 extra ones, as
    scikit-learn gives on every predict of a model fitted on a DataFrame) summarised once."""
    from offline_adp.evaluation import offpolicy
    from tests.test_cli_output import NOISE, _lines, _noisy, _summary

    _noisy(monkeypatch, offpolicy, "estimate_behaviour")  # warnings only: the results are the same
    argv = ["run", str(ROOT / "pipelines" / "driving.toml"), "--runs", str(tmp_path / "runs")]
    assert main(argv) == 0
    cap = capfd.readouterr()
    printed = cap.out.strip("\n").splitlines()
    assert normalise(printed) == normalise(readme_block())
    lines = _lines(cap)
    assert len(lines) < 60, "\n".join(lines)
    assert "\r" not in cap.err and "it/s" not in cap.err
    assert any(ln.startswith("[fit]") for ln in lines) and any(ln.startswith("[evaluate]") for ln in lines)
    summary = _summary(cap.err)
    assert len(summary) == 1 and NOISE in summary[0], cap.err
    assert int(summary[0].split("warning: ", 1)[1].split()[0]) >= 300
    assert NOISE not in cap.err.replace(summary[0], "")  # not printed one by one
    # -q: only errors on stderr (the results on stdout stay)
    assert main([*argv, "--from", "report", "-q"]) == 0
    cap = capfd.readouterr()
    assert cap.err == "" and cap.out.strip()
