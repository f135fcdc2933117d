"""The dataset fingerprint (definition v3) against a straightforward reference
implementation of its definition, its dependence on every value of every column, and
the recognition of fingerprints stored under the earlier definitions (v2, legacy)."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pyarrow as pa
import pytest

from offline_adp.data import schema as S
from offline_adp.data.dataset import TransitionDataset, read_dataset
from offline_adp.data.io import write_dataset
from offline_adp.simulate import simulate

NARROW = (pa.int8(), pa.int16(), pa.int32(), pa.uint8(), pa.uint16())


def _known(ds: TransitionDataset) -> list[str]:
    f = ds.info.feature_names
    names = [S.EPISODE_ID, S.STEP, S.T_NS, *[S.obs_column(x) for x in f], S.ACTION, S.COST,
             *[S.next_obs_column(x) for x in f], S.TERMINATED, S.TRUNCATED, S.SOURCE, S.BEHAVIOR_PROB]
    return sorted(n for n in names if n in ds.table.column_names)


def reference(ds: TransitionDataset, version: int) -> str:
    """The fingerprint's definition, column by column on whole (combined) columns."""
    h = hashlib.sha256()
    h.update(f"offline_adp fingerprint v{version}\x00".encode())
    h.update(repr((ds.info.feature_names, ds.info.action_table.to_dict())).encode())
    for name in _known(ds):
        col = ds.table.column(name).combine_chunks()
        if pa.types.is_dictionary(col.type):
            col = col.cast(col.type.value_type)
        n = len(col)
        h.update(len(name.encode()).to_bytes(8, "little") + name.encode() + n.to_bytes(8, "little"))
        nulls = np.asarray(col.is_null(), dtype=bool)
        h.update(np.packbits(nulls).tobytes())
        if pa.types.is_string(col.type):
            values = ["" if v is None else v for v in col.to_pylist()]
            words = list(dict.fromkeys(values))  # first-appearance order
            code_of = {w: i for i, w in enumerate(words)}
            raw = [w.encode() for w in words]
            h.update(np.array([len(w) for w in raw], np.int64).tobytes() + b"".join(raw))
            h.update(np.array([code_of[v] for v in values], np.int32 if version >= 3 else np.int64).tobytes())
        elif pa.types.is_integer(col.type):
            wide = np.int32 if version >= 3 and col.type in NARROW else np.int64
            h.update(np.array([0 if v is None else v for v in col.to_pylist()], wide).tobytes())
        elif pa.types.is_boolean(col.type):
            h.update(np.array([bool(v) for v in col.to_pylist()], np.uint8).tobytes())
        else:
            x = np.array([0.0 if v is None else v for v in col.to_pylist()], np.float64) + 0.0
            x[np.isnan(x)] = np.nan
            h.update(x.tobytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def pt():
    return simulate("path_tracking", 4, 3, seed=7, horizon=9)


def _awkward(ds: TransitionDataset) -> TransitionDataset:
    """``ds`` with nulls (a time, a propensity), a NaN with a payload, a -0.0, and the
    source as a chunked dictionary with an unused and a repeated word."""
    t = ds.table
    n = t.num_rows

    def put(table, name, arr):
        return table.set_column(table.column_names.index(name), name, arr)

    t_ns = t.column(S.T_NS).to_pylist()
    t_ns[2] = None
    bp = t.column(S.BEHAVIOR_PROB).to_pylist()
    bp[5] = None
    e = t.column("obs.e").to_numpy().copy()
    e[1] = np.frombuffer(np.uint64(0x7FF8_0000_0000_0001).tobytes(), np.float64)[0]  # a NaN with a payload
    e[4] = -0.0
    words = np.asarray(ds.column(S.SOURCE)).astype(str)
    k = n // 2
    first = pa.DictionaryArray.from_arrays(pa.array(np.where(words[:k] == "demonstration", 0, 2).astype(np.int32)),
                                           pa.array(["demonstration", "unused", "exploration"]))
    second = pa.DictionaryArray.from_arrays(pa.array(np.where(words[k:] == "demonstration", 1, 0).astype(np.int32)),
                                            pa.array(["exploration", "demonstration", "exploration"]))
    t = put(t, S.T_NS, pa.array(t_ns, pa.int64()))
    t = put(t, S.BEHAVIOR_PROB, pa.array(bp, pa.float64()))
    t = put(t, "obs.e", pa.array(e))
    t = put(t, S.SOURCE, pa.chunked_array([first, second]))
    return TransitionDataset(t, ds.info)


def test_fingerprint_is_its_definition(pt):
    for ds in (pt, _awkward(pt)):
        assert ds.fingerprint() == reference(ds, 3)
        assert ds._fingerprint(2) == reference(ds, 2)
        assert ds.fingerprint() != ds._fingerprint(2) != ds.legacy_fingerprint()


def test_fingerprint_is_the_same_however_the_data_is_chunked_or_written(pt, tmp_path):
    ds = _awkward(pt)
    fp = ds.fingerprint()
    t = ds.table
    for k in (1, 4, 11):
        pieces = TransitionDataset(pa.concat_tables([t.slice(i, k) for i in range(0, t.num_rows, k)]), ds.info)
        assert pieces.table.column(S.STEP).num_chunks > 1
        assert pieces.fingerprint() == fp
    for rows in (5, 9, 1000):
        assert read_dataset(write_dataset(ds, tmp_path / f"d{rows}", rows_per_part=rows)).fingerprint() == fp


def test_changing_one_value_of_any_column_changes_the_fingerprint(pt):
    fp = pt.fingerprint()
    t = pt.table
    row = 5
    for name in _known(pt):
        col = t.column(name).combine_chunks()
        if pa.types.is_dictionary(col.type):
            col = col.cast(col.type.value_type)
        values = col.to_pylist()
        v = values[row]
        values[row] = (not v if isinstance(v, bool) else v + 1 if isinstance(v, int)
                       else float(np.nextafter(v, np.inf)) if isinstance(v, float) else v + "x")
        changed = t.set_column(t.column_names.index(name), name, pa.array(values, col.type))
        assert TransitionDataset(changed, pt.info).fingerprint() != fp, name
        # a null in place of the value, too
        values[row] = None
        nulled = t.set_column(t.column_names.index(name), name, pa.array(values, col.type))
        if name != S.EPISODE_ID:  # a row needs an episode id
            assert TransitionDataset(nulled, pt.info).fingerprint() != fp, name


def test_large_dictionaries_and_the_small_dictionary_path_agree():
    """A source dictionary of more labels than the first-positions path takes is hashed
    through the hash table; both give the strings' fingerprint."""
    from offline_adp.data.columns import _FEW_LABELS

    ds = simulate("car_on_hill", 3, 3, seed=2, horizon=30)
    n = len(ds)
    for n_labels in (3, _FEW_LABELS + 5):
        labels = np.array([f"label-{i}" for i in range(n_labels)])
        idx = (np.arange(n) * 7) % n_labels
        as_text = ds.table.set_column(ds.table.column_names.index(S.SOURCE), S.SOURCE, pa.array(labels[idx]))
        as_dict = ds.table.set_column(ds.table.column_names.index(S.SOURCE), S.SOURCE,
                                      pa.DictionaryArray.from_arrays(pa.array(idx.astype(np.int32)), pa.array(labels)))
        a, b = TransitionDataset(as_text, ds.info), TransitionDataset(as_dict, ds.info)
        assert a.fingerprint() == b.fingerprint() == reference(a, 3)


def test_fingerprints_of_the_earlier_definitions_are_recognised(pt, tmp_path):
    """A dataset or a run that stored a v2 or legacy fingerprint still matches (validates,
    resumes); anything else does not."""
    from offline_adp.data.validate import validate_directory
    from offline_adp.errors import RunDirectoryError
    from offline_adp.runs import fit_run

    out = write_dataset(pt, tmp_path / "d")
    back = read_dataset(out)
    info_file = out / "meta" / "info.json"
    assert json.loads(info_file.read_text())["fingerprint"] == back.fingerprint() == reference(back, 3)
    assert not back.matches_fingerprint(None)
    cases = ((reference(back, 2), True), (back.legacy_fingerprint(), True), ("0" * 64, False))
    for stored, ok in cases:
        assert back.matches_fingerprint(stored) is ok
        info = json.loads(info_file.read_text())
        info["fingerprint"] = stored
        info_file.write_text(json.dumps(info))
        found = validate_directory(out).findings
        assert ("fingerprint_mismatch" not in set(found["check"] if len(found) else ())) is ok
    params = {"n_iterations": 2, "regressor_params": {"n_estimators": 3, "n_jobs": 1}, "random_state": 0}
    run = tmp_path / "run"
    fit_run(out, run, params=params)
    status_file = run / "run.json"
    for stored, ok in cases:
        status = json.loads(status_file.read_text())
        status["dataset_fingerprint"] = stored
        status_file.write_text(json.dumps(status))
        if ok:
            fit_run(out, run, params=params, resume=True)
            assert json.loads(status_file.read_text())["dataset_fingerprint"] == back.fingerprint()
        else:
            with pytest.raises(RunDirectoryError, match="fingerprint"):
                fit_run(out, run, params=params, resume=True)


def test_hash_column_narrow_integers_are_exact():
    """Integers hashed as int32 only where their type holds int32 values: an int64 column
    with values past int32 keeps them (no wrap-around collisions)."""
    from offline_adp.data.columns import hash_column

    def digest(arr):
        h = hashlib.sha256()
        hash_column(h, "c", pa.chunked_array([arr]))
        return h.hexdigest()

    big = pa.array([2**32 + 1, 5], pa.int64())
    small = pa.array([1, 5], pa.int64())
    assert digest(big) != digest(small)
    assert digest(pa.array([1, 5], pa.int32())) == digest(pa.array([1, 5], pa.int16()))
