"""Checks that make a saved artifact safe to use before anything is built from it.

A run directory may come from someone else, so every artifact file is untrusted input.
scikit-learn's compiled tree code and LightGBM's C++ predictor index memory with the
numbers they are given and do not check them: an out-of-range child or feature index
reads outside the arrays (a crash, or silently wrong actions), a cycle loops forever,
and a header that declares a huge array allocates it. Everything here is checked with
vectorised numpy before those libraries see it:

- :func:`check_npz` - the ``.npz`` container: member names from our key scheme only,
  plain numeric/bool/string dtypes (never objects), at most :data:`MAX_MEMBERS` members,
  and every member's declared size bounded by the bytes actually stored (an
  uncompressed member, which is what we write) or by :data:`MAX_EXPANSION` times its
  compressed size, and in total by :data:`MAX_EXPANSION` times the file size - so a
  1 MB file can never ask for gigabytes.
- :func:`check_tree_arrays` - a :class:`~offline_adp.trees.ensemble.TreeEnsemble` as
  arrays: 1-D, equal lengths, integer/float dtypes; roots strictly increasing from 0;
  every child inside its own tree and after its parent (this is how scikit-learn numbers
  nodes, and it rules out cycles); every non-root node reached exactly once (so all
  nodes are reachable from the root and the structure is a tree); leaves have no
  children; split features ``>= 0`` and below the declared width; thresholds finite.
- :func:`check_compact_tree_arrays` - the same ensemble in the compact layout of
  artifact format 2 (leaf flags in depth-first order, split features and thresholds,
  leaf values or a value table and codes): the flags must be full binary trees in
  depth-first order at the roots (then the children they give are in range), one
  feature and threshold per split, one value per leaf, every code inside its table.
- :func:`~offline_adp.artifacts.lightgbm_text.check_lightgbm_text` (its own module) - LightGBM
  model text, parsed by us first (the same rules per tree), then by LightGBM.

Every failure is one :class:`~offline_adp.errors.ArtifactError` naming the file and
the member (array key or model) at fault.
"""

from __future__ import annotations

import re
import tokenize
import zipfile
import zlib
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.errors import ArtifactError, InvalidArgumentError

#: Most array members an artifact may hold.
MAX_MEMBERS = 100_000
#: Bound on (declared bytes) / (stored bytes) for a compressed member and for the file.
MAX_EXPANSION = 64
#: Member names: our dotted keys (``q.m0.left``, ``p.c1.q.t2.action_features``...).
MEMBER_NAME = re.compile(r"^[A-Za-z0-9_]+(\.[A-Za-z0-9_]+)*\.npy$")
#: dtype kinds an artifact array may have: bool, signed/unsigned integer, float, unicode.
ALLOWED_KINDS = frozenset("biufU")
#: What reading a damaged zip member can raise (CRC, inflate, unsupported flags, encryption).
ZIP_ERRORS = (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError, RuntimeError,
              OverflowError, KeyError, TypeError, SyntaxError, tokenize.TokenError)
#: Most nodes / leaves / features a single tree or model may declare.
MAX_NODES = 1 << 31
#: Widest input a saved model may declare (features plus action features).
#: Most tree nodes a compact-layout file may declare per byte of file (``leaf_bits``: one bit a
#: node). Expanding a node for lookups takes ~140 bytes, so 2 nodes a byte keeps a crafted
#: file's allocations within ~300x its size; our files hold ~0.3 nodes a byte (a gymnasium
#: fit: 5.0M nodes in 15.1 MB).
MAX_NODES_PER_FILE_BYTE = 2
MAX_WIDTH = 1_000_000
#: Most float64 entries a loader may allocate to probe a model (actions x rows x width):
#: a declared width is checked against this before any array is built from it.
MAX_PROBE_ENTRIES = 20_000_000


def plain_dtype(dtype: np.dtype) -> bool:
    """Bool, integer, float or string; or a record of those (lookup-table rows), never objects."""
    if dtype.hasobject or dtype.subdtype is not None:
        return False
    if dtype.fields is not None:
        return 0 < len(dtype.fields) <= 10_000 and all(f[0].fields is None and f[0].kind in "biuf"
                                                       and f[0].subdtype is None
                                                       for f in dtype.fields.values())
    return dtype.kind in ALLOWED_KINDS


def fail(where: str, member: str, message: str) -> ArtifactError:
    """The error naming the file (``where``) and the member (array key or model) at fault."""
    return ArtifactError(f"{where}: {member}: {message}")


# ----------------------------------------------------------------------------- npz
def check_npz(path: str | PathLike[str], *, max_expansion: int = MAX_EXPANSION,
              name_pattern: re.Pattern[str] = MEMBER_NAME) -> dict[str, tuple[np.dtype, tuple[int, ...]]]:
    """Check an ``.npz`` file's members without loading them (``name_pattern``: the
    member names allowed, by default our artifact keys).

    Returns
    -------
    dict
        ``{member key: (dtype, shape)}`` as declared in each member's header.

    Raises
    ------
    ArtifactError
        Not a zip file, a member with a name outside our key scheme, an object or other
        non-plain dtype, a header that declares more bytes than are stored, too many
        members, or declared sizes out of proportion to the file size.
    """
    p = Path(path)
    where = str(p)
    try:
        size = p.stat().st_size
        zf = zipfile.ZipFile(p)
    except FileNotFoundError:
        raise
    except ZIP_ERRORS as exc:
        raise ArtifactError(f"{where}: not a readable .npz archive ({exc})") from None
    out: dict[str, tuple[np.dtype, tuple[int, ...]]] = {}
    total = 0
    with zf:
        infos = zf.infolist()
        if len(infos) > MAX_MEMBERS:
            raise ArtifactError(f"{where}: {len(infos)} members, at most {MAX_MEMBERS} allowed")
        for zi in infos:
            name = zi.filename
            if not name_pattern.match(name):
                raise fail(where, repr(name), "member name is not an artifact array key")
            key = name[:-4]
            if key in out:
                raise fail(where, key, "member appears twice")
            if zi.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED) or zi.flag_bits & 0x61:
                raise fail(where, key,
                            f"unsupported zip member (compression {zi.compress_type}, flags {zi.flag_bits:#x})")
            if zi.compress_type == zipfile.ZIP_STORED and zi.file_size != zi.compress_size:
                raise fail(where, key, "stored member with inconsistent sizes")
            if zi.file_size > max_expansion * max(zi.compress_size, 1) + 4096:
                raise fail(where, key, f"declares {zi.file_size} bytes from {zi.compress_size} compressed bytes")
            total += zi.file_size
            if total > max_expansion * max(size, 1) + (1 << 20):
                raise fail(where, key, f"members declare {total} bytes in a {size}-byte file")
            try:
                with zf.open(zi) as f:
                    version = np.lib.format.read_magic(f)
                    if version == (1, 0):
                        shape, fortran, dtype = np.lib.format.read_array_header_1_0(f, max_header_size=10_000)
                    elif version in ((2, 0), (3, 0)):
                        shape, fortran, dtype = np.lib.format.read_array_header_2_0(f, max_header_size=10_000)
                    else:
                        raise InvalidArgumentError(f"unknown .npy version {version}")
                    header_len = f.tell()
            except ZIP_ERRORS as exc:
                raise fail(where, key, f"unreadable array header ({exc})") from None
            if not plain_dtype(dtype):
                raise fail(where, key, f"dtype {dtype} is not allowed (bool, integer, float or string arrays only)")
            if any((not isinstance(s, int)) or s < 0 for s in shape):
                raise fail(where, key, f"bad shape {shape}")
            nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
            if nbytes + header_len > zi.file_size:
                raise fail(where, key,
                            f"header declares {nbytes} bytes of data but the member stores {zi.file_size - header_len}")
            out[key] = (dtype, tuple(shape))
    return out


def array(arrays: Any, key: str, where: str, *, kinds: str, ndim: int | None = None) -> np.ndarray:
    """``arrays[key]`` as an ndarray, checking it exists and has a dtype kind in ``kinds``."""
    if not isinstance(key, str):
        raise fail(where, repr(key), "array reference is not a string")
    try:
        a = np.asarray(arrays[key])
    except KeyError:
        raise fail(where, key, "array missing from the .npz") from None
    except ZIP_ERRORS as exc:
        raise fail(where, key, f"unreadable array ({exc})") from None
    if a.dtype.kind not in kinds or not plain_dtype(a.dtype):
        raise fail(where, key, f"dtype {a.dtype} where {'/'.join(_KIND_NAMES[k] for k in kinds)} is required")
    if ndim is not None and a.ndim != ndim:
        raise fail(where, key, f"{a.ndim}-D array where {ndim}-D is required (shape {a.shape})")
    return a


_KIND_NAMES = {"b": "bool", "i": "int", "u": "uint", "f": "float", "U": "str", "V": "record"}


# ----------------------------------------------------------------------------- trees
def tree_structure(left: np.ndarray, right: np.ndarray, roots: np.ndarray, where: str, member: str) -> None:
    """Children after parents, inside their tree, each non-root node reached once."""
    n = len(left)
    if len(roots) == 0:
        raise fail(where, member + "roots", "no trees")
    if roots[0] != 0 or np.any(np.diff(roots) <= 0) or roots[-1] >= n:
        raise fail(where, member + "roots", "tree roots must start at 0 and increase strictly within the node arrays")
    tree_of = np.repeat(np.arange(len(roots)), np.diff(np.r_[roots, n]))
    end = np.r_[roots[1:], n][tree_of]  # one past each node's tree
    idx = np.arange(n)
    leaf_l, leaf_r = left < 0, right < 0
    if np.any(leaf_l != leaf_r):
        j = int(np.flatnonzero(leaf_l != leaf_r)[0])
        raise fail(where, member + "left", f"node {j} has exactly one child")
    if np.any(left[leaf_l] != -1) or np.any(right[leaf_r] != -1):
        raise fail(where, member + "left", "leaves must have child index -1")
    inner = ~leaf_l
    for name, ch in (("left", left), ("right", right)):
        bad = inner & ((ch <= idx) | (ch >= end))
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            raise fail(where, member + name,
                        f"node {j}: child {int(ch[j])} outside ({j}, {int(end[j])}) (children follow their parent "
                        "inside its tree)")
    reached = np.bincount(np.r_[left[inner], right[inner]], minlength=n)
    is_root = np.zeros(n, bool)
    is_root[roots] = True
    bad = reached != np.where(is_root, 0, 1)
    if bad.any():
        j = int(np.flatnonzero(bad)[0])
        raise fail(where, member + "left",
                    f"node {j} is reached {int(reached[j])} times (a tree reaches every node exactly once)")


def check_leaf_values(arrays: Any, prefix: str, where: str) -> np.ndarray:
    """The compact layout's leaf values: ``value``, or ``value_table`` indexed by
    ``value_code`` (codes checked against the table before use); all finite."""
    if prefix + "value" in _members(arrays) or prefix + "value_table" not in _members(arrays):
        v = array(arrays, prefix + "value", where, kinds="f", ndim=1).astype(np.float64)
        bad = ~np.isfinite(v)
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            raise fail(where, prefix + "value", f"leaf {j}: value {float(v[j])!r} is not finite")
        return v
    table = array(arrays, prefix + "value_table", where, kinds="f", ndim=1).astype(np.float64)
    code = array(arrays, prefix + "value_code", where, kinds="u", ndim=1)
    if not np.all(np.isfinite(table)):
        raise fail(where, prefix + "value_table", "a leaf value is not finite")
    if len(code) and int(code.max()) >= len(table):
        raise fail(where, prefix + "value_code", f"code {int(code.max())} outside the {len(table)}-entry value table")
    return table[code]


def _members(arrays: Any) -> Any:
    files = getattr(arrays, "files", None)  # an opened .npz lists its members without reading them
    return set(files) if files is not None else arrays


def check_node_budget(members: dict[str, tuple[np.dtype, tuple[int, ...]]], file_size: int, where: str) -> None:
    """Refuse a file whose compact tree structures (``*leaf_bits`` members, one bit a node)
    declare more than :data:`MAX_NODES_PER_FILE_BYTE` nodes per byte of the file (plus a
    small floor), before anything is expanded: deflate lets a small file declare millions
    of nodes that each cost ~140 bytes to look up."""
    nodes = sum(8 * int(np.prod(shape)) for key, (_, shape) in members.items() if key.endswith("leaf_bits"))
    if nodes > MAX_NODES_PER_FILE_BYTE * file_size + 65_536:
        raise ArtifactError(f"{where}: declares {nodes} tree nodes in a file of {file_size} bytes, more than "
                            f"{MAX_NODES_PER_FILE_BYTE} a byte: out of proportion (a crafted or damaged file)")


def check_compact_tree_arrays(arrays: Any, prefix: str, where: str, n_features: int | None = None,
                              structure_prefix: str | None = None) -> dict[str, np.ndarray]:
    """Check a tree ensemble stored in the compact layout
    (:meth:`~offline_adp.trees.ensemble.TreeEnsemble.to_arrays`): the leaf flags, cut at
    the roots, must each be a full binary tree in depth-first order (then the children
    they give are inside their tree and after their parent, every node reached once);
    one feature and threshold per split, one value per leaf; as :func:`check_tree_arrays`
    for the rest. ``structure_prefix``: where the structure is stored when another
    ensemble's (shared structure), else ``prefix``. Returns the per-node arrays
    (:mod:`offline_adp.artifacts.tree_tables` decodes the same members, checked here by
    :func:`compact_tree_members`, into per-tree lookups without them)."""
    from offline_adp.trees.ensemble import expand_compact

    is_leaf, roots, feature, threshold, values = compact_tree_members(arrays, prefix, where, n_features,
                                                                      structure_prefix)
    sp = prefix if structure_prefix is None else structure_prefix
    out = expand_compact(is_leaf, roots, feature.astype(np.int64), threshold.astype(np.float64), values)
    tree_structure(out["left"], out["right"], out["roots"], where, sp)  # by construction; checked all the same
    return out


def compact_tree_members(arrays: Any, prefix: str, where: str, n_features: int | None = None,
                         structure_prefix: str | None = None) -> tuple[np.ndarray, ...]:
    """The checked members of a compact-layout ensemble (see
    :func:`check_compact_tree_arrays`): ``(is_leaf, roots, feature, threshold, values)``,
    the leaf flags in depth-first order (bool, one a node; binary trees at ``roots``,
    int64), the splits' features (as stored: unsigned or >= 0, below ``n_features``) and
    finite thresholds (as stored, a long double as float64), the leaves' finite values (float64)."""
    from offline_adp.trees.ensemble import preorder_valid

    sp = prefix if structure_prefix is None else structure_prefix
    bits = array(arrays, sp + "leaf_bits", where, kinds="u", ndim=1)
    roots = array(arrays, sp + "roots", where, kinds="iu", ndim=1).astype(np.int64)
    feature = array(arrays, sp + "feature", where, kinds="iu", ndim=1)
    threshold = array(arrays, sp + "threshold", where, kinds="f", ndim=1)
    if len(threshold) != len(feature):
        raise fail(where, sp + "threshold", f"{len(threshold)} thresholds for {len(feature)} split features")
    values = check_leaf_values(arrays, prefix, where)
    n = len(feature) + len(values)
    if bits.dtype != np.uint8 or len(bits) != (n + 7) // 8:
        raise fail(where, sp + "leaf_bits", f"{len(bits)} {bits.dtype} entries where {n} nodes "
                                              f"({len(feature)} splits, {len(values)} leaves) need "
                                              f"{(n + 7) // 8} bytes")
    if n == 0 or n >= MAX_NODES:
        raise fail(where, sp + "leaf_bits", f"{n} nodes")
    flags = np.unpackbits(bits)
    if flags[n:].any():
        raise fail(where, sp + "leaf_bits", "padding bits after the last node are set")
    is_leaf = flags[:n].view(bool)  # 0/1 bytes: the flags as booleans, not copied
    if int(is_leaf.sum()) != len(values):
        raise fail(where, sp + "leaf_bits", f"{int(is_leaf.sum())} leaves flagged, {len(values)} leaf values stored")
    if len(roots) == 0 or len(roots) > n or roots[0] != 0 or np.any(np.diff(roots) <= 0) or roots[-1] >= n:
        raise fail(where, sp + "roots", "tree roots must start at 0 and increase strictly within the nodes")
    if not preorder_valid(is_leaf, roots):
        raise fail(where, sp + "leaf_bits", "the leaf flags are not binary trees in depth-first order at these roots")
    if len(feature):
        top = int(feature.max())
        if feature.dtype.kind == "i" and int(feature.min()) < 0:
            raise fail(where, sp + "feature", f"negative split feature {int(feature.min())}")
        if n_features is not None and top >= n_features:
            raise fail(where, sp + "feature", f"split feature {top} outside the declared width {n_features}")
        if top >= MAX_NODES:
            raise fail(where, sp + "feature", f"split feature {top} is implausibly large")
    if threshold.dtype.itemsize > 8:  # a long double: finite here may be infinite as the float64 every reader uses
        with np.errstate(over="ignore"):
            threshold = threshold.astype(np.float64)
    if not np.all(np.isfinite(threshold)):
        raise fail(where, sp + "threshold", "non-finite split threshold")
    return is_leaf, roots, feature, threshold, values


def check_tree_arrays(arrays: Any, prefix: str, where: str, n_features: int | None = None,
                      structure_prefix: str | None = None) -> dict[str, np.ndarray]:
    """Check the arrays of a :class:`~offline_adp.trees.ensemble.TreeEnsemble` stored under ``prefix``.

    Either layout: the compact one (``leaf_bits`` present,
    :func:`check_compact_tree_arrays`) or per-node arrays (artifact version 1), checked
    here.

    Parameters
    ----------
    arrays : mapping
        The opened ``.npz``.
    prefix : str
        Key prefix (``"q.m0."``).
    where : str
        The file, for messages.
    n_features : int, optional
        Declared input width; split features must be below it.

    Returns
    -------
    dict
        The arrays, converted to the dtypes :class:`TreeEnsemble` uses.
    """
    if (structure_prefix or prefix) + "leaf_bits" in _members(arrays):
        return check_compact_tree_arrays(arrays, prefix, where, n_features, structure_prefix)
    a = {k: array(arrays, prefix + k, where, kinds="iu" if k in ("left", "right", "feature", "roots") else "f", ndim=1)
         for k in ("left", "right", "feature", "threshold", "value", "roots")}
    n = len(a["left"])
    for k in ("right", "feature", "threshold", "value"):
        if len(a[k]) != n:
            raise fail(where, prefix + k, f"{len(a[k])} entries where the tree has {n} nodes")
    if n == 0 or n >= MAX_NODES:
        raise fail(where, prefix + "left", f"{n} nodes")
    out = {k: v.astype(np.int64) if v.dtype.kind in "iu" else v.astype(np.float64) for k, v in a.items()}
    if a["left"].dtype.kind == "u" or a["right"].dtype.kind == "u":
        raise fail(where, prefix + "left", "child indices must be signed (leaves are -1)")
    tree_structure(out["left"], out["right"], out["roots"], where, prefix)
    inner = out["left"] >= 0
    f = out["feature"][inner]
    if len(f) and f.min() < 0:
        raise fail(where, prefix + "feature", f"negative split feature {int(f.min())}")
    if n_features is not None and len(f) and f.max() >= n_features:
        raise fail(where, prefix + "feature", f"split feature {int(f.max())} outside the declared width {n_features}")
    if len(f) and f.max() >= MAX_NODES:
        raise fail(where, prefix + "feature", f"split feature {int(f.max())} is implausibly large")
    if not np.all(np.isfinite(out["threshold"][inner])):
        raise fail(where, prefix + "threshold", "non-finite split threshold")
    bad = ~np.isfinite(out["value"][~inner])
    if bad.any():
        j = int(np.flatnonzero(~inner)[np.flatnonzero(bad)[0]])
        raise fail(where, prefix + "value", f"node {j}: leaf value {float(out['value'][j])!r} is not finite")
    return out


# ----------------------------------------------------------------------------- LightGBM
def check_int(value: Any, where: str, member: str, lo: int = 0, hi: int = MAX_NODES) -> int:
    """An integer from the JSON in [lo, hi]."""
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise fail(where, member, f"expected an integer in [{lo}, {hi}], found {value!r}")
    return value


__all__ = ["MAX_NODES_PER_FILE_BYTE", "check_node_budget", "compact_tree_members", "tree_structure", "MAX_WIDTH",
           "MAX_PROBE_ENTRIES", "check_npz", "check_tree_arrays", "check_compact_tree_arrays", "check_leaf_values",
           "check_int", "array", "MAX_EXPANSION", "MAX_MEMBERS"]
