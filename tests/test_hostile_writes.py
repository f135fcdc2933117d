"""Writes that fail, concurrent writers, hostile inputs: every write command ends in one
clear line naming the path and exit 2, leaves nothing half-written and no temporaries or
lock files behind (read-only location, full disk, a file where a folder is expected)."""

from __future__ import annotations

import builtins
import errno
import io
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from offline_adp.cli import main
from offline_adp.data.files import atomic_file, atomic_write_text, lock_path, locked_directory
from offline_adp.errors import LockedError, OfflineADPError, WriteError

ROOT = Path(__file__).resolve().parents[1]
FQI = "[fqi]\nn_iterations = 2\n[fqi.regressor_params]\nn_estimators = 3\nn_jobs = 1\n"
PIPELINE = ('name = "p"\n[data]\nsimulate = "gridworld"\ndemonstrations = 2\nexploration = 2\nhorizon = 10\n'
            "[fit]\n[fit.params]\nn_iterations = 2\n[fit.params.regressor_params]\nn_estimators = 3\nn_jobs = 1\n"
            "[evaluate]\nepisodes = 5\nbootstrap = 5\nfqe_bootstrap = 2\n")
EVAL = ["--episodes", "5", "--bootstrap", "5", "--fqe-bootstrap", "2", "-q"]


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _one_error_line(err: str) -> str:
    assert "Traceback" not in err, err
    lines = [x for x in err.strip().splitlines() if x.strip()]
    assert len(lines) == 1 and "error:" in lines[0], err
    return lines[0]


def _leftovers(*roots: Path) -> list[Path]:
    """Temporaries and lock files of ours under ``roots``."""
    found = []
    for r in roots:
        if r.exists():
            found += [p for p in r.rglob("*") if ".tmp" in p.name or p.name.endswith(".lock") or ".old-" in p.name]
    return found


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A dataset, its raw CSV + spec, a fit config, a pipeline file and two fitted, evaluated runs."""
    d = tmp_path_factory.mktemp("inputs")
    from offline_adp.simulate import simulate
    from offline_adp.simulate.raw import write_raw

    ds = simulate("gridworld", 3, 3, seed=1, horizon=12)
    ds.save(d / "ds")
    raw, spec = write_raw(ds, d / "raw" / "g.csv", fmt="csv")
    (d / "fqi.toml").write_text(FQI)
    (d / "p.toml").write_text(PIPELINE)
    for name in ("run", "run_b"):
        assert main(["fit", str(d / "ds"), "--config", str(d / "fqi.toml"), "--out", str(d / name), "-q"]) == 0
        assert main(["evaluate", str(d / name), *EVAL]) == 0
    return {"dir": d, "ds": d / "ds", "raw": raw, "spec": spec, "cfg": d / "fqi.toml", "pipeline": d / "p.toml",
            "run": d / "run", "run_b": d / "run_b"}


# ------------------------------------------------------------------ failing locations
def _inject(monkeypatch, kind: str, root: Path) -> None:
    """Make writes under ``root`` fail: ``erofs`` (a read-only location: creating, opening
    for writing and renaming fail) or ``enospc`` (a full disk: the final rename of every
    atomic write fails, as a write of the last block would)."""
    root_s = str(root)

    def under(p) -> bool:
        try:
            return os.path.abspath(os.fspath(p)).startswith(root_s)
        except TypeError:
            return False

    real_replace, real_mkdir, real_open, real_os_open = os.replace, os.mkdir, builtins.open, os.open

    def replace(src, dst, *a, **k):
        if under(dst):
            code = errno.ENOSPC if kind == "enospc" else errno.EROFS
            raise OSError(code, os.strerror(code), os.fspath(src), None, os.fspath(dst))
        return real_replace(src, dst, *a, **k)

    monkeypatch.setattr(os, "replace", replace)
    if kind != "erofs":
        return

    def mkdir(p, *a, **k):
        if under(p):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fspath(p))
        return real_mkdir(p, *a, **k)

    def os_open(p, flags, *a, **k):
        if under(p) and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fspath(p))
        return real_os_open(p, flags, *a, **k)

    def bopen(p, mode="r", *a, **k):
        if isinstance(p, str | os.PathLike) and under(p) and any(c in mode for c in "wax+"):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fspath(p))
        return real_open(p, mode, *a, **k)

    monkeypatch.setattr(os, "mkdir", mkdir)
    monkeypatch.setattr(os, "open", os_open)
    monkeypatch.setattr(builtins, "open", bopen)
    monkeypatch.setattr(io, "open", bopen)


#: command -> argv for an output path OUT (a new file or folder)
COMMANDS = {
    "simulate": lambda i, out: ["simulate", "gridworld", "--demonstrations", "1", "--exploration", "1", "--horizon",
                                "8", "--out", out, "-q"],
    "simulate-parquet": lambda i, out: ["simulate", "gridworld", "--demonstrations", "1", "--exploration", "1",
                                        "--horizon", "8", "--format", "parquet", "--out", f"{out}.parquet", "-q"],
    "simulate-mcap": lambda i, out: ["simulate", "gridworld", "--demonstrations", "1", "--exploration", "1",
                                     "--horizon", "8", "--format", "mcap-json", "--out", out, "-q"],
    "ingest": lambda i, out: ["ingest", "parquet", i["raw"], "--spec", i["spec"], "--out", out, "-q"],
    "fit": lambda i, out: ["fit", i["ds"], "--config", i["cfg"], "--out", out, "-q"],
    "run": lambda i, out: ["run", i["pipeline"], "--out", out, "-q"],
    "compare": lambda i, out: ["compare", i["run"], i["run_b"], "--json", f"{out}.json", "-q"],
    "export": lambda i, out: ["export", i["run"], "--out", f"{out}.onnx"],
    "convert-d4rl": lambda i, out: ["convert", i["ds"], "--to", "d4rl", "--out", f"{out}.npz"],
    "convert-lerobot": lambda i, out: ["convert", i["ds"], "--to", "lerobot", "--out", out],
    "schema": lambda i, out: ["schema", "--write", out],
}
#: file outputs checked before any work (not in COMMANDS: annotating needs an MCAP-fitted run)
FILE_ONLY = {"annotate": lambda i, out: ["annotate", i["run"], "--log", i["dir"] / "log.mcap", "--out", f"{out}.mcap"]}


@pytest.mark.parametrize("kind", ["erofs", "enospc", "notadir"])
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_write_command_into_a_failing_location_is_one_line_exit_2_and_leaves_nothing(
        tmp_path, capsys, monkeypatch, inputs, command, kind):
    if kind == "notadir":  # a real one: a regular file where a folder of the path is expected
        blocker = tmp_path / "blocker"
        blocker.write_text("a file, not a folder")
        root, out = blocker, blocker / "sub" / "out"
    else:
        root = tmp_path / "location"
        root.mkdir()
        out = root / "out"
        _inject(monkeypatch, kind, root)
    before = sorted(p.name for p in inputs["dir"].rglob("*"))
    code, _, err = _run(capsys, *COMMANDS[command](inputs, str(out)))
    monkeypatch.undo()
    line = _one_error_line(err)
    assert code == 2
    assert str(root) in line, line  # names the path at fault
    if kind == "notadir":
        assert blocker.read_text() == "a file, not a folder"
    else:
        assert [p for p in root.rglob("*") if not p.is_dir()] == [], list(root.rglob("*"))  # no file, whole or half
    assert _leftovers(tmp_path) == []
    assert sorted(p.name for p in inputs["dir"].rglob("*")) == before  # inputs untouched, no temporaries there


@pytest.mark.parametrize("kind", ["erofs", "enospc"])
@pytest.mark.parametrize("command", ["evaluate", "report"])
def test_evaluate_and_report_into_a_failing_run_directory(tmp_path, capsys, monkeypatch, inputs, command, kind):
    run = tmp_path / "run"
    shutil.copytree(inputs["run"], run)
    metrics = (run / "evaluation" / "metrics.json").read_bytes()
    snapshot = sorted(str(p.relative_to(run)) for p in run.rglob("*"))
    _inject(monkeypatch, kind, run)
    argv = ["evaluate", run, *EVAL] if command == "evaluate" else ["report", run]
    code, _, err = _run(capsys, *argv)
    monkeypatch.undo()
    line = _one_error_line(err)
    assert code == 2 and str(run) in line
    assert (run / "evaluation" / "metrics.json").read_bytes() == metrics  # the previous results, whole
    assert sorted(str(p.relative_to(run)) for p in run.rglob("*")) == snapshot
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize("command", ["export", "convert-d4rl", "compare", "simulate-parquet", "annotate"])
def test_file_output_naming_an_existing_directory(tmp_path, capsys, inputs, command):
    out = tmp_path / "adir"
    argv = {**COMMANDS, **FILE_ONLY}[command](inputs, str(out))
    target = Path(argv[argv.index("--out" if "--out" in argv else "--json") + 1])
    target.mkdir()
    (target / "keep.txt").write_text("keep")
    code, _, err = _run(capsys, *argv)
    line = _one_error_line(err)
    assert code == 2 and str(target) in line and "directory" in line
    assert (target / "keep.txt").read_text() == "keep" and sorted(p.name for p in target.iterdir()) == ["keep.txt"]
    assert _leftovers(tmp_path) == []


def test_raw_os_errors_elsewhere_are_one_line_naming_the_path(capsys, monkeypatch, inputs):
    """The CLI's last line of defence: any OSError (here from a writer we do not own) is
    one line naming the path, exit 2."""
    import offline_adp.formats as formats

    def boom(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", "/somewhere/full.npz")

    monkeypatch.setattr(formats, "convert", boom)
    code, _, err = _run(capsys, "convert", inputs["ds"], "--to", "d4rl", "--out", "/somewhere/full.npz")
    line = _one_error_line(err)
    assert code == 2 and "/somewhere/full.npz" in line and "no space left" in line


def test_temporaries_of_writers_that_do_not_clean_up_are_removed(tmp_path, capsys, monkeypatch, inputs):
    """``convert --to d4rl`` and ``export`` write ``.NAME.tmp*`` then rename: a failed
    rename used to leave the temporary (both now write through ``atomic_file``)."""
    real = os.replace

    def failing(src, dst, *a, **k):
        if str(dst).startswith(str(tmp_path)):
            raise OSError(errno.ENOSPC, "No space left on device", str(src), None, str(dst))
        return real(src, dst, *a, **k)

    monkeypatch.setattr(os, "replace", failing)
    for argv in (["convert", inputs["ds"], "--to", "d4rl", "--out", tmp_path / "d.npz"],
                 ["export", inputs["run"], "--out", tmp_path / "p.onnx"]):
        code, _, err = _run(capsys, *argv)
        assert code == 2 and "no space left" in _one_error_line(err)
    monkeypatch.undo()
    assert sorted(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ the write helpers
def test_atomic_file_removes_its_temporary_and_keeps_the_previous_file(tmp_path):
    target = tmp_path / "x.json"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_file(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("disk full half-way")
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["x.json"]
    atomic_write_text(target, "new")
    assert target.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["x.json"]
    (tmp_path / "d").mkdir()
    with pytest.raises(WriteError, match="is a directory"):
        atomic_write_text(tmp_path / "d", "x")


def test_run_directory_write_failure_leaves_the_previous_file_and_no_temporary(tmp_path, monkeypatch):
    from offline_adp.data.rundir import RunDirectory

    rd = RunDirectory(tmp_path / "run")
    with rd.lock():
        rd.write_json("run.json", {"v": 1})

        def full(src, dst, *a, **k):
            raise OSError(errno.ENOSPC, "No space left on device", str(src), None, str(dst))

        monkeypatch.setattr(os, "replace", full)
        with pytest.raises(OSError):
            rd.write_json("run.json", {"v": 2})
        with pytest.raises(OSError):
            rd.copy_in(tmp_path / "run" / "run.json", "copy.json")
        monkeypatch.undo()
    assert json.loads((tmp_path / "run" / "run.json").read_text()) == {"v": 1}
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["run.json"]


# ------------------------------------------------------------------ locks
def _cli(*args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "offline_adp", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


@pytest.mark.parametrize("command", ["evaluate", "report"])
def test_evaluate_and_report_take_the_run_lock(tmp_path, inputs, command):
    run = tmp_path / "run"
    shutil.copytree(inputs["run"], run)
    metrics = (run / "evaluation" / "metrics.json").read_bytes()
    argv = ["evaluate", run, *EVAL] if command == "evaluate" else ["report", run]
    with locked_directory(run, what="run directory"):  # stands for a first evaluation still running
        p = _cli(*argv)
        _, err = p.communicate(timeout=300)
    assert p.returncode == 2, err
    assert "another process is writing this run directory" in err and str(run) in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert (run / "evaluation" / "metrics.json").read_bytes() == metrics
    assert not (run / "report").exists()


@pytest.mark.integration
def test_two_concurrent_evaluations_one_wins(tmp_path, inputs):
    run = tmp_path / "run"
    shutil.copytree(inputs["run"], run)
    shutil.rmtree(run / "evaluation")
    procs = [_cli("evaluate", run, "--episodes", "5", "--bootstrap", "5", "--fqe-bootstrap", "2", "--seed", str(s),
                  "-q")
             for s in (1, 2)]
    results = [p.communicate(timeout=600) for p in procs]
    codes = sorted(p.returncode for p in procs)
    if codes == [0, 0]:  # the first finished before the second started: then they ran one after the other
        pytest.skip("the evaluations did not overlap on this machine")
    assert codes == [0, 2], results
    winner = next(s for s, p in zip((1, 2), procs, strict=True) if p.returncode == 0)
    loser_err = next(err for p, (_, err) in zip(procs, results, strict=True) if p.returncode == 2)
    assert "another process is writing this run directory" in loser_err and "Traceback" not in loser_err
    assert json.loads((run / "evaluation" / "metrics.json").read_text())["seed"] == winner
    assert _leftovers(tmp_path) == []


def test_lock_files_are_removed_after_release_and_a_removed_file_is_not_shared(tmp_path):
    target = tmp_path / "x"
    lp = lock_path(target)
    with locked_directory(target):
        assert lp.exists()
        code = ("import sys\nfrom offline_adp.data.files import locked_directory\nfrom offline_adp.errors import "
                "LockedError\n"
                f"try:\n    with locked_directory({str(target)!r}):\n        print('GOT')\nexcept LockedError:\n    "
                "print('LOCKED')\n")
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                           env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert r.stdout.strip() == "LOCKED"
    assert not lp.exists()  # removed on release
    # a taker that locked a lock file its holder removed (the filelock caveat) retries on the new one
    import fcntl

    fd = os.open(lp, os.O_RDWR | os.O_CREAT)
    os.unlink(lp)  # an old, removed lock file someone still holds
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        with locked_directory(target):  # not blocked by the removed file's lock: a new file is locked
            assert lp.exists()
            r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                               env={**os.environ, "PYTHONPATH": str(ROOT)})
            assert r.stdout.strip() == "LOCKED"
    finally:
        os.close(fd)
    assert not lp.exists()


def test_a_held_lock_is_a_locked_error_naming_the_target(tmp_path):
    code = ("import sys, time\nfrom offline_adp.data.files import locked_directory\n"
            f"with locked_directory({str(tmp_path / 'd')!r}):\n    print('HELD', flush=True)\n    time.sleep(30)\n")
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert p.stdout.readline().strip() == "HELD"
        with pytest.raises(LockedError, match=str(tmp_path / "d")), locked_directory(tmp_path / "d"):
            pass
    finally:
        p.kill()
        p.wait()


def test_stale_report_temporaries_are_removed_by_the_next_writer(tmp_path, capsys, inputs):
    run = tmp_path / "run"
    shutil.copytree(inputs["run"], run)
    (run / ".report.tmp-deadbeef" / "figures").mkdir(parents=True)  # a killed report's leftovers
    code, _, err = _run(capsys, "report", run)
    assert code == 0, err
    assert (run / "report" / "report.html").is_file()
    assert _leftovers(tmp_path) == []


# ------------------------------------------------------------------ former raw tracebacks
def test_header_only_csv(tmp_path, capsys, inputs):
    header = Path(inputs["raw"]).read_text().splitlines()[0]
    (tmp_path / "h.csv").write_text(header + "\n")
    code, _, err = _run(capsys, "ingest", "parquet", tmp_path / "h.csv", "--spec", inputs["spec"], "--out",
                        tmp_path / "out", "-q")
    line = _one_error_line(err)
    assert code == 2 and "h.csv: no rows" in line
    assert not (tmp_path / "out").exists() and _leftovers(tmp_path) == []


def test_compare_runs_with_different_action_tables(tmp_path, capsys, inputs):
    from offline_adp.simulate import simulate

    simulate("tabular", 2, 2, seed=1, horizon=8).save(tmp_path / "tab")
    assert main(["fit", str(tmp_path / "tab"), "--config", str(inputs["cfg"]), "--out", str(tmp_path / "trun"),
                 "-q"]) == 0
    capsys.readouterr()
    code, _, err = _run(capsys, "compare", inputs["run"], tmp_path / "trun", "--dataset", inputs["ds"], "--episodes",
                        "5",
                        "-q")
    line = _one_error_line(err)
    assert code == 2 and "trun" in line and "actions" in line
    assert not (tmp_path / "trun" / "evaluation").exists()


@pytest.mark.parametrize("setting, match", [
    ("evaluate.episodes=1e23", "evaluate.episodes"),
    ("evaluate.episodes=1e13", "evaluate.episodes: Input should be less than or equal to"),
    ("evaluate.bootstrap=1e12", "evaluate.bootstrap"),
    ('engine.address="file:///tmp/x"', "unknown address scheme 'file'"),
])
def test_pipeline_settings_that_used_to_crash(tmp_path, capsys, inputs, setting, match):
    code, _, err = _run(capsys, "run", inputs["pipeline"], "--out", tmp_path / "r", "--set", setting, "-q")
    assert code == 2 and match in _one_error_line(err)
    assert not (tmp_path / "r").exists()


def test_engine_address_in_the_pipeline_file(tmp_path, capsys, inputs):
    p = tmp_path / "p.toml"
    p.write_text(PIPELINE + '[engine]\nkind = "dask"\naddress = "file:///tmp/sock"\n')
    code, _, err = _run(capsys, "run", p, "--out", tmp_path / "r", "-q")
    line = _one_error_line(err)
    assert code == 2 and "engine.address" in line and str(p) in line
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("where", ["spec", "fit.config", "pipeline"])
@pytest.mark.parametrize("bad", ["/dev/zero", "fifo", "huge", "directory"])
def test_config_files_are_regular_and_bounded(tmp_path, capsys, inputs, where, bad):
    if bad == "fifo":
        path = tmp_path / "fifo.toml"
        os.mkfifo(path)  # reading it would block for ever
    elif bad == "huge":
        path = tmp_path / "huge.toml"
        with open(path, "wb") as f:
            f.truncate(64 << 20)  # sparse: 64 MiB of zeros
    elif bad == "directory":
        path = tmp_path / "adir.toml"
        path.mkdir()
    else:
        path = Path(bad)
    if where == "pipeline":
        argv = ["run", path, "--out", tmp_path / "r", "-q"]
    else:
        raw = inputs["raw"]
        key = f'spec = "{path}"' if where == "spec" else f'config = "{path}"'
        body = (f'name = "p"\n[data]\nformat = "parquet"\ninputs = ["{raw}"]\n' + (key + "\n" if where == "spec" else
                f'spec = "{inputs["spec"]}"\n') + "[fit]\n" + (key + "\n" if where == "fit.config" else ""))
        (tmp_path / "p.toml").write_text(body)
        argv = ["run", tmp_path / "p.toml", "--out", tmp_path / "r", "-q"]
    code, _, err = _run(capsys, *argv)
    line = _one_error_line(err)
    assert code == 2 and str(path) in line
    assert any(w in line for w in ("not a regular file", "bytes, more than", "is a directory")), line
    assert not (tmp_path / "r").exists()


def test_config_reader_helper_directly(tmp_path):
    from offline_adp.config import read_config_bytes
    from offline_adp.errors import SpecError

    (tmp_path / "ok.toml").write_text("a = 1\n")
    assert read_config_bytes(tmp_path / "ok.toml") == b"a = 1\n"
    (tmp_path / "big.toml").write_text("x" * 101)
    with pytest.raises(SpecError, match="101 bytes"):
        read_config_bytes(tmp_path / "big.toml", max_bytes=100)
    with pytest.raises(SpecError, match="not a regular file"):
        read_config_bytes("/dev/zero")


# ------------------------------------------------------------------ smaller items
def test_every_episode_quarantined_is_an_error_naming_the_quarantine(tmp_path, capsys, inputs):
    import pyarrow.compute as pc
    import pyarrow.csv as pacsv

    t = pacsv.read_csv(inputs["raw"])
    i = t.schema.get_field_index("cost")
    t = t.set_column(i, "cost", pc.multiply(t.column("cost"), float("nan")))  # every row's cost is NaN
    pacsv.write_csv(t, tmp_path / "bad.csv")
    out = tmp_path / "out"
    code, stdout, err = _run(capsys, "ingest", "parquet", tmp_path / "bad.csv", "--spec", inputs["spec"], "--out", out,
                             "--on-error", "quarantine", "-q")
    line = _one_error_line(err)
    assert code == 2 and "every episode was quarantined" in line and f"{out}/quarantine/" in line
    assert (out / "quarantine").is_dir()  # the reasons are kept for the user to read
    assert _leftovers(tmp_path) == []


def test_lock_files_are_gone_after_cli_writes(tmp_path, capsys, inputs):
    assert _run(capsys, "fit", inputs["ds"], "--config", inputs["cfg"], "--out", tmp_path / "run", "-q")[0] == 0
    assert _run(capsys, "evaluate", tmp_path / "run", *EVAL)[0] == 0
    assert _run(capsys, "report", tmp_path / "run")[0] == 0
    assert _leftovers(tmp_path) == []


def test_write_error_is_ours():
    assert issubclass(WriteError, OfflineADPError)


def test_simulate_mcap_after_a_killed_write_is_not_blocked_by_its_temporaries(tmp_path):
    """kill -9 during `simulate --format mcap-json` left `.demonstration.mcap.tmp` in the
    folder (6 of 24 kills), and the same command then failed "not empty; pass --overwrite"."""
    from offline_adp.cli import main

    out = tmp_path / "logs"
    out.mkdir()
    (out / ".demonstration.mcap.tmp").write_bytes(b"half a recording")
    assert main(["simulate", "gridworld", "--format", "mcap-json", "--out", str(out), "--demonstrations", "1",
                 "--exploration", "1", "-q"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["demonstration.mcap", "exploration.mcap"]
    (out / "notes.txt").write_text("mine")  # what is not ours still needs --overwrite
    assert main(["simulate", "gridworld", "--format", "mcap-json", "--out", str(out), "-q"]) == 2


def test_a_second_simulate_of_one_table_fails_at_once(tmp_path, capsys):
    """Two `simulate --format parquet --overwrite` runs on one --out both succeeded (each file's
    write was locked, not the command), so a table could be paired with the other's spec.
    Writer A is held between its table and its spec; writer B must fail at once now."""
    import subprocess
    import sys

    from offline_adp.cli import main

    out = tmp_path / "g.parquet"
    a = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\nimport offline_adp.data.files as f\nreal = f.atomic_write_text\n"
        "def slow(*a, **k):\n    print('between', flush=True)\n    time.sleep(30)\n    return real(*a, **k)\n"
        "f.atomic_write_text = slow\nfrom offline_adp.cli import main\n"
        f"sys.exit(main(['simulate', 'gridworld', '--format', 'parquet', '--out', {str(out)!r}, '-q']))")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert a.stdout.readline().strip() == "between"  # A wrote its table, not yet its spec
        assert main(["simulate", "gridworld", "--format", "parquet", "--out", str(out), "--overwrite",
                     "--seed", "1", "-q"]) == 2
        assert "lock" in capsys.readouterr().err.lower()
    finally:
        a.kill()
        a.wait()
