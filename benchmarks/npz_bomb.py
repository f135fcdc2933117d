"""Memory used to refuse a decompression-bomb ``q.npz`` (issue 16).

Usage: ``python benchmarks/npz_bomb.py DIR`` writes DIR/q.npz (about 1.2 MB) whose deflated
``q.m0.value`` member expands to 1.27 GB; run it again with the same DIR to load it in a
fresh process and print the outcome and the peak RSS (getrusage). Expected here: an
ArtifactError refused from the zip and .npy headers, at the import baseline (~190 MiB);
6c9638e peaked at 1404 MiB and then raised a raw ValueError.
"""

from __future__ import annotations

import io
import resource
import sys
import warnings
import zipfile
from pathlib import Path

import numpy as np


def write_bomb(d: Path, expanded_bytes: int = 1_270_000_000) -> None:
    from offline_adp.algorithms.fqi import FittedQIteration, save_fqi
    from offline_adp.simulate import simulate

    ds = simulate("path_tracking", 4, 4, seed=1, horizon=40)
    f = FittedQIteration(n_iterations=1, regressor="extra_trees",
                         regressor_params={"n_estimators": 2, "n_jobs": 1}).fit(ds)
    save_fqi(f, d)
    with np.load(d / "q.npz") as z:
        members = {k: z[k] for k in z.files}
    n = expanded_bytes // 8
    hdr = io.BytesIO()
    np.lib.format.write_array_header_1_0(hdr, {"descr": "<f8", "fortran_order": False, "shape": (n,)})
    chunk = bytes(1 << 22)
    with zipfile.ZipFile(d / "q.npz", "w", zipfile.ZIP_DEFLATED) as zf:
        for k, v in members.items():
            if k != "q.m0.value":
                with zf.open(k + ".npy", "w") as fh:
                    np.lib.format.write_array(fh, v)
        with zf.open("q.m0.value.npy", "w", force_zip64=True) as fh:
            fh.write(hdr.getvalue())
            for _ in range(n * 8 // len(chunk)):
                fh.write(chunk)
    print("wrote", d / "q.npz", (d / "q.npz").stat().st_size, "bytes")


def load(d: Path) -> None:
    from offline_adp.artifacts import load_q

    try:
        load_q(d)
        print("loaded")
    except Exception as e:  # report whatever happens: the point is the outcome and the memory
        print(type(e).__name__, str(e)[:160])
    print("peak RSS MiB", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


if __name__ == "__main__":
    warnings.simplefilter("ignore")
    target = Path(sys.argv[1])
    if (target / "q.npz").exists():
        load(target)
    else:
        write_bomb(target)
