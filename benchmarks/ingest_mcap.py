"""MCAP ingestion speed and memory vs the raw `mcap` library decoding the same topics.

Logs come from `simulate path_tracking` (vehicle layout: odometry 50 Hz, tracking state
and steering command 10 Hz, episode events), as JSON and as ROS 2 CDR, at two sizes.
Each measurement runs in a fresh subprocess so peak RSS is its own. "ours/raw" compares
wall-clock rates, "CPU ours/raw" the rates per CPU second of each process (steadier on a
shared machine). "max buffered msgs"
is the most messages our streaming assembler held at once (bounded by the reorder
window, not the file).

    python benchmarks/ingest_mcap.py [--episodes 75 300]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

SPEC = Path(__file__).resolve().parents[1] / "data" / "specs" / "path_tracking_mcap.toml"
CHILD = textwrap.dedent(
    """
    import json, resource, sys, time
    path, mode, spec = sys.argv[1], sys.argv[2], sys.argv[3]
    topics = ["/planning/tracking_state", "/vehicle/odometry", "/control/steering_cmd", "/episode/event"]
    t0, c0 = time.perf_counter(), time.process_time()
    buffered = None
    if mode == "raw":
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory
        from offline_adp.ingest.mcap import JsonDecoderFactory
        n = 0
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[JsonDecoderFactory(), DecoderFactory()])
            for _ in reader.iter_decoded_messages(topics=topics):
                n += 1
    else:
        from offline_adp.ingest.mcap import ingest_mcap
        ds, s = ingest_mcap([path], spec)
        n = sum(s["files"][0]["messages_used"].values())
        buffered = s["max_buffered_messages"]
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(json.dumps({"messages": n, "wall": wall, "cpu": cpu, "buffered": buffered,
                      "rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
    """
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, nargs="+", default=[75, 300])
    args = ap.parse_args()
    from offline_adp.simulate import simulate
    from offline_adp.simulate.mcap_writer import write_mcap

    print(f"{'encoding':<9} {'episodes':>8} {'MB':>6} {'messages':>9} {'raw msg/s':>10} {'ours msg/s':>10} "
          f"{'ours/raw':>8} "
          f"{'CPU ours/raw':>12} {'raw RSS MiB':>11} {'ours RSS MiB':>12} {'max buffered msgs':>17}")
    with tempfile.TemporaryDirectory() as d:
        for n_ep in args.episodes:
            ds = simulate("path_tracking", n_ep, 0, seed=0, horizon=200)
            for enc in ("json", "ros2"):
                (f,) = write_mcap(ds, Path(d) / f"{enc}{n_ep}", encoding=enc)
                res = {}
                for mode in ("raw", "ours"):
                    out = subprocess.run([sys.executable, "-c", CHILD, str(f), mode, str(SPEC)], check=True,
                                         capture_output=True, text=True)
                    res[mode] = json.loads(out.stdout.strip().splitlines()[-1])
                r, o = res["raw"], res["ours"]
                print(f"{enc:<9} {n_ep:>8} {f.stat().st_size / 1e6:>6.1f} {r['messages']:>9} "
                      f"{r['messages'] / r['wall']:>10,.0f} "
                      f"{o['messages'] / o['wall']:>10,.0f} "
                      f"{(o['messages'] / o['wall']) / (r['messages'] / r['wall']):>8.2f} "
                      f"{(o['messages'] / o['cpu']) / (r['messages'] / r['cpu']):>12.2f} "
                      f"{r['rss_mib']:>11.0f} {o['rss_mib']:>12.0f} {o['buffered']:>17}", flush=True)


if __name__ == "__main__":
    main()
