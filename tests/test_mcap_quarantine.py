"""MCAP quarantine as for Parquet: rejected episodes go to ``quarantine/`` with a reason
per row; every row carries ``src_file`` and ``src_log_time``; doctor findings name the
file and the message's log_time; rows in the dataset + rows in quarantine = transitions
assembled. The Dask ingest path keeps quarantine too."""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp.data.dataset import read_dataset
from offline_adp.data.io import read_quarantine
from offline_adp.errors import ValidationError
from offline_adp.ingest.mcap import ingest_mcap
from tests.test_ingest_mcap_streaming import MS, T0, episode_messages, write_log
from tests.test_ingest_mcap_streaming import spec as _spec


def _log(tmp_path):
    """Three episodes 5 s apart (gap episodes); the second has a NaN position at one step
    (the doctor's non_finite) and the third a command outside the action table."""
    msgs = []
    for ep in range(3):
        part = episode_messages(10, t0=T0 + ep * 5_000 * MS, ep=ep)
        for i, (topic, t, _m) in enumerate(part):
            if ep == 1 and topic == "/fast" and t == T0 + 5_000 * MS + 300 * MS:
                part[i] = (topic, t, {"pos": {"x": float("nan")}})
            if ep == 2 and topic == "/cmd" and t == T0 + 10_000 * MS + 395 * MS:
                part[i] = (topic, t, {"u": [7.0]})
        msgs += part
    return write_log(tmp_path / "q.mcap", msgs)


def test_quarantine_keeps_every_row_with_file_log_time_and_reason(tmp_path):
    f = _log(tmp_path)
    with pytest.raises(ValidationError) as err:  # fail: the findings name the file and the message's log_time
        ingest_mcap([f], _spec())
    text = str(err.value)
    assert f"{f}: log_time {T0 + 5_000 * MS + 200 * MS}" in text  # the step whose next state is NaN
    assert f"{f}: log_time {T0 + 10_000 * MS + 400 * MS}" in text  # the step of the bad command
    ds, s = ingest_mcap([f], _spec(), tmp_path / "ds", on_error="quarantine")
    q = read_quarantine(tmp_path / "ds")
    assert ds.n_episodes == 1 and len(ds) == 9
    assert len(ds) + q.num_rows == s["transitions_assembled"] == 27 and s["quarantined_rows"] == q.num_rows == 18
    assert set(q.column("src_file").to_pylist()) == {str(f)}
    lt = q.column("src_log_time").to_numpy()
    steps = q.column("step").to_numpy()
    ep = np.where(lt >= T0 + 10_000 * MS, 2, 1)
    np.testing.assert_array_equal(lt, T0 + ep * 5_000 * MS + steps * 100 * MS)  # the clock message of each step
    reasons = q.column("reason").to_pylist()
    assert all(r for r in reasons)
    assert any("non_finite" in r for r in reasons) and any("action_out_of_range" in r for r in reasons)
    back = read_dataset(tmp_path / "ds")  # the kept rows carry their origin too
    np.testing.assert_array_equal(back.table.column("src_log_time").to_numpy(), T0 + np.arange(9) * 100 * MS)


def test_episodes_rejected_while_assembling_go_to_quarantine_with_their_reason(tmp_path):
    """A command missing for a while: under fail an error naming file and log_time; under
    quarantine that episode's rows are set aside with the reason."""
    msgs = [m for ep in range(2) for m in episode_messages(10, t0=T0 + ep * 5_000 * MS, ep=ep)
            if not (ep == 1 and m[0] == "/cmd" and 5_300 * MS <= m[1] - T0 <= 5_600 * MS)]
    f = write_log(tmp_path / "gap.mcap", msgs)
    from offline_adp.errors import IngestError

    with pytest.raises(IngestError,
                       match=r"gap.mcap: episode gap-00001, step 4 \(log_time 15400000000\): no /cmd command"):
        ingest_mcap([f], _spec())
    ds, s = ingest_mcap([f], _spec(), tmp_path / "ds", on_error="quarantine")
    q = read_quarantine(tmp_path / "ds")
    assert list(ds.episode_ids) == ["gap-00000"] and q.num_rows == 9
    assert len(ds) + q.num_rows == s["transitions_assembled"]
    assert set(q.column("reason").to_pylist()) == {s["rejected_episodes"][0]["reason"]}
    assert s["episodes_without_command"] == 1


def test_dask_ingest_keeps_quarantine(tmp_path):
    pytest.importorskip("distributed")
    from distributed import Client, LocalCluster

    from offline_adp.engines.dask import ingest_distributed

    f = _log(tmp_path)
    local, s = ingest_mcap([f], _spec(), tmp_path / "local", on_error="quarantine")
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cl, \
            Client(cl) as client:
        ds, _ = ingest_distributed(client, [f], _spec(), tmp_path / "dist", fmt="mcap", on_error="quarantine")
    assert ds.fingerprint() == local.fingerprint()
    a, b = read_quarantine(tmp_path / "local"), read_quarantine(tmp_path / "dist")
    assert b is not None and a.num_rows == b.num_rows == s["quarantined_rows"]
    assert a.column("reason").to_pylist() == b.column("reason").to_pylist()


def test_the_doctor_on_an_mcap_dataset_directory_names_file_and_log_time(tmp_path):
    import pyarrow as pa

    from offline_adp.data.dataset import TransitionDataset
    from offline_adp.data.io import write_dataset
    from offline_adp.data.validate import validate_directory

    f = write_log(tmp_path / "ok.mcap", episode_messages(10))
    ds, _ = ingest_mcap([f], _spec())
    col = ds.table.column("obs.x").to_numpy().copy()
    col[4] = np.nan  # a defect the doctor finds, at step 4
    t = ds.table.set_column(ds.table.column_names.index("obs.x"), "obs.x", pa.array(col))
    write_dataset(TransitionDataset(t, ds.info), tmp_path / "ds")
    report = validate_directory(tmp_path / "ds")
    assert not report.ok and f"{f}: log_time {T0 + 4 * 100 * MS} (episode ok-00000, step 4)" in report.to_text()
