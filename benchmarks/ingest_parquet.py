"""Benchmark: ingest a 1M-transition Parquet table end to end (read, map, sort check,
doctor, atomic write), in a fresh subprocess per size so peak RSS is that run's own.

Reports rows/s, peak RSS, the RSS above the interpreter's post-import baseline, and the
Arrow size of the ingested table. Targets (issue 2): >= 1M rows/s end to end, peak RSS
< 3x the Arrow size.

    python benchmarks/ingest_parquet.py [--rows 1000000] [--episode-length 200]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

SPEC = """
kind = "transitions"
[episode]
id = "episode"
step = "step"
time = "timestamp_ns"
[observations]
columns = ["x0", "x1", "x2", "x3"]
next_columns = ["nx0", "nx1", "nx2", "nx3"]
[action]
column = "command"
values = [-1.0, 0.0, 1.0]
[cost]
column = "cost"
[end]
terminated = "terminated"
truncated = "truncated"
[source]
column = "source"
[propensity]
column = "behavior_prob"
"""


def make_table(path: Path, rows: int, ep_len: int) -> None:
    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    rng = np.random.default_rng(0)
    n_ep = rows // ep_len
    n = n_ep * ep_len
    ep = np.repeat(np.arange(n_ep), ep_len)
    step = np.tile(np.arange(ep_len), n_ep)
    walk = rng.normal(size=(n + n_ep, 4)).cumsum(axis=0)  # one extra state per episode
    idx = np.arange(n) + ep  # obs row i, next obs row i + 1 within the episode's block
    last = step == ep_len - 1
    table = pa.table(
        {
            "episode": pa.array(np.char.add("ep-", np.char.zfill(ep.astype(str), 7))),
            "step": step.astype(np.int32),
            "timestamp_ns": (1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 100_000_000),
            **{f"x{j}": walk[idx, j] for j in range(4)},
            "command": rng.integers(-1, 2, n).astype(np.float64),
            "cost": rng.random(n),
            **{f"nx{j}": walk[idx + 1, j] for j in range(4)},
            "terminated": np.zeros(n, bool),
            "truncated": last,
            "source": pa.array(np.where(ep % 2 == 0, "demonstration", "exploration")),
            "behavior_prob": np.full(n, 1 / 3),
        }
    )
    pq.write_table(table, path, compression="zstd")


CHILD = textwrap.dedent(
    """
    import json, resource, sys, time
    from pathlib import Path
    import psutil
    import offline_adp.ingest.parquet as ip
    base = psutil.Process().memory_info().rss
    t0, c0 = time.perf_counter(), time.process_time()
    res = ip.ingest_parquet([sys.argv[1]], sys.argv[2], sys.argv[3], overwrite=True)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(json.dumps({"rows": len(res.dataset), "wall_s": wall, "cpu_s": cpu, "peak_rss": peak,
                      "baseline_rss": base, "arrow_bytes": res.dataset.table.nbytes, "ok": res.report.ok}))
    """
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=int, nargs="+", default=[100_000, 1_000_000])
    ap.add_argument("--episode-length", type=int, default=200)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        (d / "spec.toml").write_text(SPEC)
        print(f"{'rows':>9} {'wall s':>7} {'rows/s':>11} {'peak RSS MiB':>13} {'above base MiB':>15} {'Arrow MiB':>10} {'peak/Arrow':>10} {'(above base)/Arrow':>19}")
        for rows in args.rows:
            src = d / f"t{rows}.parquet"
            make_table(src, rows, args.episode_length)
            out = subprocess.run([sys.executable, "-c", CHILD, str(src), str(d / "spec.toml"), str(d / f"ds{rows}")],
                                 check=True, capture_output=True, text=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            mib = 1 << 20
            print(
                f"{r['rows']:>9} {r['wall_s']:>7.2f} {r['rows'] / r['wall_s']:>11,.0f} {r['peak_rss'] / mib:>13.0f} "
                f"{(r['peak_rss'] - r['baseline_rss']) / mib:>15.0f} {r['arrow_bytes'] / mib:>10.0f} "
                f"{r['peak_rss'] / r['arrow_bytes']:>10.2f} {(r['peak_rss'] - r['baseline_rss']) / r['arrow_bytes']:>19.2f}"
            )
            assert r["ok"]


if __name__ == "__main__":
    main()
