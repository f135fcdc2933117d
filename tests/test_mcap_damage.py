"""Damage accounting by epoch and episode, not raw time: a lost chunk in a log whose time
restarts every episode costs exactly the episodes whose messages it held; a file cut
mid-step keeps every complete episode under both ``on_error`` modes and reports the cut
one; a cut that lost no message says so. Ground truth comes from the intact file: which
messages (and so which episodes) each chunk held."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from offline_adp.data.io import read_quarantine
from offline_adp.errors import IngestError
from offline_adp.ingest.mcap import ingest_mcap, mcap_info
from tests.test_mcap_epochs import rl_log, rl_spec, write_log


def _records(data: bytes):
    """(offset, opcode, length) of every top-level record after the magic."""
    out, off = [], 8
    while off + 9 <= len(data):
        op, n = struct.unpack_from("<BQ", data, off)
        out.append((off, op, n))
        off += 9 + n
    return out


def _chunk_episodes(data: bytes) -> list[tuple[int, int, set[int]]]:
    """Per chunk record: (offset, length, episodes of its messages)."""
    from io import BytesIO

    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk

    out = []
    for off, op, n in _records(data):
        if op == 0x06:  # chunk
            chunk = Chunk.read(ReadDataStream(BytesIO(data[off + 9:off + 9 + n])))
            eps = {json.loads(r.data)["ep"] for r in breakup_chunk(chunk) if isinstance(r, Message)}
            out.append((off, n, eps))
    return out


def _episode_of(ds) -> np.ndarray:
    return np.floor(ds.arrays().obs[:, 0] / 1000).astype(int)  # x = 1000 * episode + step


@pytest.mark.parametrize("which", ["inside an episode", "across a restart"])
def test_a_lost_chunk_costs_exactly_the_episodes_it_held(tmp_path, which):
    src = write_log(tmp_path / "rl.mcap", rl_log(n_episodes=8, k_absent=0, n_steps=300))
    data = bytearray(src.read_bytes())
    chunks = _chunk_episodes(bytes(data))
    pick = [c for c in chunks if len(c[2]) == (1 if which == "inside an episode" else 2)]
    off, n, held = pick[len(pick) // 2]
    data[off + 9 + n - 40] ^= 0xFF  # one flipped byte in the chunk's compressed data
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(IngestError, match="lost 1 corrupt chunk"):
        ingest_mcap([bad], rl_spec(2.0))
    with pytest.warns(UserWarning, match="recovered"):
        ds, s = ingest_mcap([bad], rl_spec(2.0), tmp_path / "q", on_error="quarantine")
    kept = sorted(set(_episode_of(ds)))
    assert kept == sorted(set(range(8)) - held)  # every other episode survives, whole
    assert len(ds) == 299 * len(kept)
    assert s["episodes_lost_to_damage"] == len(held)
    q = read_quarantine(tmp_path / "q")  # the damaged episodes' rows: in quarantine, with the reason
    assert len(ds) + (q.num_rows if q is not None else 0) == s["transitions_assembled"]
    a = ds.arrays()
    np.testing.assert_array_equal(ds.info.action_table.values[a.action, 0], _episode_of(ds) % 4)
    info = mcap_info(bad)  # mcap-info describes the file and shows the damage
    assert "lost 1 corrupt chunk" in info["damage"] and info["topics"]["/state"]["messages"] > 0


@pytest.mark.parametrize("on_error", ["fail", "quarantine"])
def test_a_file_cut_mid_step_keeps_every_complete_episode(tmp_path, on_error):
    """The recording stops between a state and its reward (a crash): every episode before
    the cut is kept whole in both modes; the cut one is reported (left out under fail, in
    quarantine/ under quarantine)."""
    msgs = rl_log(n_episodes=5, k_absent=0, n_steps=300)
    cut_at = next(i for i, m in enumerate(msgs) if m[2].get("ep") == 4 and m[0] == "/reward" and m[1] > 6_000_000_000)
    src = write_log(tmp_path / "rl.mcap", msgs[:cut_at])  # ends right after a state: its reward never came
    data = src.read_bytes()
    end = max(off + 9 + n for off, op, n in _records(data) if op == 0x06)
    (tmp_path / "cut.mcap").write_bytes(data[:end + 5])  # and the file stops inside the next record header
    with pytest.warns(UserWarning, match=r"cut at offset \d+ .*no message lost"):
        ds, s = ingest_mcap([tmp_path / "cut.mcap"], rl_spec(2.0), tmp_path / "out", on_error=on_error)
    assert sorted(set(_episode_of(ds))) == [0, 1, 2, 3] and len(ds) == 4 * 299
    assert s["cut_episodes"] == 1
    q = read_quarantine(tmp_path / "out")
    if on_error == "quarantine":
        assert q is not None and set(q.column("reason").to_pylist()) == {"cut: the recording ends inside this episode"}
        assert len(ds) + q.num_rows == s["transitions_assembled"]
    else:
        assert q is None and s["dropped_rows"] == s["transitions_assembled"] - len(ds) > 0


@pytest.mark.parametrize("on_error", ["fail", "quarantine"])
def test_the_cut_episode_is_the_one_left_out_whatever_order_the_ids_sort_in(tmp_path, on_error):
    """A cut recording listed before an intact one whose episode ids sort first: the rows of the
    cut episode were located in file order but removed after the sort by episode id, so a
    complete episode lost rows and the cut one stayed (a helper's bug hunt)."""
    from pathlib import Path

    from offline_adp.cli import main
    from offline_adp.ingest.mcap.spec import load_mcap_spec

    spec = load_mcap_spec(Path(__file__).resolve().parents[1] / "data" / "specs" / "path_tracking_mcap.toml")
    assert main(["simulate", "path_tracking", "--format", "mcap-ros2", "--demonstrations", "3", "--exploration", "4",
                 "--seed", "2", "--out", str(tmp_path / "mc"), "-q"]) == 0
    expl, demo = tmp_path / "mc" / "exploration.mcap", tmp_path / "mc" / "demonstration.mcap"
    data = expl.read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[:int(len(data) * 0.7)])
    full, _ = ingest_mcap([expl, demo], spec)
    with pytest.warns(UserWarning, match="recovered"):
        ds, s = ingest_mcap([tmp_path / "cut.mcap", demo], spec, tmp_path / "out", on_error=on_error)
    assert s["cut_episodes"] == 1
    rows = lambda d: dict(zip(*np.unique(np.asarray(d.table.column("episode_id").to_pylist()),  # noqa: E731
                                        return_counts=True), strict=True))
    whole, kept = rows(full), rows(ds)
    assert kept and all(kept[e] == whole[e] for e in kept)  # every kept episode whole
    assert sum(whole[e] for e in kept) == len(ds) and len(kept) == len(whole) - 1  # only the cut one left out
    q = read_quarantine(tmp_path / "out")
    if on_error == "quarantine":
        assert set(q.column("episode_id").to_pylist()) == set(whole) - set(kept)


def test_a_clock_that_steps_back_less_than_a_restart_is_said(tmp_path):
    """The clock's time falls back 0.35 s (under restart = 1 s) in file order: the steps are
    ordered by time and a transition can pair steps the robot did not take in that order. It was
    silent (every counter 0); it is now counted and warned about."""
    msgs = rl_log(n_episodes=2, k_absent=0, n_steps=300)  # each episode 1.5 s: its restart is one
    f = write_log(tmp_path / "ok.mcap", msgs)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a monotonic clock: no such warning
        _, s = ingest_mcap([f], rl_spec(0.01))
    assert s["clock_steps_back"] == 0
    states = [i for i, m in enumerate(msgs) if m[0] == "/state"]
    i, j = states[100], states[300]  # in the first episode, from its step 100 on
    jumped = [(tp, t - 350_000_000 if i <= k < j else t, d) for k, (tp, t, d) in enumerate(msgs)]
    f = write_log(tmp_path / "jump.mcap", jumped)
    with pytest.warns(UserWarning, match=r"clock messages are earlier than one .* \[episodes\] restart = 1.0"):
        _, s = ingest_mcap([f], rl_spec(0.01))
    assert s["clock_steps_back"] >= 1


def test_a_second_mcap_ingest_into_the_same_directory_fails_at_once(tmp_path):
    """The MCAP ingest took the dataset's lock only while writing: two `ingest mcap --overwrite`
    into one --out both succeeded, the last writer silently winning. It holds it from the start now."""
    import subprocess
    import sys

    from offline_adp.errors import LockedError

    f = write_log(tmp_path / "rl.mcap", rl_log(n_episodes=2, k_absent=0, n_steps=300))
    out = tmp_path / "ds"
    hold = ("import sys, time\nfrom offline_adp.data.files import locked_directory\n"
            "with locked_directory(sys.argv[1], what='dataset'):\n    print('held', flush=True)\n    time.sleep(60)\n")
    holder = subprocess.Popen([sys.executable, "-c", hold, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(LockedError, match="another process is writing"):
            ingest_mcap([f], rl_spec(0.01), out, overwrite=True)
        # refused before reading anything (not after the whole ingest): a missing input is not even opened
        with pytest.raises(LockedError, match="another process is writing"):
            ingest_mcap([tmp_path / "missing.mcap"], rl_spec(0.01), out, overwrite=True)
        assert not out.exists()
    finally:
        holder.kill()
        holder.wait()
    ds, _ = ingest_mcap([f], rl_spec(0.01), out)  # the lock released with its holder
    assert len(ds) > 0 and out.exists()


def test_an_action_topic_missing_from_the_file_is_named_as_such(tmp_path):
    from offline_adp.ingest.mcap.spec import parse_mcap_spec

    f = write_log(tmp_path / "rl.mcap", rl_log(n_episodes=2, k_absent=0, n_steps=300))
    spec = parse_mcap_spec({
        "clock": {"topic": "/state", "reorder_window": 0.01}, "episodes": {"restart": 1.0, "gap": 1.0},
        "streams": [{"topic": "/state", "fields": {"x": "x"}, "max_age": 0.001},
                    {"topic": "/reward", "role": "reward", "fields": {"r": "r"}, "max_age": 0.002}],
        "action": {"topic": "/steer", "field": "u", "max_age": 0.01, "type": "discrete", "values": [0.0, 1.0]},
        "cost": {"reward": "r"}})
    with pytest.raises(IngestError, match=r"topic '/steer' of the spec is not in the file .*'/cmd'"):
        ingest_mcap([f], spec)


def test_steps_given_a_fill_value_are_counted_and_said(tmp_path):
    """A stream whose every step got its fill value (its time field never met the clock's) was
    silent: doctor OK, no count. Filled steps are counted per topic and warned about."""
    from offline_adp.ingest.mcap.spec import parse_mcap_spec

    msgs = rl_log(n_episodes=2, k_absent=0, n_steps=300)
    msgs += [("/imu", t + 10**12, {"w": 1.0}) for tp, t, _ in msgs if tp == "/state"]  # far from the clock
    f = write_log(tmp_path / "rl.mcap", msgs)
    spec = parse_mcap_spec({
        "clock": {"topic": "/state", "reorder_window": 0.01}, "episodes": {"restart": 1.0, "gap": 1.0},
        "streams": [{"topic": "/state", "fields": {"x": "x"}, "max_age": 0.001},
                    {"topic": "/imu", "fields": {"w": "w"}, "max_age": 0.001, "missing": "fill", "fill": 0.0},
                    {"topic": "/reward", "role": "reward", "fields": {"r": "r"}, "max_age": 0.002}],
        "action": {"topic": "/cmd", "field": "u", "align": "previous", "max_age": 0.01, "type": "discrete",
                   "values": [0.0, 1.0, 2.0, 3.0]},
        "cost": {"reward": "r"}})
    with pytest.warns(UserWarning, match=r"fill value .* \{'/imu': 600\}"):
        ds, s = ingest_mcap([f], spec)
    assert s["filled_steps"] == {"/imu": 600} and len(ds) == 2 * 299


def test_a_null_field_is_a_missing_value_of_one_episode_not_of_the_file(tmp_path):
    """One JSON null in one message discarded the whole file with an error naming nothing; it is a
    missing value now: the doctor names its row, quarantine sets only that episode aside."""
    msgs = rl_log(n_episodes=3, k_absent=0, n_steps=300)
    i = next(k for k, m in enumerate(msgs) if m[0] == "/reward" and m[2]["ep"] == 1)
    msgs[i] = (msgs[i][0], msgs[i][1], {**msgs[i][2], "r": None})
    f = write_log(tmp_path / "rl.mcap", msgs)
    from offline_adp.errors import ValidationError

    with pytest.raises(ValidationError, match=r"rl.mcap: log_time \d+ .*\[non_finite\]"):
        ingest_mcap([f], rl_spec(0.01))
    ds, s = ingest_mcap([f], rl_spec(0.01), tmp_path / "q", on_error="quarantine")
    assert sorted(set(_episode_of(ds))) == [0, 2] and read_quarantine(tmp_path / "q").num_rows == 299
