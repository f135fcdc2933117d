"""Artifact files: ``<stem>.json`` + ``<stem>.npz`` written and read back with every member
checked (:mod:`offline_adp.artifacts.checks`), the format versions, and the sha256 of a
model directory's files that a run records and loading checks."""

from __future__ import annotations

import functools
import importlib
import json
import warnings
import zipfile
import zlib
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp._version import __version__
from offline_adp.artifacts import checks as C
from offline_adp.errors import ArtifactError, FormatVersionWarning

#: The artifact format written: "2" stores tree ensembles in the compact layout
#: (:meth:`~offline_adp.trees.ensemble.TreeEnsemble.to_arrays`) in a compressed ``.npz``;
#: "1" (per-node arrays) is still read.
ARTIFACT_VERSION = "2"
#: The artifact formats this version reads.
READABLE_VERSIONS = ("1", "2")


def versions() -> dict[str, str]:
    """Versions of the package and the libraries whose models we store (the libraries'
    from their installed metadata: reading a model's versions imports neither)."""
    return {"offline_adp": __version__, "numpy": np.__version__, **_library_versions()}


@functools.cache
def _library_versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for dist, module in (("scikit-learn", "sklearn"), ("lightgbm", "lightgbm")):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:  # not installed as a distribution (a source tree on the path)
            out[dist] = importlib.import_module(module).__version__
    return out


def _write(directory: str | PathLike[str], stem: str, payload: dict[str, Any], arrays: dict[str, np.ndarray],
           extra: dict[str, Any] | None, compress: bool = True) -> None:
    """``<stem>.json`` (payload, versions, extra) + ``<stem>.npz`` (arrays, :func:`savez`)
    in ``directory``; ``compress=False``: the arrays stored as they are (a checkpoint:
    written often, read rarely; the reader takes either)."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    savez(d / f"{stem}.npz", arrays, compress)
    spec = {"artifact_version": ARTIFACT_VERSION, "versions": versions(), **payload, **(extra or {})}
    (d / f"{stem}.json").write_text(json.dumps(spec, indent=1))


#: zlib level of the arrays a model stores: level 1 makes a tree model ~1% larger than the
#: default level 6 in ~half the CPU (feature indices: 3% larger, 10x faster).
COMPRESS_LEVEL = 1
#: A member is deflated when the deflated start of it (:data:`SAMPLE_BYTES`) is at most
#: this share of its size; else stored (float32 thresholds, leaf flags: ~95%, for 40% of a
#: model's deflate time).
DEFLATE_BELOW = 0.9
SAMPLE_BYTES = 1 << 16


def savez(path: str | PathLike[str], arrays: dict[str, np.ndarray], compress: bool = True) -> None:
    """``np.savez_compressed`` (``np.savez`` with ``compress=False``), readable by
    ``np.load`` alike, choosing per member: deflated at :data:`COMPRESS_LEVEL` where that
    pays (:data:`DEFLATE_BELOW`), else stored. No pickles (plain arrays only).

    A member that deflates further than our own loader accepts from an untrusted file
    (:func:`~offline_adp.artifacts.checks.check_npz`: at most ``MAX_EXPANSION`` times its
    compressed size; a constant array deflates ~1000-fold) is written again stored, so that
    every file written here loads."""
    stored: set[str] = set()
    for _ in range(3):  # the members over the limit stored; then, if the total is still over, all
        with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED, allowZip64=True, compresslevel=COMPRESS_LEVEL) as zf:
            for key, value in arrays.items():
                a = np.asanyarray(value)
                deflate = compress and key not in stored and _deflates(a)
                zf.compression = zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED
                with zf.open(f"{key}.npy", "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, a, allow_pickle=False)
            infos = zf.infolist()
        over = _too_deflated(infos, Path(path).stat().st_size)
        if not over:
            return
        stored |= over
    raise ArtifactError(f"{path}: could not be written within the loader's expansion limit")  # not reached


def _too_deflated(infos: list[zipfile.ZipInfo], size: int) -> set[str]:
    """Members the loader's expansion limits (:func:`~offline_adp.artifacts.checks.check_npz`,
    with half its margin) would refuse: those, or every deflated one when only the total is over."""
    lim = C.MAX_EXPANSION // 2
    deflated = {zi.filename[:-4] for zi in infos if zi.compress_type == zipfile.ZIP_DEFLATED}
    over = {zi.filename[:-4] for zi in infos if zi.compress_type == zipfile.ZIP_DEFLATED
            and zi.file_size > lim * max(zi.compress_size, 1) + 4096}
    if not over and sum(zi.file_size for zi in infos) > lim * max(size, 1) + (1 << 20):
        over = deflated
    return over


def _deflates(a: np.ndarray) -> bool:
    head = np.ascontiguousarray(a.reshape(-1)[:max(SAMPLE_BYTES // max(a.itemsize, 1), 1)]).tobytes()
    return len(head) < 1024 or len(zlib.compress(head, COMPRESS_LEVEL)) <= DEFLATE_BELOW * len(head)


#: The files of a model directory whose sha256 a run records (``run.json`` ``model_sha256``).
HASHED = ("q.json", "q.npz", "policy.json", "policy.npz")


def model_hashes(model_dir: str | PathLike[str]) -> dict[str, str]:
    """sha256 of each artifact file in ``model_dir`` (those of :data:`HASHED` present), for
    ``run.json``: loading checks them (:func:`check_recorded_hashes`)."""
    from offline_adp.data.files import sha256_file

    d = Path(model_dir)
    return {n: sha256_file(d / n) for n in HASHED if (d / n).is_file()}


def check_recorded_hashes(model_dir: Path, files: tuple[Path, ...]) -> None:
    """When the run holding ``model_dir`` recorded its model's hashes (``run.json``
    ``model_sha256``), each of ``files`` must still have the recorded sha256: a model file
    changed after its fit (a flipped byte in a leaf table) is refused, naming the file."""
    run_json = model_dir.parent / "run.json"
    if model_dir.name != "model" or not run_json.is_file():
        return
    from offline_adp.data.files import read_json_file, sha256_file

    recorded = read_json_file(run_json).get("model_sha256")
    if not isinstance(recorded, dict):
        return  # a run written before hashes were recorded
    extra = [n for n in HASHED if (model_dir / n).exists() and n not in recorded]
    if extra:  # e.g. a policy.json dropped next to a fitted Q: loading would prefer it
        raise ArtifactError(f"{model_dir / extra[0]}: not among the model files {run_json} recorded when the fit wrote "
                            "them (the model directory was changed after the fit); remove it or fit again")
    for f in files:
        want = recorded.get(f.name)
        if isinstance(want, str) and (not f.is_file() or sha256_file(f) != want):
            raise ArtifactError(f"{f}: its sha256 differs from the one {run_json} recorded when the fit wrote it (or "
                                "it is missing): the file was changed after the fit; restore it or fit again")


def _read(directory: str | PathLike[str], stem: str, key: str, build: Any, what: str) -> tuple[Any, dict[str, Any]]:
    """Read what :func:`_write` wrote (arrays without pickle, every member checked before
    use, see :mod:`offline_adp.artifacts.checks`); warns on other versions."""
    d = Path(directory)
    jpath, npath = d / f"{stem}.json", d / f"{stem}.npz"
    check_recorded_hashes(d, (jpath, npath))
    try:
        if jpath.stat().st_size > 1 << 30:
            raise ArtifactError(f"{jpath}: {jpath.stat().st_size} bytes is too large for an artifact description")
        spec = json.loads(jpath.read_bytes().decode("utf-8"))
        C.check_node_budget(C.check_npz(npath), npath.stat().st_size, str(npath))
        arrays = np.load(npath, allow_pickle=False)
    except FileNotFoundError as exc:
        raise ArtifactError(f"{d}: no saved {what} ({exc.filename} missing)") from exc
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise ArtifactError(f"{jpath}: unreadable {what} description ({type(exc).__name__}: {exc})") from None
    except C.ZIP_ERRORS as exc:
        raise ArtifactError(f"{npath}: unreadable {what} arrays ({exc})") from None
    if not isinstance(spec, dict) or key not in spec:
        raise ArtifactError(f"{jpath}: no {key!r} entry (not a saved {what})")
    fmt = spec.get("artifact_version", "1")
    if fmt not in READABLE_VERSIONS:
        raise ArtifactError(f"{jpath}: artifact format {fmt!r}, this offline_adp {__version__} reads formats "
                            f"{', '.join(READABLE_VERSIONS)}: written by a newer version? (upgrade "
                            "offline_adp to read it)")
    vs = spec.get("versions", {})
    now = versions()
    diff = {k: (v, now.get(k)) for k, v in vs.items() if now.get(k) != v} if isinstance(vs, dict) else {}
    if diff:
        warnings.warn(f"{d}: written with other versions {diff} (saved, current)", FormatVersionWarning, stacklevel=3)
    where = f"{jpath.parent / stem}.{{json,npz}}"
    with arrays:
        try:
            return build(spec[key], arrays, where), spec
        except (ArtifactError, FormatVersionWarning):
            raise
        except (*C.ZIP_ERRORS, IndexError, AttributeError, RecursionError, MemoryError) as exc:
            raise ArtifactError(f"{where}: malformed {what} ({type(exc).__name__}: {exc})") from None

