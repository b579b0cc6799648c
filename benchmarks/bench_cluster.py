"""Benchmark of the per-beam stages and the compressed solver on a Dask cluster
(ilt.parallel.cluster) against ilt's own process pool and threads, on this machine.

    python benchmarks/bench_cluster.py            # m = 1024 beams; compressed at m = 33075
    python benchmarks/bench_cluster.py --quick    # m = 128 / 256, compressed at 3072: a minute or so

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

compressed: the cube-corner kernel ISF of ``ilt.sim.kernel`` (m = 3 n^2 points,
``--kernel-n``; 105: m = 33075, 8.2 GiB) written block by block to a memory-mapped
``T.npy`` (in ``--kernel-dir``, kept and reused there, else a temporary directory),
compressed to the default tolerance by one process (its threads, one a core) and by
the LocalCluster's workers reading the same file, alternately; medians of
``--repeat``, the cluster / one-process ratio (goal <= 1.2: on 2 cores no speed-up is
possible, so the figure is the overhead), whether the two operators are the same bit
for bit, and the peak resident memory of this process and of each worker.
"""

from __future__ import annotations

import argparse
import resource
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
    ap.add_argument("--only", choices=["merge", "isf", "compressed"], default=None)
    ap.add_argument("--kernel-n", type=int, default=None, help="compressed: m = 3 n^2 (default 105; --quick: 32)")
    ap.add_argument("--kernel-dir", type=Path, default=None,
                    help="compressed: where the kernel's T.npy is written, and reused when there")
    args = ap.parse_args()
    m_merge = args.beams or (128 if args.quick else 1024)
    m_isf = args.beams or (256 if args.quick else 1024)

    from bench_isf import synthetic_frames

    from ilt.hdr.stages import MergeOptions, merge_capture
    from ilt.isf.build import centroids_and_isf
    from ilt.parallel.cluster import executor_for

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        if args.only != "isf":
            make_capture(tmp / "cap", m_merge, args.width, args.height, 16, np.random.default_rng(0))
        if args.only in (None, "isf"):
            synthetic_frames(tmp / "frames", m_isf, args.frame_width, args.frame_height)
        if args.only in (None, "compressed"):
            kernel = kernel_isf(args.kernel_dir or tmp, args.kernel_n or (32 if args.quick else 105))
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
            if args.only in (None, "compressed"):
                compressed_against_one_process(ex, *kernel, args.repeat)


def kernel_isf(directory: Path, n: int):
    """The kernel T (memory-mapped) of m = 3 n^2 points in ``directory``/T.npy, written
    unless it is there at that size, and the points' positions."""
    from ilt.sim.kernel import corner_kernel_isf, corner_points

    path, m = Path(directory) / "T.npy", 3 * n * n
    directory.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    try:
        T = np.load(path, mmap_mode="r")
        if T.shape != (m, m):
            raise ValueError
    except (OSError, ValueError):
        T = corner_kernel_isf(path, n)
    print(f"kernel T (m = {m}, {T.nbytes / 2**30:.1f} GiB) ready in {time.perf_counter() - t:.1f} s", file=sys.stderr)
    return T, corner_points(n)[0]


def compressed_against_one_process(ex, T, points, repeat: int) -> None:
    """compressed_operator on T by this process's threads and by the cluster, in turn."""
    from ilt.transport.compressed import compressed_operator

    m, built = T.shape[0], {}

    def build(name, executor):
        built[name] = compressed_operator(T, points=points, executor=executor)

    times = alternate({"pool": lambda: build("pool", None), "cluster": lambda: build("cluster", ex)}, repeat)
    one, cluster = statistics.median(times["pool"]), statistics.median(times["cluster"])
    ratio = statistics.median(c / p for c, p in zip(times["cluster"], times["pool"]))
    same = (np.array_equal(built["pool"].t1_unit, built["cluster"].t1_unit)
            and built["pool"].root.ranks_by_level() == built["cluster"].root.ranks_by_level())
    drift = float(np.max(np.abs(built["cluster"].t1_unit / built["pool"].t1_unit - 1)))
    workers = ex.client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
    print(f"compressed: m = {m} from a memory-mapped T.npy ({T.nbytes / 2**20:.0f} MiB), "
          f"{len(workers)} workers, medians of {repeat}")
    print(f"  one process    {one:8.2f} s   ({built['pool'].describe()})")
    print(f"  LocalCluster   {cluster:8.2f} s")
    print(f"  cluster / one  {ratio:8.2f} x   (goal <= 1.2)")
    print(f"  same operator bit for bit: {same} (largest relative difference of T1 {drift:.1e})")
    print(f"  peak resident memory: this process {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10:.0f} "
          f"MiB (T's mapped pages included); workers "
          + ", ".join(f"{v / 2**20:.0f}" for v in workers.values()) + " MiB")
    print("  all (s): " + "; ".join(f"{k}: " + ", ".join(f"{v:.2f}" for v in vs) for k, vs in times.items()))


if __name__ == "__main__":
    main()
