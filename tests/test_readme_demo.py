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


def test_the_demo_prints_the_readme_block(tmp_path, capsys):
    assert main(["run", str(ROOT / "pipelines" / "driving.toml"), "--runs", str(tmp_path / "runs")]) == 0
    printed = capsys.readouterr().out.strip("\n").splitlines()
    assert normalise(printed) == normalise(readme_block())
