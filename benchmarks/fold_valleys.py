"""Where the far beams' light has valleys: a picture of the fold test in two dimensions (issue 21).

    python benchmarks/fold_valleys.py --scan DIR [--smooth 3] -o PNG

``DIR`` is one scan of ``benchmarks/noisy_sweep.py --scratch`` (its ``hdr/`` beam frames and
``spots/spots.csv``), e.g. the noisy box at 108 beams. For every pixel, the light of the
beams farther than one spot spacing from it (the near beams' own indirect light peaks about
their spots and hides the rest), smoothed by a Gaussian of ``--smooth`` px, and its
valley-ness: the larger eigenvalue of its Hessian (positive across a valley). At a concave
fold a facet lights the facet it faces the less, the nearer the fold: the far light has a
valley there (benchmarks/bench_fold_cells.py measures it on flatland, and what cells that end
there are worth). Draws the summed frames (log), the far light and the valley-ness.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np


def far_light(scan: Path) -> tuple[np.ndarray, np.ndarray, float]:
    """(sum of the frames, the far beams' light, the spot spacing) of a scan directory."""
    from scipy.spatial import cKDTree

    from ilt.io.exr import read_exr

    with open(scan / "spots" / "spots.csv") as f:
        rows = list(csv.DictReader(f))
    xy = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    spacing = float(np.median(cKDTree(xy).query(xy, k=2)[0][:, 1]))
    total = far = None
    for r, (x, y) in zip(rows, xy):
        frame = read_exr(scan / "hdr" / f"beam-{int(r['beam']):05d}.exr")[0][..., 0].astype(np.float64)
        if total is None:
            total, far = np.zeros(frame.shape), np.zeros(frame.shape)
            rows_, cols_ = np.mgrid[:frame.shape[0], :frame.shape[1]]
        total += frame
        far += np.where(np.hypot(cols_ - x, rows_ - y) > spacing, frame, 0.0)
    return total, far, spacing


def valleyness(image: np.ndarray) -> np.ndarray:
    """The larger eigenvalue of the Hessian of ``image`` at every pixel."""
    gy, gx = np.gradient(image)
    gyy, gyx = np.gradient(gy)
    _, gxx = np.gradient(gx)
    return 0.5 * (gxx + gyy) + np.sqrt(0.25 * (gxx - gyy) ** 2 + gyx**2)


def main() -> None:
    from scipy.ndimage import gaussian_filter

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scan", type=Path, required=True)
    ap.add_argument("--smooth", type=float, default=3.0, help="Gaussian sigma, px (default 3)")
    ap.add_argument("-o", "--output", type=Path, required=True)
    args = ap.parse_args()
    total, far, spacing = far_light(args.scan)
    smooth = gaussian_filter(far, args.smooth)
    valley = valleyness(smooth)
    lit = smooth > 0.2 * smooth.max()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 5))
    ax[0].imshow(np.log10(np.maximum(total, 1e-3 * total.max())), cmap="gray")
    ax[0].set_title("the frames' sum (log)")
    ax[1].imshow(smooth, cmap="gray")
    ax[1].set_title(f"light of the beams farther than {spacing:.1f} px")
    ax[2].imshow(np.clip(valley / np.quantile(valley[lit], 0.99), 0, 1), cmap="magma")
    ax[2].set_title(f"valley-ness (Hessian, after a {args.smooth:g} px Gaussian)")
    for a in ax:
        a.set_xticks([])
        a.set_yticks([])
    fig.savefig(args.output, dpi=80, bbox_inches="tight")
    print(args.output)


if __name__ == "__main__":
    main()
