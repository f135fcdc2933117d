"""Every door as safe as the front door (part 2): what the side doors (annotate, export,
fingerprint, damaged MCAP chunks) claim, checked against ground truth known by construction."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from offline_adp.simulate import simulate

SPEC = Path(__file__).resolve().parents[1] / "data" / "specs" / "path_tracking_mcap.toml"


# --------------------------------------------------------------------------- annotate
def test_annotations_carry_the_annotated_messages_log_time_exactly(tmp_path):
    """Each annotation is stamped with the log_time of the clock message that made its step
    (found in the original log by its header stamp, which is the step's t_ns), to the
    nanosecond; the writer's transport delay makes log_time differ from the stamp by 1-3 ms."""
    pytest.importorskip("mcap")
    from mcap.reader import make_reader

    from offline_adp.annotate import annotate_mcap
    from offline_adp.ingest.mcap import ingest_mcap
    from offline_adp.runs import fit_run
    from offline_adp.simulate.mcap_writer import write_mcap

    files = write_mcap(simulate("path_tracking", 3, 0, seed=3, horizon=20), tmp_path / "logs", encoding="json", seed=4)
    ingest_mcap(files, SPEC, tmp_path / "data")
    fit_run(tmp_path / "data", tmp_path / "run", params={"regressor": "extra_trees", "n_iterations": 2,
                                                         "regressor_params": {"n_estimators": 3, "n_jobs": 1}})
    log, out = files[0], tmp_path / "annotated.mcap"
    annotate_mcap(tmp_path / "run", log, out)
    with open(log, "rb") as f:  # ground truth: the clock messages, header stamp -> log_time
        clock = {}
        for _, _, m in make_reader(f).iter_messages(topics=["/planning/tracking_state"]):
            h = json.loads(m.data)["header"]["stamp"]
            clock[int(h["sec"]) * 1_000_000_000 + int(h["nanosec"])] = m.log_time
    steps, _ = ingest_mcap([log], SPEC)
    t_ns = dict(zip(zip(steps.column("episode_id").astype(str), steps.column("step").tolist(), strict=True),
                    steps.column("t_ns").tolist(), strict=True))
    with open(out, "rb") as f:
        added = [(ch.topic, m) for _, ch, m in make_reader(f).iter_messages(log_time_order=False)
                 if ch.topic.startswith("/offline_adp/")]
    assert len(added) == 4 * len(steps)
    delays = []
    for _, m in added:
        d = json.loads(m.data)
        t = t_ns[(d["episode_id"], d["step"])]
        assert m.log_time == clock[t]  # exactly the annotated message's log_time
        delays.append(clock[t] - t)
    assert min(delays) > 0  # the test could fail: stamps and log times do differ in this log


# --------------------------------------------------------------------------- LeRobot episodes_stats
def test_lerobot_episodes_stats_are_numpys_on_each_episodes_source_arrays(tmp_path):
    from offline_adp.formats import to_lerobot

    ds = simulate("path_tracking", 3, 2, seed=7, horizon=15)
    root = to_lerobot(ds, tmp_path / "lr")
    lines = (root / "meta" / "episodes_stats.jsonl").read_text().splitlines()
    a = ds.arrays()
    ids = ds.episode_ids
    meta = [json.loads(x) for x in (root / "meta" / "episodes.jsonl").read_text().splitlines()]
    assert len(lines) == len(meta) == ds.n_episodes
    feats = json.loads((root / "meta" / "info.json").read_text())["features"]
    for line, m in zip(lines, meta, strict=True):
        rec = json.loads(line)
        assert rec["episode_index"] == m["episode_index"]
        rows = a.episode == list(ids).index(m["episode_id"])  # the episode's rows in the source dataset
        src = {"observation.state": a.obs[rows], "next.observation.state": a.next_obs[rows],
               "action": ds.info.action_table.values[a.action[rows]], "action_index": a.action[rows],
               "next.reward": -a.cost[rows], "next.done": a.terminated[rows], "next.truncated": a.truncated[rows],
               "frame_index": np.arange(rows.sum())}
        assert set(rec["stats"]) == set(feats)
        for name, x in src.items():
            x = np.asarray(x, np.float64).reshape(int(rows.sum()), -1)
            st = rec["stats"][name]
            assert st["count"] == [int(rows.sum())]
            np.testing.assert_array_equal(st["min"], x.min(axis=0))
            np.testing.assert_array_equal(st["max"], x.max(axis=0))
            np.testing.assert_allclose(st["mean"], x.mean(axis=0), rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(st["std"], x.std(axis=0), rtol=1e-9, atol=1e-12)


# --------------------------------------------------------------------------- fingerprint
def _with(table, name, values):
    import pyarrow as pa

    return table.set_column(table.column_names.index(name), name, pa.array(values, table.schema.field(name).type))


def test_fingerprint_depends_on_the_values_only(tmp_path):
    """The same content stored in different parts, row groups and chunks has one fingerprint;
    changing one value (even by 1 ns of a timestamp, where a null makes the column
    nullable) changes it."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from offline_adp.data.dataset import TransitionDataset, read_dataset
    from offline_adp.data.io import write_dataset

    ds = simulate("path_tracking", 5, 0, seed=11, horizon=12)
    t = ds.table
    t_ns = t.column("t_ns").to_pylist()
    t_ns[3] = None  # a nullable timestamp column (epoch-scale values, beyond float64's integer range)
    t = _with(t, "t_ns", t_ns)
    base = TransitionDataset(t, ds.info)
    fp = base.fingerprint()
    # the same rows, in other pieces: written as parts of other sizes, row groups, concatenated slices
    for rows in (7, 25, 10_000):
        assert read_dataset(write_dataset(base, tmp_path / f"d{rows}", rows_per_part=rows)).fingerprint() == fp
    for k in (1, 5, 13):
        pieces = pa.concat_tables([t.slice(i, k) for i in range(0, t.num_rows, k)])
        assert pieces.column("obs.e").num_chunks > 1
        assert TransitionDataset(pieces, ds.info).fingerprint() == fp
        pq.write_table(t, tmp_path / f"rg{k}.parquet", row_group_size=k)
        assert TransitionDataset(pq.read_table(tmp_path / f"rg{k}.parquet"), ds.info).fingerprint() == fp
    # the source column stored as plain strings or as a dictionary with another value order
    plain = t.set_column(t.column_names.index("source"), "source", t.column("source").cast(pa.string()))
    assert TransitionDataset(plain, ds.info).fingerprint() == fp
    # one value changed: a different fingerprint
    changed = list(t_ns)
    changed[7] += 1  # one nanosecond
    assert TransitionDataset(_with(t, "t_ns", changed), ds.info).fingerprint() != fp
    e = t.column("obs.e").to_numpy().copy()
    e[5] = np.nextafter(e[5], np.inf)
    assert TransitionDataset(_with(t, "obs.e", e), ds.info).fingerprint() != fp
    moved = list(t_ns)
    moved[3], moved[4] = moved[4], None  # the null moved to another row
    assert TransitionDataset(_with(t, "t_ns", moved), ds.info).fingerprint() != fp


# --------------------------------------------------------------------------- ONNX input documentation
def test_onnx_input_names_its_features_and_units_in_the_graph(tmp_path):
    """A consumer reading only the graph (onnx's own loader, no metadata) sees each input
    column's feature name and unit, in column order; the metadata is kept."""
    onnx = pytest.importorskip("onnx")
    from offline_adp.algorithms.fqi import FittedQIteration
    from offline_adp.onnx_export import save_onnx

    ds = simulate("path_tracking", 2, 2, seed=5, horizon=10)
    f = FittedQIteration(regressor="extra_trees", regressor_params={"n_estimators": 3, "n_jobs": 1}, n_iterations=2,
                         gamma=0.9).fit(ds)
    path = save_onnx(f.policy_, tmp_path / "p.onnx")
    model = onnx.load(str(path))
    (obs,) = [i for i in model.graph.input if i.name == "observation"]
    names, units = ds.info.feature_names, [ft.unit for ft in ds.info.features]
    assert any(units), "no feature has a unit: the test would prove nothing"
    cols = obs.doc_string.split(": ", 1)[1].split(", ")
    assert cols == [f"{n} [{u}]" if u else n for n, u in zip(names, units, strict=True)]
    (act,) = [o for o in model.graph.output if o.name == "action"]
    at = ds.info.action_table
    assert act.doc_string.split(": ", 1)[1].split(", ") == [f"{n} [{u}]" if u else n
                                                              for n, u in zip(at.dims, at.units, strict=True)]
    meta = {p.key: p.value for p in model.metadata_props}
    assert json.loads(meta["feature_names"]) == list(names) and json.loads(meta["feature_units"]) == units


# --------------------------------------------------------------------------- damaged MCAP chunks
def _chunks(path):
    """Ground truth from the intact file: per chunk record, its byte range and the log
    times of its messages (all topics)."""
    import struct
    from io import BytesIO

    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk

    data = path.read_bytes()
    pos, out = 8, []
    while pos + 9 <= len(data):
        opcode, length = struct.unpack("<BQ", data[pos:pos + 9])
        if opcode == 0x06:
            chunk = Chunk.read(ReadDataStream(BytesIO(data[pos + 9:pos + 9 + length])))
            out.append((pos, pos + 9 + length, [r.log_time for r in breakup_chunk(chunk) if isinstance(r, Message)]))
        if opcode == 0x0F:
            break
        pos += 9 + length
    return out


def _episode_spans(path):
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        ev = [(m.log_time, json.loads(m.data)) for _, _, m in make_reader(fh).iter_messages(topics=["/episode/event"])]
    starts = {e["episode_id"]: t for t, e in ev if e["event"] == "start"}
    ends = {e["episode_id"]: t for t, e in ev if e["event"] == "end"}
    return {ep: (starts[ep], ends[ep]) for ep in starts}


def _corrupt_chunk_holding_whole_episodes(tmp_path, seed):
    pytest.importorskip("mcap")
    from offline_adp.simulate.mcap_writer import write_mcap

    ds = simulate("path_tracking", 24, 0, seed=seed, horizon=4)  # short episodes: several in one chunk
    (f,) = write_mcap(ds, tmp_path / "logs", encoding="json", chunk_size=24 * 1024)
    spans = _episode_spans(f)
    chunks = _chunks(f)
    held = [{ep for ep, (a, b) in spans.items() if any(a <= t <= b for t in ts)} for _, _, ts in chunks]
    whole = [{ep for ep, (a, b) in spans.items() if min(ts) <= a and b <= max(ts)} for _, _, ts in chunks]
    k = max(range(1, len(chunks) - 1), key=lambda i: len(whole[i]))  # an inner chunk, most whole episodes
    assert len(whole[k]) >= 2, "no chunk holds whole episodes: the test would prove nothing"
    assert held[k] - whole[k], "the chunk should also cut into a neighbouring episode"
    lo, hi, _ = chunks[k]
    data = bytearray(f.read_bytes())
    data[(lo + hi) // 2] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    return ds, bad, held[k]


@pytest.mark.parametrize("seed", [1, 2])
def test_a_lost_chunk_counts_every_episode_it_held_even_wholly_inside_it(tmp_path, seed):
    from offline_adp.ingest.mcap import ingest_mcap

    ds, bad, held = _corrupt_chunk_holding_whole_episodes(tmp_path, seed)
    with pytest.warns(UserWarning, match="lost 1 corrupt chunk"):
        part, summary = ingest_mcap([bad], SPEC, tmp_path / "q", on_error="quarantine")
    assert summary["episodes_lost_to_damage"] == len(held)
    assert set(part.episode_ids) == set(ds.episode_ids) - held  # exactly the others are kept


def test_a_lost_chunk_without_message_index_is_said_to_be_uncounted(tmp_path):
    """Without the message-index records after a chunk nothing tells how many episodes a
    lost chunk held wholly: the count is then a lower bound, and the summary says so."""
    from mcap.reader import make_reader
    from mcap.writer import IndexType, Writer

    from offline_adp.ingest.mcap import ingest_mcap

    ds, indexed, held = _corrupt_chunk_holding_whole_episodes(tmp_path, 1)
    src = tmp_path / "logs" / next(p.name for p in (tmp_path / "logs").iterdir())
    plain = tmp_path / "plain.mcap"
    with open(src, "rb") as fin, open(plain, "wb") as fout:  # the same messages, chunked, no index records
        w = Writer(fout, index_types=IndexType.NONE, chunk_size=24 * 1024)
        w.start()
        sch_ids, ch_ids = {}, {}
        for sch, ch, m in make_reader(fin).iter_messages(log_time_order=False):
            if sch.id not in sch_ids:
                sch_ids[sch.id] = w.register_schema(sch.name, sch.encoding, sch.data)
            if ch.id not in ch_ids:
                ch_ids[ch.id] = w.register_channel(ch.topic, ch.message_encoding, sch_ids[sch.id])
            w.add_message(ch_ids[ch.id], m.log_time, m.data, m.publish_time)
        w.finish()
    chunks = _chunks(plain)
    lo, hi, _ = chunks[len(chunks) // 2]
    data = bytearray(plain.read_bytes())
    data[(lo + hi) // 2] ^= 0xFF
    plain.write_bytes(bytes(data))
    with pytest.warns(UserWarning, match="lost 1 corrupt chunk"):
        part, summary = ingest_mcap([plain], SPEC, tmp_path / "q2", on_error="quarantine")
    assert summary["lost_chunks_uncounted"] == 1
    lost = set(ds.episode_ids) - set(part.episode_ids)
    assert 1 <= summary["episodes_lost_to_damage"] <= len(lost)
    _, summary = ingest_mcap([indexed], SPEC, tmp_path / "q3", on_error="quarantine")
    assert summary["lost_chunks_uncounted"] == 0 and summary["episodes_lost_to_damage"] == len(held)


@pytest.mark.parametrize("kind", ["dev_zero", "directory", "huge", "binary"])
def test_load_mcap_spec_reads_only_a_bounded_regular_text_file(tmp_path, kind):
    from offline_adp.errors import SpecError
    from offline_adp.ingest.mcap.spec import load_mcap_spec

    target = {"dev_zero": "/dev/zero", "directory": str(tmp_path)}.get(kind)
    if kind == "huge":
        target = str(tmp_path / "huge.toml")
        with open(target, "wb") as f:
            f.truncate(64 * 2**20)
    if kind == "binary":
        target = str(tmp_path / "bin.toml")
        Path(target).write_bytes(b"\xff\xfe\x00bad")
    with pytest.raises(SpecError, match=re.escape(str(Path(target).name)) if kind != "dev_zero" else "zero"):
        load_mcap_spec(target)


def test_a_dataset_written_with_the_previous_fingerprint_still_validates(tmp_path):
    """The fingerprint's definition changed; a dataset (or run) that stored the previous one
    is recognised, not reported as changed; anything else still is."""
    from offline_adp.data.dataset import read_dataset
    from offline_adp.data.io import write_dataset
    from offline_adp.data.validate import validate_directory

    ds = simulate("path_tracking", 2, 1, seed=3, horizon=12)
    out = write_dataset(ds, tmp_path / "d")
    info_file = out / "meta" / "info.json"
    back = read_dataset(out)
    assert back.legacy_fingerprint() != back.fingerprint()
    for stored, ok in ((back.legacy_fingerprint(), True), ("0" * 64, False)):
        info = json.loads(info_file.read_text())
        info["fingerprint"] = stored
        info_file.write_text(json.dumps(info))
        checks = set(validate_directory(out).findings["check"]) if len(validate_directory(out).findings) else set()
        assert ("fingerprint_mismatch" not in checks) is ok
