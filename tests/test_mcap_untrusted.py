"""Bounded reading of untrusted MCAP: record and chunk lengths are checked against the
file size and a cap before anything is allocated (declared uncompressed sizes are
untrusted), a log_time of 2^64-1 is a clean error, and mutated small files give a clean
error of ours or a result: never a raw exception, a hang or a memory blowup."""

from __future__ import annotations

import json
import resource
import signal
import struct
import time
import zlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from offline_adp.errors import OfflineADPError
from offline_adp.ingest.mcap import ingest_mcap, mcap_info, parse_mcap_spec

MS = 1_000_000
NIGHTLY = settings().max_examples >= 1000
N_FUZZ = 3000 if NIGHTLY else 300

SPEC = parse_mcap_spec({
    "clock": {"topic": "/s", "reorder_window": 0.2},
    "streams": [{"topic": "/s", "fields": {"x": "x"}, "max_age": 0.001}],
    "action": {"topic": "/u", "field": "u", "max_age": 0.05, "missing": "drop_step", "type": "discrete",
               "values": [0.0, 1.0]},
    "cost": {"terms": [{"field": "x", "op": "square"}]},
})


def _small_file(chunked: bool = True, compression: str = "zstd") -> bytes:
    from io import BytesIO

    from mcap.writer import CompressionType, Writer

    buf = BytesIO()
    w = Writer(buf, chunk_size=600, use_chunking=chunked,
               compression=CompressionType.ZSTD if compression == "zstd" else CompressionType.NONE)
    w.start()
    sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
    cs = w.register_channel(topic="/s", message_encoding="json", schema_id=sid)
    cu = w.register_channel(topic="/u", message_encoding="json", schema_id=sid)
    for k in range(30):
        t = k * 100 * MS
        w.add_message(cs, log_time=t, publish_time=t, data=json.dumps({"x": 0.1 * k}).encode())
        w.add_message(cu, log_time=t + MS, publish_time=t + MS, data=json.dumps({"u": float(k % 2)}).encode())
    w.finish()
    return buf.getvalue()


def _chunk_offsets(data: bytes) -> list[int]:
    out, off = [], 8
    while off + 9 <= len(data):
        op, n = struct.unpack_from("<BQ", data, off)
        if op == 0x06:
            out.append(off)
        off += 9 + n
    return out


def test_a_chunk_declaring_a_huge_uncompressed_size_is_damage_not_an_allocation(tmp_path):
    data = bytearray(_small_file())
    off = _chunk_offsets(bytes(data))[1]
    # chunk body: start u64, end u64, uncompressed_size u64, crc u32, compression str, data
    struct.pack_into("<Q", data, off + 9 + 16, 1 << 40)  # "1 TiB uncompressed"
    f = tmp_path / "huge.mcap"
    f.write_bytes(bytes(data))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    info = mcap_info(f)
    assert "lost 1 corrupt chunk" in info["damage"] and "declares 1099511627776 bytes uncompressed" in info["damage"]
    with pytest.warns(UserWarning, match="declares 1099511627776 bytes"), \
            pytest.raises(OfflineADPError, match=f"damage: lost chunk at offset {off}"):
        ingest_mcap([f], SPEC, on_error="quarantine")  # the one episode lost its messages in that chunk
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200 * 1024  # < 200 MiB more (KiB units)


def test_a_record_longer_than_the_file_is_a_cut_not_an_allocation(tmp_path):
    data = bytearray(_small_file())
    off = _chunk_offsets(bytes(data))[2]
    struct.pack_into("<Q", data, off + 1, (1 << 64) - 1)
    f = tmp_path / "long.mcap"
    f.write_bytes(bytes(data))
    assert "does not fit in the file" in mcap_info(f)["damage"]


def test_log_time_of_2_64_minus_1_is_a_clean_error(tmp_path):
    from mcap.writer import Writer

    f = tmp_path / "t.mcap"
    with open(f, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        c = w.register_channel(topic="/s", message_encoding="json", schema_id=sid)
        w.add_message(c, log_time=(1 << 64) - 1, publish_time=0, data=b'{"x": 1.0}')
        w.finish()
    with pytest.raises(OfflineADPError, match=r"t.mcap: .*log_time 18446744073709551615 .*beyond the int64 range"):
        ingest_mcap([f], SPEC)
    with pytest.raises(OfflineADPError, match="beyond the int64 range"):
        mcap_info(f)


def _mutate(data: bytes, edits: list[tuple[int, int]], words: list[tuple[int, int]], cut: int | None) -> bytes:
    b = bytearray(data)
    for pos, val in edits:
        b[pos % len(b)] = val
    for pos, val in words:
        p = pos % max(len(b) - 8, 1)
        b[p:p + 8] = struct.pack("<Q", val)
    if cut is not None:
        b = b[: cut % (len(b) + 1)]
    return bytes(b)


BASES = {"zstd": _small_file(), "none": _small_file(compression="none"), "plain": _small_file(chunked=False)}


class _Timeout(Exception):
    pass


def _alarm(*_):
    raise _Timeout


@pytest.mark.filterwarnings("ignore::UserWarning")
@settings(max_examples=N_FUZZ)
@given(st.sampled_from(sorted(BASES)),
       st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=6),
       st.lists(st.tuples(st.integers(0, 10**6), st.sampled_from([0, 1, 2**31, 2**32 + 7, 2**63, 2**64 - 1])),
                max_size=2),
       st.none() | st.integers(0, 10**6))
def test_mutated_files_give_a_clean_error_or_a_result(tmp_path_factory, base, edits, words, cut):
    data = _mutate(BASES[base], edits, words, cut)
    f = tmp_path_factory.mktemp("fuzz") / "m.mcap"
    f.write_bytes(data)
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(10)  # a hang fails the test
    t0 = time.perf_counter()
    try:
        for call in (lambda: mcap_info(f), lambda: ingest_mcap([f], SPEC),
                     lambda: ingest_mcap([f], SPEC, on_error="quarantine")):
            try:
                call()
            except OfflineADPError:
                pass
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    assert time.perf_counter() - t0 < 10
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss < 4 * 1024 * 1024  # KiB: never GBs
    zlib.crc32(data)  # (keeps the mutated bytes referenced until here)
