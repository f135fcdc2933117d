"""ROS bags as untrusted input: a split SQLite bag is one recording however it is named
(glob, directory, one part), a bag's metadata.yaml cannot point outside the bag, list a
file twice or expand YAML aliases, mcap-info describes every input ingest reads, a ROS 1
bag cut short keeps its complete episodes, and a topic absent from a file is named as
such. Ground truth: the unsplit recording (or the uncut bag) ingested through rosbags'
own readers, and counts known by construction."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from offline_adp.errors import IngestError
from offline_adp.ingest.mcap import ingest_mcap

pytest.importorskip("rosbags")
yaml = pytest.importorskip("yaml")

sys.path.insert(0, str(Path(__file__).parent))
from test_mcap_rosbags import SPEC, _messages  # noqa: E402 - the bag tests' recording and spec

N = 40  # /state messages (and as many /cmd_vel): 39 transitions, one episode
FIELDS = ("obs", "next_obs", "action", "cost", "terminated", "truncated", "step")
HYP = settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _store():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _write_bag(path: Path, msgs, storage="sqlite3") -> Path:
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = _store()
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {}
        for topic, typ, t, msg in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=store)
            w.write(conns[topic], t, store.serialize_cdr(msg, typ))
    return path


def _meta(bag: Path) -> dict:
    return yaml.safe_load((bag / "metadata.yaml").read_text())


def _split_bag(root: Path, cut: int, name="split") -> Path:
    """The recording as rosbag2 writes it split in two SQLite parts: ``NAME_0.db3`` holds
    the first ``cut`` messages, ``NAME_1.db3`` the rest, metadata.yaml lists both (each
    part written by rosbags' writer; the metadata is the unsplit bag's with both files)."""
    msgs = _messages(_store())
    whole = _write_bag(root / f"{name}_whole", msgs)
    parts = [_write_bag(root / f"{name}_p0", msgs[:cut]), _write_bag(root / f"{name}_p1", msgs[cut:])]
    bag = root / name
    bag.mkdir()
    meta = _meta(whole)
    info = meta["rosbag2_bagfile_information"]
    info["relative_file_paths"] = [f"{name}_{i}.db3" for i in range(2)]
    info["files"] = []
    for i, p in enumerate(parts):
        shutil.copy(p / f"{p.name}.db3", bag / f"{name}_{i}.db3")
        f = _meta(p)["rosbag2_bagfile_information"]["files"][0]
        info["files"].append({**f, "path": f"{name}_{i}.db3"})
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    return bag


def _same(ds, ref):
    a, b = ds.arrays(), ref.arrays()
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    np.testing.assert_array_equal(ds.table.column("t_ns").to_numpy(), ref.table.column("t_ns").to_numpy())
    assert list(ds.episode_ids) == list(ref.episode_ids)


@pytest.fixture(scope="module")
def unsplit(tmp_path_factory):
    bag = _write_bag(tmp_path_factory.mktemp("ref") / "split", _messages(_store()))
    ds, s = ingest_mcap([bag], SPEC)
    a = ds.arrays()
    assert len(ds) == N - 1 and ds.n_episodes == 1  # ground truth by construction
    np.testing.assert_array_equal(np.round(a.obs[:, 0]), np.arange(N - 1))
    assert s["messages_used"] == {"/state": N, "/cmd_vel": N}
    return ds


# ---------------------------------------------------------------- a split SQLite bag
@HYP
@given(cut=st.integers(1, 2 * N - 1))
def test_a_split_sqlite_bag_is_one_recording_by_glob_directory_or_part(tmp_path_factory, unsplit, cut):
    root = tmp_path_factory.mktemp("split")
    bag = _split_bag(root, cut)
    import sqlite3

    from rosbags.highlevel import AnyReader

    for i, n in enumerate((cut, 2 * N - cut)):  # each part holds its messages
        with sqlite3.connect(bag / f"split_{i}.db3") as db:
            assert db.execute("select count(*) from messages").fetchone()[0] == n
    with AnyReader([bag], default_typestore=_store()) as r:  # rosbags reads both parts: 2N messages
        assert sum(1 for _ in r.messages()) == 2 * N
    inputs = {"glob": [str(bag / "*.db3")], "directory": [bag], "part 0": [bag / "split_0.db3"],
              "part 1": [bag / "split_1.db3"],
              "both parts and the directory": [bag / "split_1.db3", bag, bag / "split_0.db3"]}
    for what, files in inputs.items():
        for on_error in ("fail", "quarantine"):
            ds, s = ingest_mcap(files, SPEC, on_error=on_error, jobs=2)
            assert len(s["recordings"]) == 1, what
            assert s["messages_used"] == {"/state": N, "/cmd_vel": N}, what  # each message once
            assert s["doctor"]["ok"] and s["quarantined_rows"] == 0
            _same(ds, unsplit)


def test_a_db3_part_not_listed_or_without_metadata_is_refused_by_name(tmp_path):
    bag = _split_bag(tmp_path, N)
    stray = bag / "other.db3"
    shutil.copy(bag / "split_0.db3", stray)
    with pytest.raises(IngestError, match=r"other\.db3: not listed in .*metadata\.yaml"):
        ingest_mcap([stray], SPEC)
    lone = tmp_path / "lone"
    lone.mkdir()
    shutil.copy(bag / "split_0.db3", lone / "split_0.db3")
    with pytest.raises(IngestError, match=r"lone/split_0\.db3: a rosbag2 SQLite part without its bag's metadata\.yaml"):
        ingest_mcap([lone / "split_0.db3"], SPEC)


@pytest.mark.parametrize("damage", ["garbage", "text"])
def test_a_damaged_sqlite_part_is_one_clear_error_in_ingest_and_mcap_info(tmp_path, capsys, damage):
    """A corrupted .db3 raised sqlite3/UnicodeDecodeError inside rosbags: a traceback in
    mcap-info, and a misleading "field path" error in ingest."""
    from offline_adp.cli import main

    bag = _write_bag(tmp_path / "bag", _messages(_store()))
    db = next(bag.glob("*.db3"))
    data = db.read_bytes()
    if damage == "garbage":
        data = bytes(range(256)) * (len(data) // 256)
    else:  # a type name in the bag's own tables made undecodable: rosbags lets UnicodeDecodeError through
        i = data.find(b"std_msgs")
        assert i > 0
        data = data[:i] + b"\xff\xfe\xfd\xfc" + data[i + 4:]
    db.write_bytes(data)
    with pytest.raises(IngestError, match="cannot read as a ROS bag|not a database|malformed"):
        ingest_mcap([bag], SPEC)
    assert main(["mcap-info", str(bag)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "error:" in err


# ---------------------------------------------------------------- metadata.yaml entries
def _set_paths(bag: Path, entries) -> None:
    meta = _meta(bag)
    meta["rosbag2_bagfile_information"]["relative_file_paths"] = entries
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))


HOSTILE = st.sampled_from(["../outside.db3", "../../etc/passwd", "sub/../../outside.db3", "/abs/outside.db3",
                           "ABS", "LINK_OUT", "DUP", "LINK_DUP", "DIR", "FIFO", "MISSING", ""])


@HYP
@given(kind=HOSTILE, at=st.integers(0, 2), storage=st.sampled_from(["sqlite3", "mcap"]))
def test_hostile_relative_file_paths_are_refused_naming_metadata_and_entry(tmp_path_factory, kind, at, storage):
    root = tmp_path_factory.mktemp("hostile")
    bag = _write_bag(root / "bag", _messages(_store()), storage)
    own = _meta(bag)["rosbag2_bagfile_information"]["relative_file_paths"][0]
    outside = root / "outside.db3"
    shutil.copy(bag / own, outside)  # a readable bag file outside the bag: must not be read
    entry = {"ABS": str(outside), "DUP": own, "LINK_OUT": "link_out", "LINK_DUP": "link_dup", "DIR": "sub",
             "FIFO": "fifo", "MISSING": "missing.db3"}.get(kind, kind)
    (bag / "link_out").symlink_to(outside)
    (bag / "link_dup").symlink_to(bag / own)
    (bag / "sub").mkdir()
    os.mkfifo(bag / "fifo")
    entries = [own]
    entries.insert(min(at, 1), entry)
    _set_paths(bag, entries)
    first_bad = 1 if kind in ("DUP", "LINK_DUP") else entries.index(entry)  # a duplicate: the second listing
    with pytest.raises(IngestError) as err:
        ingest_mcap([bag], SPEC)
    msg = str(err.value)
    assert f"{bag / 'metadata.yaml'}: relative_file_paths[{first_bad}] = {entries[first_bad]!r}" in msg, msg
    assert "\n" not in msg and "Traceback" not in msg


def test_one_file_listed_a_thousand_times_is_refused_not_ingested_a_thousand_times(tmp_path):
    bag = _write_bag(tmp_path / "bag", _messages(_store()))
    own = _meta(bag)["rosbag2_bagfile_information"]["relative_file_paths"][0]
    _set_paths(bag, [own] * 1000)
    with pytest.raises(IngestError, match=r"relative_file_paths\[1\] = .*lists the same file as"):
        ingest_mcap([bag], SPEC)
    with pytest.raises(IngestError, match=r"relative_file_paths\[1\]"):
        ingest_mcap([bag / own], SPEC)  # by its part too


def test_metadata_that_is_not_a_regular_file_or_too_large_is_refused(tmp_path):
    bag = _write_bag(tmp_path / "bag", _messages(_store()))
    text = (bag / "metadata.yaml").read_text()
    (bag / "metadata.yaml").unlink()
    (bag / "metadata.yaml").symlink_to("/dev/zero")
    with pytest.raises(IngestError, match=r"metadata\.yaml: a symbolic link leading out of the bag directory"):
        ingest_mcap([bag], SPEC)
    (bag / "metadata.yaml").unlink()
    os.mkfifo(bag / "metadata.yaml")  # a reader would block forever
    with pytest.raises(IngestError, match=r"metadata\.yaml: the bag's metadata is not a regular file"):
        ingest_mcap([bag], SPEC)
    (bag / "metadata.yaml").unlink()
    (bag / "metadata.yaml").write_text(text + "#" * (1 << 20))
    with pytest.raises(IngestError, match=r"metadata\.yaml: the bag's metadata is \d+ bytes, more than the limit"):
        ingest_mcap([bag], SPEC)
    (bag / "metadata.yaml").write_text(text)
    ds, _ = ingest_mcap([bag], SPEC)  # restored: read
    assert len(ds) == N - 1


# ---------------------------------------------------------------- YAML aliases
def _bomb(levels=9) -> str:
    lines = ['  a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, levels):
        lines.append(f"  a{i}: &a{i} [" + ",".join([f"*a{i - 1}"] * 9) + "]")
    return ("rosbag2_bagfile_information:\n  storage_identifier: sqlite3\n" + "\n".join(lines)
            + f"\n  relative_file_paths: *a{levels - 1}\n")


def test_a_yaml_alias_bomb_is_refused_with_bounded_memory(tmp_path):
    bag = _write_bag(tmp_path / "bag", _messages(_store()))
    text = _bomb()
    assert len(text) < 800
    doc = yaml.safe_load(text)  # the document is valid YAML: 9**9 strings once its aliases are expanded
    assert len(doc["rosbag2_bagfile_information"]["relative_file_paths"]) == 9
    (bag / "metadata.yaml").write_text(text)
    code = textwrap.dedent(f"""
        import resource, sys
        from offline_adp.errors import IngestError
        from offline_adp.ingest.mcap import ingest_mcap, mcap_info
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_mcap_rosbags import SPEC
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        errors = []
        for call in (lambda: ingest_mcap([{str(bag)!r}], SPEC), lambda: mcap_info({str(bag)!r}),
                     lambda: ingest_mcap([{str(bag / 'bag.db3')!r}], SPEC)):
            try:
                call()
            except IngestError as exc:
                errors.append(str(exc))
        after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        print(after - before)
        print("\\n".join(errors))
    """)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    growth_kb, *errors = out.stdout.strip().split("\n")
    print(f"peak RSS growth reading the alias bomb: {int(growth_kb)} kB")
    assert int(growth_kb) < 20_000, growth_kb  # kB: the expanded document would need gigabytes
    assert len(errors) == 3
    # the control: what the old reader did with the parsed list (str() of each entry) exhausts
    # 300 MB more address space, so the bound above is what refusing aliases buys
    control = textwrap.dedent(f"""
        import resource, yaml
        import psutil
        rel = yaml.safe_load({text!r})["rosbag2_bagfile_information"]["relative_file_paths"]
        cap = psutil.Process().memory_info().vms + 300 * 2**20
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
        try:
            [str(x) for x in rel]
            print("expanded")
        except MemoryError:
            print("MemoryError")
    """)
    out = subprocess.run([sys.executable, "-c", control], capture_output=True, text=True, timeout=120, env=env)
    assert out.stdout.strip() == "MemoryError", (out.stdout, out.stderr[-500:])
    for e in errors:
        assert "metadata.yaml: not valid bag metadata (YAML alias *a0" in e and "not allowed" in e, e


# ---------------------------------------------------------------- mcap-info on every input ingest reads
def _write_ros1(path: Path, msgs, compression=None, chunk_threshold=1 << 20) -> Path:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    w = Writer(path)
    w.chunk_threshold = chunk_threshold
    if compression:
        w.set_compression(getattr(Writer.CompressionFormat, compression))
    with w:
        conns = {}
        for topic, typ, t, msg in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=store)
            w.write(conns[topic], t, store.serialize_ros1(msg, typ))
    return path


def _ros1_store():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC)


def test_mcap_info_describes_every_input_ingest_reads(tmp_path, capsys):
    from offline_adp.cli import main
    from offline_adp.ingest.mcap import mcap_info

    split = _split_bag(tmp_path, 30)
    inputs = {"sqlite bag": split, "sqlite part": split / "split_1.db3",
              "mcap bag": _write_bag(tmp_path / "mcap_bag", _messages(_store()), "mcap"),
              "ros1 bag": _write_ros1(tmp_path / "run.bag", _messages(_ros1_store(), ros1=True), "LZ4", 500)}
    for what, path in inputs.items():
        ingest_mcap([path], SPEC)  # ingest reads it ...
        info = mcap_info(path)  # ... so mcap-info describes it: every message, per topic, with its fields
        assert info["messages"] == 2 * N, what
        assert {t: v["messages"] for t, v in info["topics"].items()} == {"/state": N, "/cmd_vel": N}, what
        assert info["topics"]["/state"]["schema"] == "geometry_msgs/msg/PointStamped"
        assert "point.x" in info["topics"]["/state"]["fields"] and info["topics"]["/state"]["rate_hz"] == 10.0
        assert "linear.x" in info["topics"]["/cmd_vel"]["fields"] and "damage" not in info
    # the CLI: a glob over both parts and the directory describe the bag once
    assert main(["mcap-info", str(split / "split_0.db3"), str(split / "split_1.db3"), str(split)]) == 0
    out = capsys.readouterr().out
    assert out.count(f"{split}: profile ros2") == 1 and " 40 msgs" in out
    lone = tmp_path / "lone"
    lone.mkdir()
    shutil.copy(split / "split_0.db3", lone / "split_0.db3")
    with pytest.raises(IngestError, match=r"split_0\.db3: a rosbag2 SQLite part without its bag's metadata\.yaml "
                                          r"\(.*lone/metadata\.yaml is missing"):
        mcap_info(lone / "split_0.db3")
    assert main(["mcap-info", str(lone / "split_0.db3")]) == 2
    err = capsys.readouterr().err
    assert "metadata.yaml is missing" in err and err.count("\n") == 1 and "Traceback" not in err


# ---------------------------------------------------------------- a ROS 1 bag cut short
GAP_SPEC = {"clock": {"topic": "/state", "time": "header.stamp"}, "episodes": {"gap": 1.0},
            "streams": [{"topic": "/state", "time": "header.stamp", "fields": {"x": "point.x"}, "max_age": 0.001}],
            "action": {"topic": "/cmd_vel", "fields": {"v": "linear.x", "w": "angular.z"}, "max_age": 0.01,
                       "vectors": [[v, w] for v in (0.0, 0.2, 0.4) for w in (-0.5, 0.0, 0.5)]},
            "cost": {"terms": [{"field": "action.v", "op": "square"}]}}


def _episodes_messages(store, n_eps=6, steps=15):
    """``n_eps`` runs of ``steps`` states at 10 Hz (and commands 3 ms later), 3 s apart:
    with episodes.gap = 1 s, one episode each."""
    one = _messages(store, ros1=True)[: 2 * steps]
    out = []
    for e in range(n_eps):
        for topic, typ, t, msg in one:
            shift = e * (steps * 100_000_000 + 3_000_000_000)
            if topic == "/state":
                st_ = msg.header.stamp
                ns = st_.sec * 10**9 + st_.nanosec + shift
                msg = type(msg)(
                    header=type(msg.header)(
                        seq=msg.header.seq, stamp=type(st_)(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="map"
                    ),
                    point=type(msg.point)(x=float(e * 100) + msg.point.x, y=0.0, z=0.0),
                )
            out.append((topic, typ, t + shift, msg))
    return out


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frac=st.floats(0.15, 0.999), compression=st.sampled_from([None, "BZ2", "LZ4"]),
       threshold=st.sampled_from([300, 1000, 4000]))
@pytest.mark.parametrize("pinned", [0.6])
def test_a_ros1_bag_cut_short_keeps_every_episode_that_ended_before_the_cut(tmp_path_factory, pinned, frac, compression,
                                                                           threshold):
    from rosbags.rosbag1 import Reader

    from offline_adp.ingest.mcap import parse_mcap_spec

    spec = parse_mcap_spec(GAP_SPEC)
    root = tmp_path_factory.mktemp("cut")
    whole = _write_ros1(root / "whole.bag", _episodes_messages(_ros1_store()), compression, threshold)
    ref, _ = ingest_mcap([whole], spec)
    assert ref.n_episodes == 6 and len(ref) == 6 * 14  # ground truth by construction
    data = whole.read_bytes()
    for f in (frac, pinned):
        cut_at = int(len(data) * f)
        cut = root / f"cut_{f}.bag"
        cut.write_bytes(data[:cut_at])
        with Reader(whole) as r:  # rosbags' index of the whole bag: the chunks wholly before the cut
            done = [ci.end_time - 1 for ci in r.chunk_infos if r.chunks[ci.pos].datapos + r.chunks[ci.pos].datasize
                    <= cut_at]
            last_t = max(done, default=-1)  # every message up to this time is recovered, none after
            all_t = sorted(t for _, t, _ in r.messages())
        recovered = [t for t in all_t if t <= last_t]
        t_ns = ref.table.column("t_ns").to_numpy()
        ep = ref.table.column("episode_id").to_numpy(zero_copy_only=False)
        ids = list(dict.fromkeys(ep))
        # an episode ended before the cut when a later message (its successor's) was recovered
        expected = [i for i in ids if recovered and recovered[-1] > t_ns[ep == i].max() + 1_000_000_000]
        if f == pinned:  # the case: a 60% cut holds some complete episodes, not all
            assert 0 < len(expected) < 6, expected
        with pytest.raises(Exception) as no_read:  # rosbags' own reader cannot open it (its index is gone)
            Reader(cut).open()
        assert type(no_read.value).__module__.startswith("rosbags")
        if not expected:
            with pytest.raises(IngestError, match="no episode|no decodable messages"):  # nothing complete
                ingest_mcap([cut], spec, on_error="quarantine")
            continue
        with pytest.warns(UserWarning, match=r"cut_.*\.bag.*cut at offset"):
            ds, s = ingest_mcap([cut], spec, on_error="fail")  # a file merely cut short is kept
        assert ds.n_episodes == len(expected), (f, expected)
        rows = np.isin(ep, expected)
        a, b = ds.arrays(), ref.arrays()
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name)[rows], err_msg=name)
        np.testing.assert_array_equal(ds.table.column("t_ns").to_numpy(), t_ns[rows])
        assert s["doctor"]["ok"]


# ---------------------------------------------------------------- a spec topic absent from the file
def _with_reward(store, ks, ros1=False):
    F64 = store.types["std_msgs/msg/Float64"]
    out = _messages(store, ros1=ros1)
    out += [("/cartpole/reward", "std_msgs/msg/Float64", t + MS_, F64(data=1.0))
            for topic, _, t, _ in list(out) if topic == "/state" and (t - out[0][2]) // 100_000_000 in ks]
    return sorted(out, key=lambda m: m[2])


MS_ = 1_000_000
REWARD_SPEC = {**GAP_SPEC, "episodes": {},
               "streams": GAP_SPEC["streams"] + [{"topic": "/cartpole/reward", "fields": {"r": "data"}, "max_age": 0.2,
                                                  "role": "aux"}]}


@pytest.mark.parametrize("kind", ["sqlite", "mcap", "ros1"])
def test_a_spec_topic_absent_from_the_file_is_named_as_such(tmp_path, kind):
    from offline_adp.ingest.mcap import parse_mcap_spec

    spec = parse_mcap_spec(REWARD_SPEC)
    write = {"sqlite": lambda p, m: _write_bag(p, m, "sqlite3"), "mcap": lambda p, m: _write_bag(p, m, "mcap"),
             "ros1": lambda p, m: _write_ros1(p.with_suffix(".bag"), m)}[kind]
    store = _ros1_store() if kind == "ros1" else _store()
    absent = write(tmp_path / "absent", _messages(store, ros1=kind == "ros1"))
    for on_error in ("fail", "quarantine"):
        with pytest.raises(IngestError) as err:
            ingest_mcap([absent], spec, on_error=on_error)
        msg = str(err.value)
        assert "topic '/cartpole/reward' of the spec is not in the file" in msg and str(absent) in msg, msg
        assert "['/cmd_vel', '/state']" in msg and "max_age" not in msg, msg
    late = write(tmp_path / "late", _with_reward(store, range(20, 40), ros1=kind == "ros1"))  # there, but late
    with pytest.raises(IngestError, match=r"no /cartpole/reward message within max_age"):
        ingest_mcap([late], spec)
    full = write(tmp_path / "full", _with_reward(store, range(40), ros1=kind == "ros1"))  # there throughout
    ds, s = ingest_mcap([full], spec)
    assert len(ds) == N - 1 and s["messages_used"]["/cartpole/reward"] == N
