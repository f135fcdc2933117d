"""Column encodings of a dataset table (episode ids as dictionary codes, without a hash
where the ids arrive sorted) and the block-wise hashing behind its fingerprint; used by
:class:`offline_adp.data.dataset.TransitionDataset` and the Parquet ingestion."""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc


def encode_strings(col: pa.Array | pa.ChunkedArray) -> pa.DictionaryArray:
    """Dictionary-encode a string column into one array whose codes follow first appearance.

    Chunks are combined first: encoding chunk by chunk would give each chunk its own
    dictionary and codes that disagree across chunks.
    """
    if isinstance(col, pa.ChunkedArray):
        col = col.combine_chunks()
    return pc.dictionary_encode(col)


def bool_values(col: pa.Array | pa.ChunkedArray, null: bool = False) -> np.ndarray:
    """A boolean column as a numpy bool array, each null as ``null``: what
    ``np.asarray(col.fill_null(null).to_numpy(zero_copy_only=False), dtype=bool)`` gives,
    unpacked from the bit-packed buffers in one vectorised pass per chunk (Arrow's own
    conversion goes value by value: 2 ms against 0.15 ms for 2M values)."""
    chunks = [c for c in (col.chunks if isinstance(col, pa.ChunkedArray) else [col]) if len(c)]
    if len(chunks) == 1 and not chunks[0].null_count:  # the unpacked bits themselves: no second copy
        return _bits(chunks[0].buffers()[1], chunks[0].offset, len(chunks[0]))
    out = np.empty(len(col), bool)
    at = 0
    for c in chunks:
        n = len(c)
        if n:
            validity, data = c.buffers()[:2]
            out[at:at + n] = _bits(data, c.offset, n)
            if c.null_count:
                out[at:at + n][~_bits(validity, c.offset, n)] = null
        at += n
    return out


def _bits(buf: pa.Buffer, offset: int, n: int) -> np.ndarray:
    """Bits ``offset`` to ``offset + n`` of an Arrow bitmap (least significant bit first)."""
    first = offset // 8
    raw = np.frombuffer(buf, np.uint8, count=(offset + n + 7) // 8 - first, offset=first)
    return np.unpackbits(raw, count=offset % 8 + n, bitorder="little")[offset % 8:].view(bool)


def episode_sums(codes: np.ndarray, starts: np.ndarray, x: np.ndarray, n_episodes: int,
                 block: int = 1 << 16) -> np.ndarray:
    """``np.bincount(codes, weights=x, minlength=n_episodes)``, bit for bit, for rows in
    episode order (episode ``k`` is rows ``starts[k]`` to ``starts[k + 1]``): numpy copies
    read-only weights (a column viewed from Arrow) whole before summing, here whole episodes
    of about ``block`` rows at a time are copied into a reused buffer instead. Each episode
    is summed in one call, from 0.0 in row order, as bincount does."""
    n = len(codes)
    if not (len(starts) == n_episodes and n and np.array_equal(codes[starts], np.arange(n_episodes))):
        return np.bincount(codes, weights=x, minlength=n_episodes)
    out = np.empty(n_episodes)
    buf = np.empty(min(n, block))
    e = 0
    while e < n_episodes:
        lo = int(starts[e])
        if n - lo <= block:
            e2, hi = n_episodes, n
        else:  # the episodes starting within the block (at least one)
            e2 = max(e + 1, int(np.searchsorted(starts, lo + block, side="right")) - 1)
            hi = int(starts[e2]) if e2 < n_episodes else n
        w = buf[:hi - lo] if hi - lo <= len(buf) else np.empty(hi - lo)
        np.copyto(w, x[lo:hi])
        out[e:e2] = np.bincount(codes[lo:hi] - e, weights=w, minlength=e2 - e)
        e = e2
    return out


_HASH_BLOCK = 1 << 16  # values per conversion block: temporaries stay in cache, never a column copy


#: integer types whose every value is an int32: hashed as int32 by :func:`hash_column`
#: (``narrow``), others as int64
_NARROW_INTS = (pa.int8(), pa.int16(), pa.int32(), pa.uint8(), pa.uint16())


def hash_column(h: Any, name: str, col: pa.ChunkedArray, encoding: tuple[np.ndarray, np.ndarray] | None = None,
                *, narrow: bool = True) -> None:
    """Feed one column's content into ``h``, the same for any chunking of the same values.

    ``encoding`` (codes in first-appearance order, distinct values) may be given for a
    string column without nulls whose encoding is already known (the episode ids). The
    bytes fed are exactly those of the definition in :meth:`TransitionDataset.fingerprint`;
    they are produced chunk by chunk and block by block, without copying whole columns.
    With ``narrow`` (fingerprint v3), string codes are fed as int32 (as int64 only past
    2**31 - 1 distinct values) and integers of a type whose values all fit int32 (int8 to
    int32, uint8, uint16) as int32; without it (v2), both as int64.
    """
    n = len(col)
    name_b = name.encode()
    h.update(len(name_b).to_bytes(8, "little") + name_b + n.to_bytes(8, "little"))
    is_dict = pa.types.is_dictionary(col.type)
    is_str = is_dict or pa.types.is_string(col.type) or pa.types.is_large_string(col.type)
    if is_str and not col.null_count and n:
        codes, mapping, words_arr = (*encoding[:1], None,
                                     encoding[1]) if encoding is not None else _first_appearance_encoding(col)
        h.update(bytes((n + 7) // 8))  # the packed null mask: no nulls
        words = [str(w).encode() for w in words_arr]  # one per distinct value
        h.update(np.asarray([len(w) for w in words], np.int64).tobytes() + b"".join(words))
        code_type = np.int32 if narrow and len(words) <= np.iinfo(np.int32).max else np.int64
        if mapping is not None and mapping.dtype != code_type:
            mapping = mapping.astype(code_type)
        if mapping is None and codes.dtype == code_type:
            h.update(np.ascontiguousarray(codes))
            return
        for lo in range(0, n, _HASH_BLOCK):  # codes as int32 (v2: int64), block by block
            block = codes[lo:lo + _HASH_BLOCK]
            h.update(mapping[block] if mapping is not None else block.astype(code_type))
        return
    if is_dict:
        col = col.cast(col.type.value_type)
    # the packed null mask (all zero bytes without nulls: no mask of n booleans to pack)
    h.update(np.packbits(np.asarray(pc.is_null(col), dtype=bool)).tobytes() if col.null_count else bytes((n + 7) // 8))
    if pa.types.is_string(col.type) or pa.types.is_large_string(col.type):
        enc = encode_strings(col.cast(pa.large_string()).fill_null(""))
        words = [w.encode() for w in enc.dictionary.to_pylist()]  # one per distinct value
        h.update(np.asarray([len(w) for w in words], np.int64).tobytes() + b"".join(words))
        code_type = np.int32 if narrow and len(words) <= np.iinfo(np.int32).max else np.int64
        h.update(enc.indices.to_numpy(zero_copy_only=False).astype(code_type).tobytes())
        return
    kind = ("b" if pa.types.is_boolean(col.type) else "i" if pa.types.is_integer(col.type)
            else "f" if pa.types.is_floating(col.type) else None)
    if kind is None:
        h.update(str(col.type).encode())  # any other type: its values in Python form
        h.update(repr(col.to_pylist()).encode())
        return
    if col.null_count:
        col = col.fill_null(False if kind == "b" else 0 if kind == "i" else 0.0)
    int_type = np.int32 if narrow and col.type in _NARROW_INTS else np.int64
    buf = np.empty(min(n, _HASH_BLOCK), int_type if kind == "i" else np.float64)  # reused by every block
    for chunk in col.chunks:
        if kind == "b":  # no nulls left: the values as bytes
            h.update(bool_values(chunk).view(np.uint8))
            continue
        arr = chunk.to_numpy(zero_copy_only=False)  # no nulls left: a view
        if kind == "i" and arr.dtype == int_type:
            h.update(np.ascontiguousarray(arr))
        else:
            for lo in range(0, len(arr), _HASH_BLOCK):
                block = arr[lo:lo + _HASH_BLOCK]
                b = buf[:len(block)]
                if kind == "i":
                    np.copyto(b, block, casting="unsafe")  # as astype(int_type): exact
                else:
                    np.add(block, 0.0, out=b, casting="unsafe")  # -0.0 and 0.0 are the same value
                    with np.errstate(invalid="ignore", over="ignore"):
                        some_nan = np.isnan(np.add.reduce(b))  # a NaN (or inf - inf) in the block
                    if some_nan:
                        b[np.isnan(b)] = np.nan  # one NaN whatever its payload
                h.update(b)


_FEW_LABELS = 64  # a dictionary this small is re-encoded by first positions, not hashing


def _first_appearance_encoding(col: pa.ChunkedArray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """What ``encode_strings`` of a string or dictionary column without nulls gives, as
    ``(indices, mapping, words)``: the codes (first-appearance order) are
    ``mapping[indices]`` (``indices`` when ``mapping`` is None), ``words`` the distinct
    values. A dictionary column is re-encoded through its integer indices, never
    materialising its strings or a second column of codes."""
    if not pa.types.is_dictionary(col.type):
        enc = encode_strings(col)
        return enc.indices.to_numpy(zero_copy_only=False), None, np.asarray(enc.dictionary.to_pylist(), dtype=object)
    col = col.unify_dictionaries()
    chunks = [c for c in col.chunks if len(c)]
    dictionary = chunks[0].dictionary
    if len(dictionary) <= _FEW_LABELS:  # e.g. source labels: no hash table over the rows
        # one chunk: its indices as they are (combining copies even one chunk)
        indices = chunks[0].indices if len(chunks) == 1 else pa.chunked_array([c.indices for c in chunks]
                                                                             ).combine_chunks()
        arr = indices.to_numpy(zero_copy_only=False)
        # the indices used, ascending: Arrow's hash kernel (np.bincount copied the read-only
        # indices whole, widened to int64: 16 MB at 2M rows)
        present = np.sort(pc.unique(indices).to_numpy(zero_copy_only=False).astype(np.int64))
        # where each index first occurs (a scan that stops there; once per index used)
        first = [pc.index(indices, pa.scalar(int(i), indices.type)).as_py() for i in present]
        order = present[np.argsort(first)]  # the indices used, in first-appearance order
        by_value = pc.dictionary_encode(dictionary.take(pa.array(order)).cast(pa.large_string()))
        mapping = np.zeros(len(dictionary), np.int64)
        mapping[order] = by_value.indices.to_numpy(zero_copy_only=False)
        return arr, mapping, np.asarray(by_value.dictionary.to_pylist(), dtype=object)
    by_index = pc.dictionary_encode(pa.chunked_array([c.indices for c in chunks]).combine_chunks())
    values = dictionary.take(by_index.dictionary)  # per distinct index, in first-appearance order
    by_value = pc.dictionary_encode(values.cast(pa.large_string()))  # indices with equal values merge
    mapping = by_value.indices.to_numpy(zero_copy_only=False).astype(np.int64)
    return (
        by_index.indices.to_numpy(zero_copy_only=False),
        mapping,
        np.asarray(by_value.dictionary.to_pylist(), dtype=object),
    )


def sorted_encoding(ids: pa.Array | pa.ChunkedArray, order: np.ndarray) -> pa.DictionaryArray | None:
    """The encoding of ``ids`` if rows are already ordered by (id, order), else None.

    Checked without sorting or hashing: each id is compared with the next (chunk by
    chunk, no copy); ids in order make first-appearance order lexical order, so the
    codes are the running count of id changes and the dictionary the id at each change.
    Then ``order`` must not decrease within an id.
    """
    chunked = ids if isinstance(ids, pa.ChunkedArray) else pa.chunked_array([ids])
    n = len(chunked)
    if n == 0 or chunked.null_count:
        return _sorted_encoding_hashed(ids, order)
    changes = []
    prev: pa.Scalar | None = None
    for c in chunked.chunks:
        if not len(c):
            continue
        if prev is not None:
            a, b = prev.as_py(), c[0].as_py()
            if (b.encode() if isinstance(b, str) else b) < (a.encode() if isinstance(a, str) else a):
                return None
            changes.append(np.array([a != b]))
        if len(c) > 1:
            head, tail = c.slice(0, len(c) - 1), c.slice(1)
            change = bool_values(pc.not_equal(tail, head))  # unpacked in one pass (no nulls here)
            at = pa.array(np.flatnonzero(change))  # ids out of order differ: compared only where they change
            if len(at) and pc.any(pc.less(tail.take(at), head.take(at))).as_py():
                return None
            changes.append(change)
        prev = c[len(c) - 1]
    first = np.concatenate([np.ones(1, bool), *changes])
    del changes
    starts = np.flatnonzero(first)
    # order decreases only where an id starts (rows where it decreases are few: compare there)
    if not first[np.flatnonzero(order[1:] < order[:-1]) + 1].all():
        return None
    dictionary = _take_chunkwise(chunked, starts)
    if pa.types.is_large_string(dictionary.type):
        dictionary = dictionary.cast(pa.string())
    codes = np.repeat(np.arange(len(starts), dtype=np.int32), np.diff(np.r_[starts, n]))  # cumsum over bools is slower
    return pa.DictionaryArray.from_arrays(pa.array(codes), dictionary)


def _take_chunkwise(col: pa.ChunkedArray, idx: np.ndarray) -> pa.Array:
    """``col.take(idx).combine_chunks()`` for sorted ``idx``, taken chunk by chunk: Arrow's
    take on a chunked string column first concatenates every chunk (a copy of the whole
    column's text, e.g. 22 MiB of episode ids at 2M rows, to pick one id per episode)."""
    if col.num_chunks == 1:
        return col.chunk(0).take(pa.array(idx))
    bounds = np.cumsum([0, *(len(c) for c in col.chunks)])
    cut = np.searchsorted(idx, bounds)
    parts = [c.take(pa.array(idx[cut[k]:cut[k + 1]] - bounds[k])) for k, c in enumerate(col.chunks)]
    return pa.concat_arrays(parts)


def _sorted_encoding_hashed(ids: pa.Array | pa.ChunkedArray, order: np.ndarray) -> pa.DictionaryArray | None:
    enc = encode_strings(ids)
    dictionary = enc.dictionary
    if len(dictionary) > 1 and not bool(pc.all(pc.less(dictionary[:-1], dictionary[1:])).as_py()):
        return None
    codes = enc.indices.to_numpy(zero_copy_only=False)
    if (codes[1:] < codes[:-1]).any():
        return None
    same = codes[1:] == codes[:-1]
    return None if (same & (order[1:] < order[:-1])).any() else enc
