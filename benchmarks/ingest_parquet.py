"""Benchmark: ingest a 1M-transition Parquet table end to end (read, map, sort check,
doctor, atomic write), in a fresh subprocess per size so peak RSS is that run's own.

Reports, per size, the CPU seconds of the ingestion (user + system of every thread of
the child process, imports excluded; the median run by CPU seconds), rows per CPU-second,
the medians of user and of system seconds on their own (system time, mostly the kernel
zeroing fresh pages, varies most between identical runs), wall seconds, and peak memory:
the child's peak RSS (``VmHWM``: not ``ru_maxrss``, which Linux carries over ``exec`` from
the parent's image) above its post-import baseline,
relative to the Arrow size of the ingested table. Targets (issue #33): >= 2M rows per
CPU-second, peak memory above baseline < 2x the Arrow table.

``--compare DIR`` also runs the same inputs with the ``offline_adp`` package found in
``DIR`` (e.g. ``git archive <commit> offline_adp | tar -x -C DIR``), alternating with the
current code, so before and after come from one run on the same machine load.

    python benchmarks/ingest_parquet.py [--rows 100000 1000000] [--episode-length 200]
                                        [--repeat 1] [--compare DIR]
"""

from __future__ import annotations

import argparse
import json
import os
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
    ru = resource.getrusage(resource.RUSAGE_SELF)
    t0, u0, s0 = time.perf_counter(), ru.ru_utime, ru.ru_stime
    res = ip.ingest_parquet([sys.argv[1]], sys.argv[2], sys.argv[3], overwrite=True)
    wall = time.perf_counter() - t0
    # VmHWM: this process's own peak. Not ru_maxrss, which Linux carries over exec from
    # the forked parent's image (a parent holding the generated table inflated it by ~30 MiB)
    peak = next(int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith("VmHWM:"))
    ru = resource.getrusage(resource.RUSAGE_SELF)
    user, sys_ = ru.ru_utime - u0, ru.ru_stime - s0  # every thread of this process
    print(json.dumps({"module": ip.__file__, "rows": len(res.dataset), "wall_s": wall, "cpu_s": user + sys_,
                      "user_s": user, "sys_s": sys_, "peak_rss": peak,
                      "baseline_rss": base, "arrow_bytes": res.dataset.table.nbytes, "ok": res.report.ok}))
    """
)


def run_child(src: Path, spec: Path, out: Path, pythonpath: str) -> dict:
    env = dict(os.environ, PYTHONPATH=pythonpath)
    res = subprocess.run([sys.executable, "-c", CHILD, str(src), str(spec), str(out)],  # cwd: no package there
                         check=True, capture_output=True, text=True, env=env, cwd=src.parent)
    r = json.loads(res.stdout.strip().splitlines()[-1])
    assert r["ok"]
    return r


def med(runs: list[dict], key: str) -> float:
    """The median of ``key`` over the runs (user and system seconds: each its own median)."""
    return sorted(r[key] for r in runs)[len(runs) // 2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=int, nargs="+", default=[100_000, 1_000_000])
    ap.add_argument("--episode-length", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=1, help="runs per size and code version (the median is shown)")
    ap.add_argument("--compare", metavar="DIR", help="also run the offline_adp package in DIR (the 'before')")
    args = ap.parse_args()
    here = str(Path(__file__).resolve().parents[1])
    versions = {"current": here}
    if args.compare:
        versions = {"before": str(Path(args.compare).resolve()), "after": here}
    mib = 1 << 20
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        (d / "spec.toml").write_text(SPEC)
        print(f"{'code':>7} {'rows':>9} {'CPU s':>6} {'rows/CPU-s':>11} {'user s':>6} {'sys s':>6} {'wall s':>6} "
              f"{'peak RSS MiB':>12} "
              f"{'above base MiB':>14} {'Arrow MiB':>9} {'(peak-base)/Arrow':>17}")
        for rows in args.rows:
            src = d / f"t{rows}.parquet"
            make_table(src, rows, args.episode_length)
            runs: dict[str, list[dict]] = {k: [] for k in versions}
            for _ in range(args.repeat):
                for name, pp in versions.items():  # alternate, so both see the same load
                    runs[name].append(run_child(src, d / "spec.toml", d / f"ds{rows}", pp))
            for name, rs in runs.items():
                r = sorted(rs, key=lambda r: r["cpu_s"])[len(rs) // 2]
                above = r["peak_rss"] - r["baseline_rss"]
                print(
                    f"{name:>7} {r['rows']:>9} {r['cpu_s']:>6.2f} {r['rows'] / r['cpu_s']:>11,.0f} "
                    f"{med(rs, 'user_s'):>6.2f} {med(rs, 'sys_s'):>6.2f} {r['wall_s']:>6.2f} "
                    f"{r['peak_rss'] / mib:>12.0f} {above / mib:>14.0f} {r['arrow_bytes'] / mib:>9.0f} "
                    f"{above / r['arrow_bytes']:>17.2f}"
                )


if __name__ == "__main__":
    main()
