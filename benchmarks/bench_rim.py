"""The rim's cost (ilt.isf.fine.rim, docs/fullres.md "The rim"), once per decompose.

    python benchmarks/bench_rim.py [--size 4000x3000] [--cells 4096] [--repeats 3]

Cells: the Voronoi regions of ``--cells`` jittered grid points, kept inside an irregular
lit region (an ellipse less two holes and a notch, ~60% of the frame), as a scan of a
12 Mpx camera gives. Times :func:`ilt.isf.fine.rim` (two chamfer distance transforms and
a k-d tree over the cells' border pixels) against the baseline it replaced in design, an
exact Euclidean distance transform with indices (``scipy.ndimage.distance_transform_edt``)
that finds the same rim and nearest pixels, back to back in this process. Prints medians,
the median of the per-repeat ratios, the rim's size, and the share of rim pixels whose
nearest inside pixel is at the same distance both ways (ties may pick another pixel).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from scipy.ndimage import distance_transform_cdt, distance_transform_edt
from scipy.spatial import cKDTree

from ilt.isf.fine import RIM_PX, CellGeometry, rim


def labels_of(width: int, height: int, cells: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    side = int(np.sqrt(cells))
    gx, gy = np.meshgrid((np.arange(side) + 0.5) * width / side, (np.arange(side) + 0.5) * height / side)
    points = np.column_stack([gx.ravel(), gy.ravel()]) + rng.uniform(-0.3, 0.3, (side * side, 2)) * width / side
    y, x = np.mgrid[:height, :width]
    lit = ((x - width / 2) / (0.45 * width)) ** 2 + ((y - height / 2) / (0.45 * height)) ** 2 < 1
    for cx, cy, r in ((0.35, 0.4, 0.08), (0.65, 0.6, 0.05)):
        lit &= (x - cx * width) ** 2 + (y - cy * height) ** 2 > (r * width) ** 2
    lit &= ~((x > 0.8 * width) & (np.abs(y - height / 2) < 0.03 * height))
    _, nearest = cKDTree(points).query(np.column_stack([x[lit], y[lit]]))
    labels = -np.ones((height, width), np.int64)
    labels[lit] = nearest
    return labels


def exact(geometry: CellGeometry) -> tuple[np.ndarray, np.ndarray]:
    """The rim and each pixel's nearest inside pixel (flat index) by the exact transform."""
    covered = np.zeros(geometry.shape, bool)
    covered.flat[geometry.inside] = True
    _, (iy, ix) = distance_transform_edt(~covered, return_indices=True)
    chess = distance_transform_cdt(~covered, metric="chessboard")   # the rim's extent is chessboard
    pixels = np.flatnonzero((chess > 0) & (chess <= RIM_PX))
    return pixels, (iy.ravel() * geometry.shape[1] + ix.ravel())[pixels]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", default="4000x3000", help="WxH (default 4000x3000, 12 Mpx)")
    parser.add_argument("--cells", type=int, default=4096)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    width, height = map(int, args.size.split("x"))
    labels = labels_of(width, height, args.cells)
    geometry = CellGeometry.from_labels(labels, int(labels.max()) + 1)
    ours, base, ratios = [], [], []
    for _ in range(args.repeats):
        t = time.perf_counter()
        pixels, nearest = rim(geometry)
        ours.append(time.perf_counter() - t)
        t = time.perf_counter()
        e_pixels, e_nearest = exact(geometry)
        base.append(time.perf_counter() - t)
        ratios.append(ours[-1] / base[-1])
    assert np.array_equal(pixels, e_pixels)
    yx = lambda flat: np.column_stack(np.divmod(flat, width)).astype(np.float64)
    d_ours = np.linalg.norm(yx(pixels) - yx(geometry.inside[nearest]), axis=1)
    d_exact = np.linalg.norm(yx(pixels) - yx(e_nearest), axis=1)
    print(f"frame {width} x {height}, {geometry.m} cells over {geometry.inside.size / labels.size:.2f} of it; "
          f"rim {pixels.size} px ({pixels.size / labels.size:.3f})")
    print(f"rim(): median {statistics.median(ours):.3f} s; exact EDT with indices: median "
          f"{statistics.median(base):.3f} s; ratio (median of repeats) {statistics.median(ratios):.2f}")
    print(f"nearest at the least distance: {np.mean(np.isclose(d_ours, d_exact)):.4f} of the rim")


if __name__ == "__main__":
    main()
