"""Two writers into one run directory: exactly one succeeds, the other exits 2 with a clear
message, and the survivor's output is intact (issue: no locking)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from offline_adp.algorithms.fqi import load_fqi
from offline_adp.data.rundir import RunDirectory
from offline_adp.errors import OfflineADPError

pytestmark = pytest.mark.integration


def _cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "offline_adp", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.time() + timeout
    while not path.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    assert path.exists(), f"{path} never appeared (first writer exited {proc.poll()})"


@pytest.fixture(scope="module")
def ds_dir(tmp_path_factory):
    from offline_adp.simulate import simulate

    d = tmp_path_factory.mktemp("ds") / "ds"
    simulate("path_tracking", 10, 10, seed=1, horizon=60).save(d)
    return d


def _cfg(tmp_path: Path, n: int) -> Path:
    p = tmp_path / f"fqi{n}.toml"
    p.write_text(f"[fqi]\nn_iterations = {n}\nmode = \"refit\"\n[fqi.regressor_params]\nn_estimators = "
                 "20\nn_jobs = 1\n")
    return p


def test_two_fits_into_one_out(tmp_path, ds_dir):
    out = tmp_path / "run"
    first = _cli("fit", str(ds_dir), "--config", str(_cfg(tmp_path, 40)), "--out", str(out), "-q")
    _wait_for(out / "config.json", first)
    second = _cli("fit", str(ds_dir), "--config", str(_cfg(tmp_path, 2)), "--out", str(out), "-q")
    _, err2 = second.communicate(timeout=300)
    _, err1 = first.communicate(timeout=600)
    assert (first.returncode, second.returncode) == (0, 2), (err1, err2)
    assert "another process is writing this run directory" in err2 or "already holds a run" in err2
    assert len(err2.strip().splitlines()) == 1, "one line, no traceback"
    config = json.loads((out / "config.json").read_text())
    assert config["params"]["n_iterations"] == 40
    assert len(load_fqi(out / "model").history_) == 40  # the model is the survivor's, as its config says


def test_two_pipeline_runs_into_one_directory(tmp_path):
    p = tmp_path / "p.toml"
    p.write_text('name = "p"\n[data]\nsimulate = "path_tracking"\ndemonstrations = 10\nexploration = 10\nhorizon = 60\n'
                 "[fit]\n[fit.params]\nn_iterations = 40\nmode = "
                 "\"refit\"\n[fit.params.regressor_params]\nn_estimators = 20\nn_jobs = 1\n")
    out = tmp_path / "r"
    first = _cli("run", str(p), "--out", str(out), "-q")
    _wait_for(out / "manifest.json", first)
    second = _cli("run", str(p), "--out", str(out), "-q")
    _, err2 = second.communicate(timeout=300)
    _, err1 = first.communicate(timeout=600)
    assert (first.returncode, second.returncode) == (0, 2), (err1, err2)
    assert "another process is writing this run directory" in err2
    man = json.loads((out / "manifest.json").read_text())
    assert all(s["status"] == "completed" for s in man["stages"].values())


def test_lock_is_exclusive_and_writes_do_not_follow_links(tmp_path):
    rd = RunDirectory(tmp_path / "run")
    outside = tmp_path / "outside.txt"
    outside.write_text("precious")
    probe = ("import sys\nfrom offline_adp.data.rundir import RunDirectory\nfrom offline_adp.errors import "
             "LockedError\n"
             "try:\n    RunDirectory(sys.argv[1]).lock().__enter__()\nexcept LockedError as e:\n    print(e); "
             "sys.exit(2)\n")
    with rd.lock():
        other = subprocess.run([sys.executable, "-c", probe, str(rd.path)], capture_output=True, text=True)
        assert other.returncode == 2 and "another process is writing this run directory" in other.stdout
        (rd.path / "config.json").symlink_to(outside)
        (rd.path / ".model.tmp-abc").mkdir()  # a killed writer's leftovers
        rd.write_json("config.json", {"a": 1})
    assert outside.read_text() == "precious"
    assert not (rd.path / "config.json").is_symlink()
    with rd.lock():  # the next writer cleans our stale temporaries
        assert not (rd.path / ".model.tmp-abc").exists()


def test_pipeline_writes_replace_planted_links(tmp_path):
    from offline_adp.pipeline import run_pipeline

    p = tmp_path / "p.toml"
    p.write_text('name = "p"\n[data]\nsimulate = "tabular"\ndemonstrations = 20\nexploration = 20\n'
                 "[fit]\n[fit.params]\nn_iterations = 3\n[fit.params.regressor_params]\nn_estimators = 5\nn_jobs = 1\n"
                 '[evaluate]\nsimulator = "tabular"\nepisodes = 20\nbootstrap = 20\nfqe_bootstrap = 2\n[report]\n')
    out = tmp_path / "r"
    out.mkdir()
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "manifest.json").write_text("{}")
    (out / "manifest.json").symlink_to(outside / "manifest.json")
    with pytest.raises(OfflineADPError, match="manifest.json is a symbolic link"):
        run_pipeline(p, out=out, say=lambda s: None)
    out = tmp_path / "r2"
    out.mkdir()
    for name in ("config.json", "manifest.json", "metrics.json", "report.html", "validation.json"):
        (outside / name).write_text("precious")
        if name != "manifest.json":
            (out / name).symlink_to(outside / name)
    (out / "figures").symlink_to(outside, target_is_directory=True)
    run_pipeline(p, out=out, say=lambda s: None)
    for name in ("config.json", "manifest.json", "metrics.json", "report.html", "validation.json"):
        assert (outside / name).read_text() == "precious", name
        assert not (out / name).is_symlink() and (out / name).stat().st_size > 0
    assert not (out / "figures").is_symlink() and sorted(outside.iterdir()) == sorted(outside / n for n in (
        "config.json", "manifest.json", "metrics.json", "report.html", "validation.json"))
