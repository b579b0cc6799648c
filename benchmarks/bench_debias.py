"""What raising T's noisy diagonal costs in memory and time (issue 21, ilt decompose).

    python benchmarks/bench_debias.py [--beams 4096] [--repeats 3]

When the beam frames' noise is a share of each pixel's light (a path tracer's), decompose
raises T's diagonal by its variance over itself before inverting it
(:func:`ilt.transport.regularise.diagonal_raise`). T is read memory-mapped ("never held
twice"); the first version copied it into memory (8 m^2 bytes: 1.2 GB at m = 12288), now the
raised T goes to a memory map in a scratch directory beside the operator cache, a block
of columns at a time (``ilt.decompose.stage._debiased_diagonal``). This times both on a
memory-mapped m x m T and reports the peak of memory allocated (tracemalloc: numpy's
arrays count, the page cache of a memory map does not), medians of ``--repeats``.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def measure(fn) -> tuple[float, float]:
    """(seconds, peak MB allocated) of ``fn()``."""
    tracemalloc.start()
    t0 = time.perf_counter()
    fn()
    seconds = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    return seconds, peak


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--beams", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    from ilt.decompose.stage import _debiased_diagonal
    from ilt.transport.regularise import diagonal_raise, raise_diagonal

    m = args.beams
    with tempfile.TemporaryDirectory(prefix="bench-debias-") as tmp:
        tmp = Path(tmp)
        T = np.lib.format.open_memmap(tmp / "T.npy", mode="w+", dtype=np.float64, shape=(m, m))
        rng = np.random.default_rng(0)
        for j0 in range(0, m, 1024):
            T[:, j0:j0 + 1024] = 1e-3 * rng.random((m, min(1024, m - j0)))
        T[np.diag_indices(m)] = 1.0
        T.flush()
        variance = np.zeros((m, m), np.float32)
        variance[np.diag_indices(m)] = 0.04
        np.save(tmp / "T_var.npy", variance)
        del T, variance
        mapped = np.load(tmp / "T.npy", mmap_mode="r")
        T_var = np.load(tmp / "T_var.npy", mmap_mode="r")
        cache = tmp / "cache"
        cache.mkdir()

        def in_memory():   # the first version: a copy of T in memory
            raise_by, _ = diagonal_raise(mapped, T_var)
            return raise_diagonal(mapped, raise_by)

        def memory_map():
            with contextlib.ExitStack() as stack:
                out, _ = _debiased_diagonal(mapped, T_var, False, cache, stack)
                out.flush()

        rows = {"in memory (before)": [], "memory map (now)": []}
        for _ in range(args.repeats):
            rows["in memory (before)"].append(measure(in_memory))
            rows["memory map (now)"].append(measure(memory_map))
    print(f"m = {m}: T is {8 * m * m / 2**20:.0f} MB (float64)")
    medians = {}
    for name, runs in rows.items():
        seconds = statistics.median(r[0] for r in runs)
        peak = statistics.median(r[1] for r in runs)
        medians[name] = (seconds, peak)
        print(f"  {name:20s} {seconds:7.3f} s   peak allocated {peak:9.1f} MB")
    before, now = medians["in memory (before)"], medians["memory map (now)"]
    print(f"  now / before: time {now[0] / before[0]:.2f}x, memory {now[1] / max(before[1], 1e-9):.3f}x")


if __name__ == "__main__":
    main()
