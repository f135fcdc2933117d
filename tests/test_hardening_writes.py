"""Issue 16, safe and concurrent writes of dataset directories: a lock per directory,
stale temporaries of ours cleaned up, normal permissions, no writes through symlinks."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from offline_adp.data.dataset import read_dataset
from offline_adp.data.files import locked_directory, write_text_nofollow
from offline_adp.data.validate import validate_directory
from offline_adp.errors import LockedError, OfflineADPError
from offline_adp.simulate import simulate
from offline_adp.simulate.raw import write_raw

ROOT = Path(__file__).resolve().parents[1]


def _cli(*args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "offline_adp", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


@pytest.fixture(scope="module")
def raw_log(tmp_path_factory):
    d = tmp_path_factory.mktemp("raw")
    ds = simulate("path_tracking", 60, 60, seed=3, horizon=200)
    raw, spec = write_raw(ds, d / "raw.parquet")
    return raw, spec, ds


def test_second_ingest_while_the_first_holds_the_lock_exits_2(tmp_path, raw_log):
    raw, spec, ds = raw_log
    out = tmp_path / "ds"
    with locked_directory(out, what="dataset"):  # stands for a first ingest still running
        p = _cli("ingest", "parquet", str(raw), "--spec", str(spec), "--out", str(out), "--overwrite")
        _, err = p.communicate(timeout=120)
    assert p.returncode == 2, err
    assert "another process is writing this dataset" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()


@pytest.mark.integration
def test_two_concurrent_ingests_one_wins_and_its_output_is_intact(tmp_path, raw_log):
    raw, spec, ds = raw_log
    out = tmp_path / "ds"
    # no --overwrite: whichever comes second fails, by the lock while the first runs or by
    # "already exists" after it finished; never both succeed (the later silently replacing)
    procs = [_cli("ingest", "parquet", str(raw), "--spec", str(spec), "--out", str(out)) for _ in range(2)]
    results = [p.communicate(timeout=300) for p in procs]
    codes = sorted(p.returncode for p in procs)
    assert codes == [0, 2], results
    loser_err = next(err for p, (_, err) in zip(procs, results, strict=True) if p.returncode == 2)
    assert ("another process is writing this dataset" in loser_err or "already exists" in loser_err), loser_err
    assert "Traceback" not in loser_err and len(loser_err.strip().splitlines()) == 1
    back = read_dataset(out)
    assert back.fingerprint() == ds.fingerprint()
    assert validate_directory(out).ok
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]  # no temporaries or lock file left


def test_lock_is_reentrant_in_one_process_and_exclusive_across_processes(tmp_path):
    target = tmp_path / "x"
    code = ("import sys\nfrom offline_adp.data.files import locked_directory\nfrom offline_adp.errors import "
            "LockedError\n"
            f"try:\n    with locked_directory({str(target)!r}):\n        print('GOT')\nexcept LockedError as e:\n    "
            "print('LOCKED', e)\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with locked_directory(target), locked_directory(target):  # re-entrant
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
        assert r.stdout.startswith("LOCKED") and str(target) in r.stdout
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert r.stdout.startswith("GOT")  # released with the outer block


def test_lock_error_type():
    assert issubclass(LockedError, OfflineADPError)


def test_stale_temporaries_of_killed_writes_are_removed(tmp_path, small_pt):
    (tmp_path / ".ds.tmp-deadbeef" / "data").mkdir(parents=True)
    (tmp_path / ".ds.tmp-deadbeef" / "data" / "part-00000.parquet").write_bytes(b"half")
    (tmp_path / ".ds.old-0badf00d").mkdir()
    (tmp_path / ".other.tmp-12345678").mkdir()  # not ours to remove: another target's
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep.txt").write_text("keep")
    (tmp_path / ".ds.tmp-linked00").symlink_to(outside)
    small_pt.save(tmp_path / "ds")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == [".other.tmp-12345678", "ds", "outside"]
    assert (outside / "keep.txt").read_text() == "keep"  # the link was removed, not followed


def test_directories_get_normal_permissions(tmp_path, small_pt):
    old = os.umask(0o022)
    try:
        small_pt.save(tmp_path / "ds")
    finally:
        os.umask(old)
    mode = (tmp_path / "ds").stat().st_mode & 0o777
    assert mode == 0o755, oct(mode)  # mkdtemp would give 0700: unreadable to teammates and Dask workers


def test_overwriting_a_symlinked_target_replaces_the_link_not_the_pointee(tmp_path, small_pt):
    outside = tmp_path / "outside"
    small_pt.save(outside)
    before = sorted(p.name for p in (outside / "data").iterdir())
    (tmp_path / "ds").symlink_to(outside)
    half = small_pt.select_episodes(small_pt.episode_ids[:2])
    half.save(tmp_path / "ds", overwrite=True)
    assert not (tmp_path / "ds").is_symlink() and len(read_dataset(tmp_path / "ds")) == len(half)
    assert (
        len(read_dataset(outside)) == len(small_pt) and sorted(p.name for p in (outside / "data").iterdir()) == before
    )


def test_metadata_writes_do_not_follow_symlinks(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    (tmp_path / "info.json").symlink_to(victim)
    with pytest.raises(OfflineADPError, match="symbolic link"):
        write_text_nofollow(tmp_path / "info.json", "{}")
    assert victim.read_text() == "precious"
    write_text_nofollow(tmp_path / "fresh.json", "{}")
    assert (tmp_path / "fresh.json").read_text() == "{}"
