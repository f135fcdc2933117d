"""The README's tour runs as written.

Every fenced block preceded by a ``<!-- tour -->`` line in README.md is run in order, in
a fresh directory laid out like the repository's root after ``make demo``: ``.venv/bin``
(``offline-adp`` and ``python`` from the interpreter running the tests, with this
checkout's package first on the path) and ``data/specs`` (the repository's specs). A
``sh`` block runs in bash with ``-e`` (a failing command fails the block); a ``python``
block runs in the same interpreter. Each block must succeed and print on stdout exactly
the lines its ``#| `` comments show (when it has any: the fit is deterministic for a
seed), and the outputs the tour names must exist afterwards. So a renamed option, a
changed default, a changed number or a broken command breaks this test instead of the
README.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.slow, pytest.mark.integration]

BLOCK = re.compile(r"^<!-- tour -->\n```(sh|python)\n(.*?)^```\s*$", re.M | re.S)


def tour_blocks() -> list[tuple[str, str]]:
    """The (language, code) of every block marked ``<!-- tour -->``, in README order."""
    return BLOCK.findall((ROOT / "README.md").read_text())


def test_the_tour_is_marked():
    blocks = tour_blocks()
    marked = len(re.findall(r"^<!-- tour -->$", (ROOT / "README.md").read_text(), re.M))
    assert len(blocks) == marked, "a <!-- tour --> marker is not followed by a ```sh or ```python block"
    code = "\n".join(c for _, c in blocks)
    for command in ("simulate", "ingest parquet", "ingest mcap", "fit", "evaluate", "report", "export",
                    "annotate", "convert", "compare", "--log-level", "history.csv"):
        assert command in code, command
    assert any(lang == "python" and "onnxruntime" in c for lang, c in blocks)


def fake_checkout(tmp_path: Path) -> dict[str, str]:
    """``tmp_path`` laid out like the repository after ``make demo``; the environment."""
    bin_dir = tmp_path / ".venv" / "bin"
    bin_dir.mkdir(parents=True)
    for name, args in (("offline-adp", f'"{sys.executable}" -m offline_adp'), ("python", f'"{sys.executable}"')):
        script = bin_dir / name
        script.write_text(f'#!/bin/sh\nexec {args} "$@"\n')
        script.chmod(0o755)
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "specs").symlink_to(ROOT / "data" / "specs")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["MPLBACKEND"] = "Agg"
    env.pop("MINARI_DATASETS_PATH", None)
    return env


def test_the_tour_runs_as_written(tmp_path):
    env = fake_checkout(tmp_path)
    for i, (lang, code) in enumerate(tour_blocks()):
        cmd = ["bash", "-e", "-c", code] if lang == "sh" else [sys.executable, "-c", code]
        done = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, (
            f"tour block {i} ({lang}) failed:\n{code}\n--- stdout\n{done.stdout}\n--- stderr\n{done.stderr}"
        )
        expected = [line[3:] for line in code.splitlines() if line.startswith("#| ")]
        if expected:
            assert done.stdout.splitlines() == expected, f"tour block {i} printed other lines than its #| comments"
    for path in ("data/pt/meta/info.json", "data/pt-mcap/meta/info.json", "runs/pt-fqi/model/history.csv",
                 "runs/pt-fqi/evaluation/metrics.json", "runs/pt-fqi/report/report.html", "policy.onnx",
                 "annotated.mcap", "pt.npz", "data/pt-from-d4rl/meta/info.json",
                 "minari/offline_adp/pt-v0", "data/pt-from-minari/meta/info.json", "lerobot/pt/meta/info.json",
                 "runs/compare.html"):
        assert (tmp_path / path).exists(), path
