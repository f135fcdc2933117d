"""LightGBM model text checked before LightGBM parses it (see :mod:`offline_adp.artifacts.checks`
for why every artifact file is untrusted): per tree, array lengths against ``num_leaves``,
children after parents and in range, each node reached once, split features within
``max_feature_idx``, no categorical or linear trees; then LightGBM's own parse, compared
with what the text declares."""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.artifacts.checks import fail

_TREE_ARRAYS = ("split_feature", "threshold", "decision_type", "left_child", "right_child", "leaf_value")


def _ints(text: str, where: str, member: str) -> np.ndarray:
    try:
        return np.array([int(x) for x in text.split()], dtype=np.int64)
    except (ValueError, OverflowError):
        raise fail(where, member, f"not a list of integers: {text[:60]!r}") from None


def _floats(text: str, where: str, member: str) -> np.ndarray:
    try:
        return np.array([float(x) for x in text.split()], dtype=np.float64)
    except ValueError:
        raise fail(where, member, f"not a list of numbers: {text[:60]!r}") from None


def check_lightgbm_text(model: Any, where: str, member: str = "lightgbm model", n_features: int | None = None) -> str:
    """Check LightGBM model text before and after LightGBM parses it.

    Returns the text to hand to LightGBM (our checked copy, without ``tree_sizes``, so
    LightGBM parses the trees one after the other instead of trusting stored offsets).

    Raises
    ------
    ArtifactError
        Anything outside what a plain regression booster trained by us can contain.
    """
    if not isinstance(model, str):
        raise fail(where, member, f"model text expected, found {type(model).__name__}")
    head, sep, _ = model.partition("\nTree=")
    if not model.startswith("tree\n"):
        raise fail(where, member, "not LightGBM model text (no 'tree' header)")
    header: dict[str, str] = {}
    for line in head.splitlines()[1:]:
        k, eq, v = line.partition("=")
        if eq:
            header[k.strip()] = v.strip()
    try:
        n_feat = int(header.get("max_feature_idx", "")) + 1
        n_class = int(header.get("num_class", ""))
        per_iter = int(header.get("num_tree_per_iteration", "1"))
    except ValueError:
        raise fail(where, member, "header lacks integer max_feature_idx / num_class") from None
    if not 1 <= n_feat <= len(model) or n_class != 1 or per_iter != 1:
        raise fail(where, member,
                    f"max_feature_idx {n_feat - 1}, num_class {n_class}: a single-output regression "
                    "booster is required")
    if n_features is not None and n_feat != n_features:
        raise fail(where, member, f"model has {n_feat} features, the artifact declares {n_features}")
    body, end_sep, tail = model.partition("\nend of trees")
    if not end_sep:
        raise fail(where, member, "model text is truncated (no 'end of trees')")
    blocks = body.split("\nTree=")[1:] if sep else []
    for b in blocks:
        lines = b.splitlines()
        tname = f"{member} Tree={lines[0].strip() if lines else '?'}"
        kv: dict[str, str] = {}
        for line in lines[1:]:
            k, eq, v = line.partition("=")
            if eq:
                kv[k.strip()] = v.strip()
        try:
            nl = int(kv.get("num_leaves", ""))
            ncat = int(kv.get("num_cat", "0"))
            linear = int(kv.get("is_linear", "0"))
        except ValueError:
            raise fail(where, tname, "num_leaves / num_cat / is_linear are not integers") from None
        if not 1 <= nl <= len(model):
            raise fail(where, tname, f"num_leaves {nl} out of range")
        if ncat != 0 or linear != 0:
            raise fail(where, tname, "categorical or linear trees are not accepted in artifacts")
        leaf_value = _floats(kv.get("leaf_value", ""), where, tname + " leaf_value")
        if len(leaf_value) != nl or np.any(np.isnan(leaf_value)):
            raise fail(where, tname, f"leaf_value has {len(leaf_value)} entries for {nl} leaves, or NaN")
        if nl == 1:
            continue
        ni = nl - 1
        sf = _ints(kv.get("split_feature", ""), where, tname + " split_feature")
        th = _floats(kv.get("threshold", ""), where, tname + " threshold")
        dt = _ints(kv.get("decision_type", ""), where, tname + " decision_type")
        lc = _ints(kv.get("left_child", ""), where, tname + " left_child")
        rc = _ints(kv.get("right_child", ""), where, tname + " right_child")
        for nm, arr in (("split_feature", sf), ("threshold", th), ("decision_type", dt), ("left_child", lc),
                        ("right_child", rc)):
            if len(arr) != ni:
                raise fail(where, f"{tname} {nm}", f"{len(arr)} entries for {ni} internal nodes")
        if np.any((sf < 0) | (sf >= n_feat)):
            raise fail(where, f"{tname} split_feature", f"feature index outside [0, {n_feat})")
        if not np.all(np.isfinite(th)):
            raise fail(where, f"{tname} threshold", "non-finite threshold")
        if np.any((dt < 0) | (dt > 255) | (dt & 1)):
            raise fail(where, f"{tname} decision_type", "categorical or unknown decision type")
        idx = np.arange(ni)
        reached_inner = np.zeros(ni, np.int64)
        reached_leaf = np.zeros(nl, np.int64)
        for nm, ch in (("left_child", lc), ("right_child", rc)):
            inner = ch >= 0
            if np.any(inner & ((ch <= idx) | (ch >= ni))) or np.any(~inner & (~ch >= nl)):
                raise fail(where, f"{tname} {nm}", "child index out of range (children follow their parent)")
            reached_inner += np.bincount(ch[inner], minlength=ni)
            reached_leaf += np.bincount(~ch[~inner], minlength=nl)
        if reached_inner[0] != 0 or np.any(reached_inner[1:] != 1) or np.any(reached_leaf != 1):
            raise fail(where, f"{tname} left_child", "not a tree (a node or leaf is reached other than once)")
    # our checked copy: no stored byte offsets for LightGBM to trust
    text = "\n".join(line for line in model.split("\n") if not line.startswith("tree_sizes="))
    try:
        import lightgbm as lgb

        booster = lgb.Booster(model_str=text)
    except Exception as exc:  # LightGBMError and friends: the text is not a model
        raise fail(where, member,
                    "LightGBM cannot parse the model "
                    f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    if booster.num_feature() != n_feat or booster.num_trees() != len(blocks):
        raise fail(where, member, f"LightGBM read {booster.num_trees()} trees over {booster.num_feature()} features, "
                                   f"the text declares {len(blocks)} over {n_feat}")
    return text
