"""Field paths that select a list element by a field's value: ``transforms[child_frame_id=base_link]``.

A /tf message holds transforms of several frame pairs, one pair in one message, others in
the next; ``transforms[0]`` reads whichever pair comes first, so a stream on it mixes
frames. The oracle here is the same log with each frame pair on a topic of its own (read
with ``transforms[0]``): a selector on the mixed topic must give the very same dataset,
and the messages of no selected pair are counted (``messages_unselected``), not used.
"""

from __future__ import annotations

import warnings
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from offline_adp.errors import IngestError, SpecError
from offline_adp.ingest.mcap import ingest_mcap, parse_mcap_spec
from tests.test_ingest_mcap_streaming import write_log
from tests.test_mcap_message_counts import _partition_holds

MS = 1_000_000
PAIRS = (("odom", "base_link"), ("map", "odom"), ("base_link", "wheel"))


def _tf(parent, child, t, x):
    return {"header": {"frame_id": parent, "stamp": {"sec": t // 10**9, "nanosec": t % 10**9}},
            "child_frame_id": child, "transform": {"translation": {"x": x}}}


def _logs(seed: int, n: int = 240):
    """(mixed, split): the clock /odom at 25 Hz; per frame pair a series of transforms at its
    own rate and phase, each x = a pair's code + its time, logged on a 10 ms grid. ``mixed``
    puts them on /tf, the pairs logged at one time in one message (in a random order);
    ``split`` writes each pair's transforms on a topic of its own, with the same log times."""
    rng = np.random.default_rng(seed)
    t0 = 10_000 * MS
    mixed, split = [], []
    for k in range(n):
        t = t0 + k * 40 * MS
        mixed.append(("/odom", t, {"v": float(k % 7), "u": float(k % 3)}))
        split.append(("/odom", t, {"v": float(k % 7), "u": float(k % 3)}))
    for code, (parent, child) in enumerate(PAIRS):
        period = int(rng.choice([17, 33, 50, 100])) * MS
        phase = int(rng.integers(0, period))
        for t in range(t0 + phase, t0 + n * 40 * MS, period):
            x = 100.0 * code + (t - t0) / 1e9
            lt = (t + int(rng.integers(0, 5 * MS))) // (10 * MS) * (10 * MS) + 1  # on a 10 ms grid: pairs meet
            mixed.append(("/tf", lt, [_tf(parent, child, t, x)]))
            split.append((f"/tf_{child}", mixed[-1][1], [_tf(parent, child, t, x)]))
    # a log time shared by two pairs' transforms is one /tf message holding both (in a random order)
    mixed.sort(key=lambda m: (m[1], m[0]))
    merged = []
    for topic, t, m in mixed:
        if topic == "/tf" and merged and merged[-1][0] == "/tf" and merged[-1][1] == t:
            both = merged[-1][2] + m
            merged[-1] = ("/tf", t, both if rng.random() < 0.5 else both[::-1])
        else:
            merged.append((topic, t, m))
    split.sort(key=lambda m: (m[1], m[0]))
    wrap = {"/tf": lambda m: {"transforms": m}}
    return ([(tp, t, wrap.get(tp, lambda m: {"transforms": m} if isinstance(m, list) else m)(m))
             for tp, t, m in merged],
            [(tp, t, {"transforms": m} if isinstance(m, list) else m) for tp, t, m in split])


def _spec(selector: bool, second: bool = True, child: str = "base_link") -> dict:
    def stream(ch, name):
        topic, sel = ("/tf", f"transforms[child_frame_id={ch}]") if selector else (f"/tf_{ch}", "transforms[0]")
        return {"topic": topic, "time": f"{sel}.header.stamp", "align": "previous", "max_age": 0.2,
                "missing": "drop_step", "role": "obs", "fields": {name: f"{sel}.transform.translation.x"}}
    return {
        "clock": {"topic": "/odom"}, "episodes": {"gap": 1.0},
        "streams": [{"topic": "/odom", "max_age": 0.001, "fields": {"v": "v"}}, stream(child, "x_base"),
                    *([stream("odom", "x_map")] if second else [])],
        "action": {"topic": "/odom", "field": "u", "max_age": 0.001, "type": "discrete", "values": [0, 1, 2]},
        "cost": {"terms": [{"field": "v", "op": "abs"}]},
    }


def _ingest(tmp_path, name, msgs, spec):
    f = write_log(tmp_path / f"{name}.mcap", msgs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ingest_mcap([f], parse_mcap_spec(spec))


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), second=st.booleans())
def test_a_selector_on_a_mixed_topic_equals_each_pair_on_its_own_topic(tmp_path_factory, seed, second):
    tmp = tmp_path_factory.mktemp("sel")
    mixed, split = _logs(seed)
    ds_sel, s_sel = _ingest(tmp, "mixed", mixed, _spec(True, second))
    ds_ref, s_ref = _ingest(tmp, "split", split, _spec(False, second))
    a, b = ds_sel.arrays(), ds_ref.arrays()
    np.testing.assert_array_equal(a.obs, b.obs)
    np.testing.assert_array_equal(a.next_obs, b.next_obs)
    np.testing.assert_array_equal(a.action, b.action)
    np.testing.assert_array_equal(a.step, b.step)
    # each pair's values are its own (code 0 for base_link, 1 for odom), never another pair's
    assert np.all(a.obs[:, 1] < 100) and (not second or np.all((a.obs[:, 2] >= 100) & (a.obs[:, 2] < 200)))
    # what became of each /tf message: read = used + unselected, the wheel-only messages unselected
    tf = [m[2]["transforms"] for m in mixed if m[0] == "/tf"]
    wanted = {"base_link", "odom"} if second else {"base_link"}
    n_used = sum(any(x["child_frame_id"] in wanted for x in m) for m in tf)
    assert s_sel["messages_read"]["/tf"] == len(tf)
    assert s_sel["messages_used"]["/tf"] == n_used
    assert s_sel["messages_unselected"].get("/tf", 0) == len(tf) - n_used
    assert s_ref["messages_unselected"] == {}
    for s in (s_sel, s_sel["files"][0]):  # the counts partition the file's messages, per topic
        _partition_holds(s, Counter(m[0] for m in mixed))


@pytest.mark.parametrize("missing", ["drop_step", "error"])
def test_a_selector_that_never_matches_names_the_stream_and_the_values_seen(tmp_path, missing):
    """A typo in a selector: the error names the stream (at the end, or at the first step
    the stream must give a value to) and the values the list held."""
    mixed, _ = _logs(0, n=60)
    spec = _spec(True, second=False, child="base_lnk")
    spec["streams"][1]["missing"] = missing
    where = r"streams\[1\] \(/tf\)" if missing == "drop_step" else r"no /tf message .* found no element in"
    with pytest.raises(IngestError, match=where + r".*'base_link', 'odom', 'wheel'"):
        _ingest(tmp_path, "typo", mixed, spec)


def test_a_selector_matching_two_elements_is_an_error_naming_the_message(tmp_path):
    msgs = [("/odom", 10_000 * MS + k * 40 * MS, {"v": 1.0, "u": 0.0}) for k in range(30)]
    msgs.insert(3, ("/tf", 10_090 * MS, {"transforms": [_tf("odom", "base_link", 10_090 * MS, 1.0),
                                                          _tf("odom", "base_link", 10_091 * MS, 2.0)]}))
    with pytest.raises(IngestError, match=r"topic '/tf', message at log_time 10090000000.*2 elements"):
        _ingest(tmp_path, "two", msgs, _spec(True, second=False))


@pytest.mark.parametrize("path", ["transforms[child_frame_id=base_link", "transforms..x", "a[k=v]b", "a[]", ".a",
                                  "a.", "a[h..x=1]"])
def test_a_malformed_field_path_is_refused_before_any_file_is_read(path):
    spec = _spec(True, second=False)
    spec["streams"][1]["fields"]["x_base"] = path
    with pytest.raises(SpecError, match=r"spec\.streams\[1\]\.fields\.x_base: .* is no field path"):
        parse_mcap_spec(spec)


def test_mcap_info_says_where_the_first_element_changes_and_how_to_select(tmp_path, capsys):
    """`mcap-info` decodes only a topic's first message for its fields; /tf's first element
    is another frame pair in later messages. It counts the values of the lists' string fields
    (in how many messages each appears) and says when element [0] is not one thing, with the
    selector to use. Ground truth: the generator's messages. A topic whose [0] is the same
    in every message (the split log's) is not flagged."""
    from offline_adp.cli import main
    from offline_adp.ingest.mcap import mcap_info

    mixed, split = _logs(5, n=120)
    f = write_log(tmp_path / "mixed.mcap", mixed)
    g = write_log(tmp_path / "split.mcap", split)
    tf = [m[2]["transforms"] for m in mixed if m[0] == "/tf"]
    want = Counter(c for m in tf for c in {x["child_frame_id"] for x in m})
    got = mcap_info(f)["topics"]["/tf"]["list_values"]
    assert got == {"transforms[].child_frame_id": dict(want)}
    assert all(not t["list_values"] for t in mcap_info(g)["topics"].values())
    assert main(["mcap-info", str(f)]) == 0
    top = max(sorted(want), key=lambda c: want[c])
    out = capsys.readouterr().out
    assert "transforms[0] is another element from message to message" in out
    assert f"read one with transforms[child_frame_id={top}]" in out


def _proto_list():
    """A protobuf message with a repeated message field ``items`` (name, v, on)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    f = descriptor_pb2.FileDescriptorProto(name="sel_test.proto", package="sel_test")
    item = f.message_type.add(name="Item")
    item.field.add(name="name", number=1, type=9, label=1)
    item.field.add(name="v", number=2, type=1, label=1)
    item.field.add(name="on", number=3, type=8, label=1)
    lst = f.message_type.add(name="List")
    lst.field.add(name="items", number=1, type=11, label=3, type_name=".sel_test.Item")
    pool = descriptor_pool.DescriptorPool()
    pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("sel_test.List"))


def test_selectors_read_every_kind_of_decoded_list():
    """JSON dicts (elements without the key are not it), dotted keys, numbers and booleans,
    numpy scalars (rosbags), protobuf repeated fields (no __iter__ attribute under upb)."""
    from offline_adp.ingest.mcap.decode import NoElement, get_path

    js = {"l": [{"id": "a"}, {"v": 2}, {"id": "/b c.d", "v": 3, "h": {"f": "x"}}],
          "b": [{"f": True, "v": 1}, {"f": 1, "v": 2}]}
    assert get_path(js, "l[id=/b c.d].v") == 3 and get_path(js, 'l[id="/b c.d"].v') == 3
    assert get_path(js, "l[h.f=x].v") == 3
    assert get_path(js, "b[f=true].v") == 1 and get_path(js, "b[f=1].v") == 2  # a boolean is not the number 1

    class E:  # a rosbags-like object with numpy scalar fields
        def __init__(self, i):
            self.id, self.flag, self.v = np.uint8(i), np.bool_(i == 2), float(i)

    ros = {"l": [E(1), E(2)]}
    assert get_path(ros, "l[id=2].v") == 2.0 and get_path(ros, "l[flag=true].v") == 2.0
    msg = _proto_list()()
    msg.items.add(name="a", v=1.0)
    msg.items.add(name="b", v=2.0, on=True)
    assert get_path(msg, "items[name=b].v") == 2.0 and get_path(msg, "items[on=true].v") == 2.0
    with pytest.raises(NoElement) as no:
        get_path(msg, "items[name=zz].v")
    assert no.value.seen == ("a", "b")
    with pytest.raises(NoElement):
        get_path(_proto_list()(), "items[name=a].v")  # an empty list


def test_two_matches_in_a_time_field_name_the_message(tmp_path):
    msgs = [("/odom", 10_000 * MS + k * 40 * MS, {"v": 1.0, "u": 0.0}) for k in range(30)]
    msgs.insert(3, ("/tf", 10_090 * MS, {"transforms": [_tf("odom", "base_link", 10_090 * MS, 1.0),
                                                          _tf("odom", "base_link", 10_091 * MS, 1.0)]}))
    spec = _spec(True, second=False)
    spec["streams"][1]["fields"] = {"x_base": "transforms[0].transform.translation.x"}
    with pytest.raises(IngestError, match=r"topic '/tf', message at log_time 10090000000: its time field .*"
                                          r"2 elements"):
        _ingest(tmp_path, "two", msgs, spec)
