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
              "part 1": [bag / "split_1.db3"], "both parts and the directory": [bag / "split_1.db3", bag, bag / "split_0.db3"]}
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
    for e in errors:
        assert "metadata.yaml: not valid bag metadata (YAML alias *a0" in e and "not allowed" in e, e
