"""What cells ended at barriers by their lines of sight cost (issue 21, :mod:`ilt.isf.folds`).

    python benchmarks/bench_fold_lines.py [--width 4000 --height 3000] [--beams 4096] [--repeats 3]

A barrier that stops short of the light's edge encloses nothing, so :func:`ilt.isf.folds.fold_cells`
also gives each pixel whose straight line to its spot crosses a long barrier to a spot it
sees (``_line_of_sight``), after carrying each long barrier's ends on along its valley's
floor (``_follow``, in :func:`ilt.isf.folds.valley_barriers`). This times ``fold_cells`` on
a full-resolution frame (a 12 Mpx sensor by default) with ``--beams`` spots on a jittered
grid and nine long slanted barriers, six that end 300 px short of the frame's edges and
three that cross them, with and without the line-of-sight pass, back to back in every
repeat; medians and the ratio. (The region pass alone is what build-isf did before; the
far light's pass over the frames, which both share, is bench_isf.py folds.)
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def frame(width: int, height: int, beams: int, rng):
    from ilt.isf.cells import voronoi_cells

    side = max(2, int(round(np.sqrt(beams * width / height))))
    rows = max(2, int(round(beams / side)))
    gx, gy = np.meshgrid(np.linspace(0.01 * width, 0.99 * width, side), np.linspace(0.01 * height, 0.99 * height, rows))
    centroids = np.column_stack([gx.ravel(), gy.ravel()]) + rng.normal(0, 1.0, (side * rows, 2))
    labels = voronoi_cells(centroids, (height, width))
    barriers = np.zeros((height, width), bool)
    for k in range(6):                                  # slanted, 300 px short of the top and bottom
        r = np.arange(300, height - 300)
        barriers[r, (0.08 * width + 0.14 * width * k + 0.3 * (r - 300)).astype(int) % width] = True
    for k in range(3):                                  # across the frame
        c = np.arange(0, width)
        barriers[(0.2 * height + 0.27 * height * k + 0.1 * c).astype(int) % height, c] = True
    return labels, centroids, barriers


def main() -> None:
    from ilt.isf import folds

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--width", type=int, default=4000)
    ap.add_argument("--height", type=int, default=3000)
    ap.add_argument("--beams", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    labels, centroids, barriers = frame(args.width, args.height, args.beams, np.random.default_rng(0))
    spacing = folds.spacing_of(centroids)
    sight = folds._line_of_sight
    times = {"regions": [], "regions + lines of sight": []}
    for _ in range(args.repeats):
        folds._line_of_sight = lambda *a, **k: 0
        start = time.perf_counter()
        _, plain = folds.fold_cells(labels, centroids, barriers, spacing)
        times["regions"].append(time.perf_counter() - start)
        folds._line_of_sight = sight
        start = time.perf_counter()
        _, record = folds.fold_cells(labels, centroids, barriers, spacing)
        times["regions + lines of sight"].append(time.perf_counter() - start)
    print(f"{args.width} x {args.height} px, {len(centroids)} spots ({spacing:.1f} px apart), "
          f"{record['barrier_pixels']} barrier pixels; {record['blocked_pixels']} pixels blocked from their spot, "
          f"{record['moved_pixels']} moved in all ({plain['moved_pixels']} by the regions alone)")
    for name, t in times.items():
        print(f"  fold_cells, {name:26s} median {statistics.median(t):6.2f} s over {args.repeats}")
    print(f"  ratio {statistics.median(times['regions + lines of sight']) / statistics.median(times['regions']):.1f}x")


if __name__ == "__main__":
    main()
