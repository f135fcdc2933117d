"""SIGTERM (what ``timeout``, systemd, ``docker stop`` and Slurm send) is handled as Ctrl-C:
a crash audit found a fit killed that way exited 143 in silence with run.json still
"running" and its checkpoint behind the one SIGINT writes at the same moment."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from offline_adp.simulate import simulate


@pytest.mark.skipif(os.name != "posix", reason="POSIX signals")
def test_a_fit_stopped_by_sigterm_says_so_and_records_it(tmp_path):
    simulate("gridworld", 5, 20, seed=0, horizon=40).save(tmp_path / "data")
    (tmp_path / "fit.toml").write_text('[fqi]\nmode = "refit"\nn_iterations = 5000\nregressor_params = '
                                       '{n_estimators = 5}\n')
    proc = subprocess.Popen([sys.executable, "-m", "offline_adp", "fit", str(tmp_path / "data"), "--config",
                             str(tmp_path / "fit.toml"), "--out", str(tmp_path / "run")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ck = tmp_path / "run" / "checkpoint" / "q.json"
    deadline = time.monotonic() + 120
    while not ck.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert proc.poll() is None, "the fit ended before it could be stopped"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143 and "terminated" in err and "Traceback" not in err
    status = json.loads((tmp_path / "run" / "run.json").read_text())
    assert status["status"] == "interrupted"
    assert not [p for p in (tmp_path / "run").iterdir() if p.name.startswith(".")]  # no temporary left
