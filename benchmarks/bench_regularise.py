"""What denoising T costs a decompose (ilt/transport/regularise.py, on by default when T's noise is known).

    python benchmarks/bench_regularise.py [--sizes 1024,2048,4096] [--repeats 3]

``ilt decompose`` filters T along the cells' neighbours (``regularise_isf(..., pairs=)``)
before it factorises T. This times, on a synthetic T of each size (m beams on a square
grid of Voronoi cells over a frame, a smooth indirect part falling with distance, noise
1e-3 a unit-column entry, the directly lit entry 1):

- the filter at the fixed width 0.82 (edge weights along pixels and beams, the
  diffusion's passes, the discrepancy check), given the cells' pairs;
- the filter at the chosen width, what ``ilt decompose`` runs (``width=None``: every
  width of ``CHOICES`` one from the next, for T and a noise probe, and the risk of each);
- finding the pairs from a cells image (``ilt.isf.fine.adjacent_cells``), 640 x 480 px;
- the LU factorisation of T (scipy, float64), which every decompose with the dense
  solver does once: the baseline, timed in the same process;

alternating, and prints the medians and the ratio of the filter to the factorisation.
The solve of the photo's bounces is O(m^2) per bounce on top of the factorisation.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def synthetic(m: int, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T, pairs, labels): m spots on a grid over a 480 x 640 frame, their Voronoi cells,
    and a unit-column T whose indirect part falls smoothly with the spots' distance."""
    from scipy.spatial import cKDTree

    from ilt.isf.fine import adjacent_cells

    side = int(np.ceil(np.sqrt(m * 4 / 3)))
    xs, ys = np.meshgrid(np.linspace(8, 632, side), np.linspace(8, 472, int(np.ceil(m / side))))
    spots = np.stack([xs.ravel(), ys.ravel()], axis=1)[:m]
    yy, xx = np.mgrid[0:480, 0:640]
    labels = cKDTree(spots).query(np.stack([xx.ravel(), yy.ravel()], axis=1))[1].reshape(480, 640)
    d = np.linalg.norm(spots[:, None] - spots[None], axis=2)
    T = 0.3 / m * np.exp(-d / 200.0) + 1e-3 * rng.normal(size=(m, m))
    np.fill_diagonal(T, 1.0)
    return T, adjacent_cells(labels), labels


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="1024,2048,4096")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    import scipy.linalg

    from ilt.isf.fine import adjacent_cells
    from ilt.transport.regularise import regularise_isf

    rng = np.random.default_rng(0)
    print("| m | pairs | filter at 0.82 (s) | filter, width chosen (s) | pairs from the cells image (s) | "
          "LU of T (s) | filter / LU | chosen / LU | chosen width |")
    print("|---|---|---|---|---|---|---|---|---|")
    for m in map(int, args.sizes.split(",")):
        T, pairs, labels = synthetic(m, rng)
        times = {"filter": [], "chosen": [], "pairs": [], "lu": []}
        for _ in range(args.repeats):
            start = time.perf_counter()
            regularise_isf(T, None, 1e-3, pairs=pairs)
            times["filter"].append(time.perf_counter() - start)
            start = time.perf_counter()
            _, reg = regularise_isf(T, None, 1e-3, width=None, pairs=pairs)
            times["chosen"].append(time.perf_counter() - start)
            start = time.perf_counter()
            adjacent_cells(labels)
            times["pairs"].append(time.perf_counter() - start)
            start = time.perf_counter()
            scipy.linalg.lu_factor(T, check_finite=False)
            times["lu"].append(time.perf_counter() - start)
        med = {k: float(np.median(v)) for k, v in times.items()}
        print(f"| {m} | {len(pairs)} | {med['filter']:.3f} | {med['chosen']:.3f} | {med['pairs']:.3f} | "
              f"{med['lu']:.3f} | {med['filter'] / med['lu']:.2f}x | {med['chosen'] / med['lu']:.2f}x | "
              f"{reg.width:g} |", flush=True)


if __name__ == "__main__":
    main()
