"""MCAP epochs: which epoch a message belongs to when its stream appears late, restarts
before or after the clock, or skips epochs. Regression for the cross-episode pairing of
issue 13: the result never depends on buffer flush points or ``reorder_window``.

Every value encodes its own episode, so the right pairing is known by construction."""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp.ingest.mcap import ingest_mcap, parse_mcap_spec
from tests.test_ingest_mcap_streaming import write_log

MS = 1_000_000
T0 = 5_000 * MS


def rl_log(n_episodes=8, k_absent=3, n_steps=300):
    """An RL recording like the one of issue 13: log_time restarts at T0 every episode; a
    200 Hz state (the clock), a 200 Hz command and a reward. The command topic is absent in
    the first ``k_absent`` episodes and its restart record (2 ms before the state's) comes
    before the clock's in the file. Every field carries its episode number."""
    msgs = []
    for ep in range(n_episodes):
        for j in range(n_steps):
            t = T0 + j * 5 * MS
            if ep >= k_absent:
                msgs.append(("/cmd", t - 2 * MS, {"u": float(ep % 4), "ep": ep}))
            msgs.append(("/state", t, {"x": 1000.0 * ep + j, "ep": ep}))
            msgs.append(("/reward", t + 1 * MS, {"r": -float(ep), "ep": ep}))
    return msgs


def rl_spec(reorder_window):
    return parse_mcap_spec({
        "clock": {"topic": "/state", "reorder_window": reorder_window},
        "episodes": {"restart": 1.0, "gap": 1.0},
        "streams": [{"topic": "/state", "fields": {"x": "x"}, "max_age": 0.001},
                    {"topic": "/state", "role": "aux", "fields": {"state_ep": "ep"}, "max_age": 0.001},
                    {"topic": "/cmd", "role": "aux", "fields": {"cmd_ep": "ep"}, "align": "previous",
                     "max_age": 0.01, "missing": "drop_step"},
                    {"topic": "/reward", "role": "reward", "fields": {"r": "r"}, "max_age": 0.002},
                    {"topic": "/reward", "role": "aux", "fields": {"rew_ep": "ep"}, "max_age": 0.002}],
        "action": {"topic": "/cmd", "field": "u", "align": "previous", "max_age": 0.01, "missing": "drop_step",
                   "type": "discrete", "values": [0.0, 1.0, 2.0, 3.0]},
        "cost": {"reward": "r"},
    })


@pytest.mark.parametrize("reorder_window", [0.01, 0.2, 2.0, 30.0])
def test_a_late_starting_command_stream_is_never_paired_across_episodes(tmp_path, reorder_window):
    n_ep, k = 8, 3
    f = write_log(tmp_path / "rl.mcap", rl_log(n_ep, k))
    ds, s = ingest_mcap([f], rl_spec(reorder_window))
    a = ds.arrays()
    x_ep = np.floor(a.obs[:, 0] / 1000).astype(int)
    act = ds.info.action_table.values[a.action, 0]
    np.testing.assert_array_equal(act, x_ep % 4)  # the command of the state's own episode
    np.testing.assert_array_equal(a.cost, x_ep.astype(float))  # reward -ep, negated
    assert ds.n_episodes == n_ep - k and len(ds) == (n_ep - k) * 299
    # the first k episodes have no command: their steps are dropped, counted
    assert s["dropped_steps"] == k * 300 and s["restarts"] == n_ep - 1
    assert not s["late_messages"]


def test_a_stale_first_stamp_is_not_taken_for_a_restart(tmp_path):
    """Like amcl in a real nav2 bag: the first pose is stamped seconds before the clock's
    first message (and logged after it). It belongs to the current epoch (older than
    anything the clock covered), not to a next one: the steps use it."""
    msgs = []
    for k in range(90):  # odometry (the clock) at 30 Hz from 10 s
        t = 10_000 * MS + k * 33 * MS
        msgs.append(("/odom", t, {"x": float(k)}))
        if k == 5:
            msgs.append(("/pose", 6_000 * MS, {"p": -1.0}))  # stamped 4 s before the first odometry
        if k % 18 == 17:
            msgs.append(("/pose", t - 10 * MS, {"p": float(k)}))
    f = write_log(tmp_path / "nav.mcap", msgs)
    sp = parse_mcap_spec({
        "clock": {"topic": "/odom"},
        "streams": [{"topic": "/odom", "fields": {"x": "x"}, "max_age": 0.001},
                    {"topic": "/pose", "fields": {"p": "p"}, "align": "previous", "max_age": 5.0}],
        "action": {"topic": "/odom", "field": "x", "max_age": 0.001, "type": "continuous", "n_bins": 2},
        "cost": {"terms": [{"field": "x", "op": "abs"}]},
    })
    ds, s = ingest_mcap([f], sp)
    a = ds.arrays()
    k = a.obs[:, 0].astype(int)
    expected = np.where(k < 17, -1.0, (k + 1) // 18 * 18 - 1.0)  # the last pose at or before each step
    np.testing.assert_array_equal(a.obs[:, 1], expected)
    assert s["restarts"] == 0 and s["orphan_messages"] == 0 and len(ds) == 89


def test_per_file_epochs_keep_the_parts_of_a_split_recording_apart(tmp_path):
    """[episodes] per_file = true: every part file is an epoch of its own, even when its
    times overlap the previous part's by less than `restart` (no time jump to see)."""
    for part in range(2):
        msgs = []
        for j in range(20):  # both parts cover the same 1 s of log_time
            t = T0 + j * 50 * MS
            msgs.append(("/cmd", t - 2 * MS, {"u": float(part), "ep": part}))
            msgs.append(("/state", t, {"x": 1000.0 * part + j, "ep": part}))
            msgs.append(("/reward", t + MS, {"r": -float(part), "ep": part}))
        write_log(tmp_path / f"rec_{part}.mcap", msgs)
    d = rl_spec(2.0).raw
    sp = parse_mcap_spec({**d, "episodes": {"restart": 5.0, "gap": 1.0, "per_file": True}})
    ds, s = ingest_mcap([tmp_path / "rec_0.mcap", tmp_path / "rec_1.mcap"], sp)
    a = ds.arrays()
    x_ep = np.floor(a.obs[:, 0] / 1000).astype(int)
    assert ds.n_episodes == 2 and len(ds) == 2 * 19
    np.testing.assert_array_equal(ds.info.action_table.values[a.action, 0], x_ep)
    np.testing.assert_array_equal(a.cost, x_ep.astype(float))
    np.testing.assert_array_equal(a.obs[:, 0] % 1000, np.r_[np.arange(19), np.arange(19)])


def test_a_sparse_stream_that_began_before_the_clock_is_seen_to_restart():
    """Found by the nightly run (seed 7): a 3 Hz stream's one message of an episode came
    before the clock's first one; in the next episode its first message lay above that one
    in time (no jump back), so only its pace with the clock tells the restart (rule 3), and
    that pace had no start: the message stayed in the old episode, counted late. The pace
    now counts from the clock's first message. Ground truth: the logs below, and the plain
    reference implementation."""
    from offline_adp.ingest.mcap.build import assemble
    from offline_adp.ingest.mcap.records import Message
    from tests import mcap_reference as ref

    def m(topic, t_ms, v, k):
        return Message(topic, t_ms * MS, t_ms * MS, {"v": float(v), "k": k})

    msgs = [m("/s0", 958, 100, 0)]
    for t in range(1030, 1500, 100):  # episode 0: the clock at 10 Hz from 1.03 s, commands between its ticks
        msgs += [m("/clock", t, 0, 0), m("/cmd", t + 40, 1, 0)]
    msgs += [m("/cmd", 957, 2, 1), m("/s0", 989, 200, 1)]  # episode 1: the stream's first message, above 0.958 s
    for t in range(996, 1900, 100):
        msgs += [m("/clock", t, 0, 1), m("/cmd", t + 60, 3, 1)]
        if t in (1296, 1696):
            msgs.append(m("/s0", t + 12, 300, 1))
    spec = parse_mcap_spec({
        "clock": {"topic": "/clock", "reorder_window": 0.01}, "episodes": {"restart": 0.25, "gap": 0.45},
        "streams": [{"topic": "/s0", "fields": {"x": "v", "k": "k"}, "align": "previous", "max_age": 1.0,
                     "missing": "fill", "fill": -7.0}],
        "action": {"topic": "/cmd", "field": "v", "align": "nearest", "max_age": 0.15, "missing": "drop_step",
                   "type": "continuous", "n_bins": 2},
        "cost": {"terms": [{"field": "x", "op": "square"}]},
    })
    got = assemble([msgs], spec, flush_every=1)
    want = ref.assemble(msgs, spec, name="memory")
    assert sum(got.late.values()) == want.late == 0
    second = next(e for e in got.episodes if e.epoch == 1)
    assert set(second.obs[:, 1].tolist()) == {1.0}  # every value of the second episode from its own messages
    assert second.obs[0, 0] == 200.0
