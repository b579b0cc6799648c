"""Benchmark of the per-beam stages on a Dask cluster (ilt.cluster) against ilt's own
process pool, on this machine.

    python benchmarks/bench_cluster.py            # m = 1024 beams
    python benchmarks/bench_cluster.py --quick    # m = 128 / 256, a minute or so

merge: a capture of m beams (the paper's 11-frame bracket of simulated DNGs of
--width x --height; 16 distinct brackets, the other beams hard links to them, so the
page cache holds them and both runs read from memory) merged by a process pool of
--workers processes and by a LocalCluster of as many single-threaded worker processes
(started once, before the timing, as a running cluster would be: its start-up is
printed apart). centroids + build-isf: m synthetic beam frames (benchmarks/bench_isf.py)
through ``centroids_and_isf`` (every EXR decoded once), the same two ways. The two
runs alternate in every repeat, so load from other users of the machine falls on both
alike; medians of --repeat. Prints the times, the cluster / pool ratios (goal <= 1.15)
and the per-beam costs (worker-seconds per beam: wall x workers / m) that
docs/cluster.md's model uses.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_hdr import make_capture  # noqa: E402  (the same synthetic capture)


def alternate(runs: dict, repeat: int) -> dict:
    """{name: [wall s]}: every run once per repeat, in turn."""
    times = {name: [] for name in runs}
    for _ in range(repeat):
        for name, fn in runs.items():
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    return times


def report(title: str, m: int, workers: int, times: dict) -> dict:
    pool, cluster = statistics.median(times["pool"]), statistics.median(times["cluster"])
    ratio = statistics.median(c / p for c, p in zip(times["cluster"], times["pool"]))
    print(f"{title}: m = {m}, {workers} workers, medians of {len(times['pool'])}")
    print(f"  process pool   {pool:8.2f} s   {1e3 * pool * workers / m:7.2f} worker-ms/beam")
    print(f"  LocalCluster   {cluster:8.2f} s   {1e3 * cluster * workers / m:7.2f} worker-ms/beam")
    print(f"  cluster / pool {ratio:8.2f} x   (goal <= 1.15)")
    print("  all (s): " + "; ".join(f"{k}: " + ", ".join(f"{v:.2f}" for v in vs) for k, vs in times.items()))
    return {"pool": pool, "cluster": cluster, "ratio": ratio}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="m = 128 merge, 256 centroids + build-isf")
    ap.add_argument("--beams", type=int, default=None, help="m (default 1024; --quick: 128 / 256)")
    ap.add_argument("--width", type=int, default=320, help="sensor width of the merge's DNGs")
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--frame-width", type=int, default=320, help="frame width of centroids + build-isf")
    ap.add_argument("--frame-height", type=int, default=240)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only", choices=["merge", "isf"], default=None)
    args = ap.parse_args()
    m_merge = args.beams or (128 if args.quick else 1024)
    m_isf = args.beams or (256 if args.quick else 1024)

    from bench_isf import synthetic_frames

    from ilt.build_isf import centroids_and_isf
    from ilt.cluster import executor_for
    from ilt.hdr.stages import MergeOptions, merge_capture

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        if args.only != "isf":
            make_capture(tmp / "cap", m_merge, args.width, args.height, 16, np.random.default_rng(0))
        if args.only != "merge":
            synthetic_frames(tmp / "frames", m_isf, args.frame_width, args.frame_height)
        print(f"data written in {time.perf_counter() - t:.1f} s", file=sys.stderr)
        t = time.perf_counter()
        with executor_for("local", args.workers) as ex:
            print(f"LocalCluster of {args.workers} workers started in {time.perf_counter() - t:.1f} s")

            def merge(executor):
                shutil.rmtree(tmp / "hdr", ignore_errors=True)
                merge_capture(tmp / "cap", tmp / "hdr", MergeOptions(), executor=executor, workers=args.workers)

            def isf(executor):
                centroids_and_isf(tmp / "frames", tmp / "spots", tmp / "isf", executor=executor,
                                  workers=args.workers, force=True)

            for key, name, fn, m in (("merge", "merge", merge, m_merge), ("isf", "centroids + build-isf", isf, m_isf)):
                if args.only and key != args.only:
                    continue
                fn(ex)   # warm: the page cache, the workers' imports and operator caches
                times = alternate({"pool": lambda fn=fn: fn(None), "cluster": lambda fn=fn: fn(ex)}, args.repeat)
                report(name, m, args.workers, times)


if __name__ == "__main__":
    main()
